//! A high-dynamic-range input brought into the range the fit compares in, and the result taken
//! back to the input's.
//!
//! Why: the fit's loss is the MSE of sRGB-encoded values, and the encoding clamps to [0, 1] as a
//! display or a camera does (`evaluator`). A JPEG or PNG photo lies in that range. A linear EXR
//! (a render by another renderer, a raw developed to linear) need not: lit brightly, its yarn tops
//! are well above 1 (a red weft of the seed-2020 Mitsuba set at 1.37 on average, half the image
//! above 1). Clamped, those pixels are a flat 1: the loss sees neither the highlights nor the
//! family's true colour, and the fitted colour stops where the clamp hides the rest (that weft
//! came back at 1.09, a family-colour error of 0.28; docs/benchmarks.md, session 21).
//!
//! The whole fit on the input divided by one scale (its [`SCALE_PERCENTILE`] brightness) fixed
//! the colours but changed what the pattern search saw (a 3/1 twill of two near-identical blues
//! read as a 2/2). So the pattern, the shapes and the appearance are fitted as the input shows
//! on a display, and a last stage fits the colours again against the divided target at the
//! divided exposure ([`DisplayRange::evaluator`]); the scale then goes back into the fitted scene's
//! exposure ([`DisplayRange::result_to_input`]), so that the parameter file re-renders the input's
//! own values and every image the fit returns is in the input's units. An input within [0, 1]
//! (every photo) is fitted exactly as before.

use super::evaluator::Evaluator;
use super::FitResult;
use crate::image_io::Image;
use crate::scene::Scene;

/// Percentile of the pixels' brightest channel that the scale brings to 1: the highlights of the
/// few brightest pixels (specular glints) may still clamp, the yarns' tops do not.
pub(crate) const SCALE_PERCENTILE: f64 = 0.995;

/// The scale of an input: its values divided by `scale` lie (up to [`SCALE_PERCENTILE`]) in the
/// fit's range.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct DisplayRange {
    /// At least 1; exactly 1 where the input needs no scaling.
    pub scale: f32,
}

impl DisplayRange {
    /// No scaling.
    pub(crate) const IDENTITY: Self = Self { scale: 1.0 };

    /// The scale of `input`: its [`SCALE_PERCENTILE`] of the per-pixel largest channel when that is
    /// above 1, else 1. Non-finite values are not expected here (`check_input` refuses them) and
    /// are skipped.
    pub(crate) fn of(input: &Image) -> Self {
        let mut brightest: Vec<f32> =
            input.data.iter().map(|p| p[0].max(p[1]).max(p[2])).filter(|v| v.is_finite()).collect();
        if brightest.is_empty() {
            return Self::IDENTITY;
        }
        let k = ((brightest.len() - 1) as f64 * SCALE_PERCENTILE).round() as usize;
        let (_, v, _) = brightest.select_nth_unstable_by(k, f32::total_cmp);
        Self { scale: v.max(1.0) }
    }

    /// Whether the input is fitted as it is.
    pub(crate) fn is_identity(&self) -> bool {
        self.scale <= 1.0
    }

    /// `img` divided by the scale (into the fit's range).
    pub(crate) fn divided(&self, img: &Image) -> Image {
        scaled(img, 1.0 / self.scale)
    }

    /// The fit evaluator `ev` on the target divided by the scale, at the exposure divided by it:
    /// the same renders, compared where the loss's clamp no longer hides the input's bright end.
    pub(crate) fn evaluator(&self, ev: &Evaluator) -> Evaluator {
        let scene = Scene { exposure: ev.scene().exposure / self.scale, ..ev.scene().clone() };
        ev.sibling(scene, self.divided(ev.target()), ev.block())
    }

    /// The result of a fit finished on [`DisplayRange::evaluator`] in the input's units: the scale
    /// multiplies the fitted scene's exposure (the parameter file and every render made from the
    /// result), the target and the final render; the crop PSNR is taken again between the two as
    /// the input shows them. The identity returns `res` as it is.
    pub(crate) fn result_to_input(&self, mut res: FitResult) -> FitResult {
        if self.is_identity() {
            return res;
        }
        let s = self.scale;
        res.params.scene.exposure *= s;
        res.fit_scene.exposure *= s;
        res.target = scaled(&res.target, s);
        res.render = scaled(&res.render, s);
        res.psnr_db = res.observed_render().psnr_srgb(&res.target);
        res
    }
}

/// `img` times `s`.
fn scaled(img: &Image, s: f32) -> Image {
    Image { width: img.width, height: img.height, data: img.data.iter().map(|p| p.map(|v| v * s)).collect() }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_display_referred_input_is_left_as_it_is() {
        let mut img = Image::filled(20, 10, [0.2, 0.5, 1.0]);
        img.data[3] = [0.0, 0.0, 0.0];
        let r = DisplayRange::of(&img);
        assert_eq!(r.scale, 1.0);
        assert!(r.is_identity());
    }

    #[test]
    fn an_hdr_input_is_scaled_by_its_bright_end_and_a_few_glints_do_not_set_it() {
        // 1000 pixels: 600 at 0.5, 396 with a channel at 1.6, 4 glints at 40.
        let mut img = Image::filled(100, 10, [0.5, 0.4, 0.3]);
        for (i, p) in img.data.iter_mut().enumerate() {
            if i % 5 < 2 && i < 990 {
                *p = [1.6, 0.2, 0.1];
            }
        }
        for p in img.data.iter_mut().rev().take(4) {
            *p = [40.0, 40.0, 40.0];
        }
        let r = DisplayRange::of(&img);
        assert_eq!(r.scale, 1.6, "the 99.5th percentile is a yarn top, not a glint");
        let fit = r.divided(&img);
        assert!((fit.data[0][0] - 1.0).abs() < 1e-6);
        assert!((fit.data[2][0] - 0.5 / 1.6).abs() < 1e-6);
        // Back: the scale multiplies the input's units again.
        assert!((scaled(&fit, r.scale).data[0][0] - 1.6).abs() < 1e-6);
    }

    #[test]
    fn the_divided_evaluator_unclamps_the_target_and_agrees_at_the_truth() {
        use crate::fit::target::fit_scene;
        use crate::scene::LightRig;
        let truth = crate::fit::demo::demo_cloth();
        // Front light only: a back light seen through a gap is clipped per sample to the display
        // white of the exposure (`render::integrator`), the one place a render is not linear in it.
        let front = LightRig::named("front").expect("the front rig");
        let mut scene = fit_scene(truth.pattern.n_e(), truth.pattern.n_a(), 6, 2, 3, &front);
        scene.exposure = 4.0;
        let ev = Evaluator::of_own_render(&truth, scene);
        let above = |img: &Image| img.data.iter().filter(|p| p.iter().any(|&v| v > 1.0 + 1e-5)).count();
        assert!(above(ev.target()) * 20 > ev.target().data.len(), "the test needs a bright target");
        let range = DisplayRange::of(ev.target());
        assert!(range.scale > 1.0);
        let hdr = range.evaluator(&ev);
        // At most the percentile's share of pixels still above 1.
        let share = above(hdr.target()) as f64 / hdr.target().data.len() as f64;
        assert!(share <= 1.0 - SCALE_PERCENTILE + 1e-3, "{share}");
        assert!((hdr.scene().exposure - 4.0 / range.scale).abs() < 1e-5);
        // The renders scale with the exposure, so the truth still matches exactly.
        assert!(hdr.trace_mse(&truth) < 1e-8, "{}", hdr.trace_mse(&truth));
        // A family dimmed by a fifth: where the clamp hid it, the divided target shows it.
        let mut dim = truth.clone();
        dim.appearance.r_b_e = dim.appearance.r_b_e.map(|v| v * 0.8);
        assert!(hdr.trace_mse(&dim) > 0.0);
    }

    #[test]
    fn the_scale_ignores_non_finite_values_and_an_empty_image() {
        let mut img = Image::filled(4, 4, [2.0, 0.0, 0.0]);
        img.data[0] = [f32::NAN, 0.0, 0.0];
        assert_eq!(DisplayRange::of(&img).scale, 2.0);
        let empty = Image { width: 0, height: 0, data: vec![] };
        assert_eq!(DisplayRange::of(&empty).scale, 1.0);
    }
}
