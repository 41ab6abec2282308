//! The fit's output stage: the final state (clamped to Table 1, rendered at `final_spp`, the
//! pattern reduced, a scene that frames the input) and the files of a fit: `fit.json`,
//! `prep.json`, `noise.json`, `fit.png`, `fit_sharp.png`, `fit_noise.png`, `compare.png`, `trace.png`, `log.jsonl`, `export/`.

use super::evaluator::Evaluator;
use super::options::RenderSettings;
use super::FitResult;
use crate::image_io::Image;
use crate::params::{param, ClothParams, ParamFile, PARAMS};
use crate::plot::{register_font, write_rgb_png as write_png};
use crate::render::{render, Prepared, RenderOptions};
use crate::scene::Scene;
use anyhow::{Context, Result};
use plotters::prelude::*;
use std::path::Path;

/// The fit's final state.
pub(crate) struct FinalState {
    /// Best cloth on the fit grid, clamped to the Table-1 ranges.
    pub cloth: ClothParams,
    /// The cloth with the reduced pattern and a scene that renders the input's framing.
    pub params: ParamFile,
    /// Render of `cloth` at the fit's view and `final_spp`.
    pub render: Image,
    /// PSNR (sRGB) of `render` against the target.
    pub psnr_db: f32,
    /// The fit's view with the backdrop solved for `cloth` ([`Scene::backdrop`]).
    pub fit_scene: Scene,
}

/// The final state of `best` (on the `grid` of the fit's evaluator `ev`) for an input of `size`
/// pixels, prepared by `prep` or not; errors when the parameter file does not validate.
pub(crate) fn final_state(
    best: &ClothParams,
    ev: &Evaluator,
    settings: &RenderSettings,
    grid: (usize, usize),
    size: (u32, u32),
    prep: Option<&crate::prep::Prepared>,
) -> Result<FinalState> {
    // The barrier lets the optimizer step a little past the Table-1 ranges.
    let cloth = best.clamped();
    // The backdrop seen through the gaps, solved on the fit's own samples (the loss solves it at
    // every evaluation), in the lights' units: the scene's exposure multiplies it again.
    let mut fit_scene = ev.scene().clone();
    let exposure = fit_scene.exposure.max(1e-4);
    fit_scene.backdrop =
        ev.backdrop(&ev.record(&cloth), &cloth.appearance).map(|b| b.map(|v| (v / exposure).clamp(0.0, 100.0)));
    let final_scene =
        Scene { spp: settings.final_spp.max(1), seed: settings.seed.wrapping_add(7), ..fit_scene.clone() };
    let render = Prepared::new(&cloth, &final_scene, &RenderOptions::default()).render(&cloth.appearance);
    // Against the target as the fit saw it: the render blurred as preparation blurred the target.
    let psnr_db = ev.observe(&render).psnr_srgb(ev.target());
    // A body texture is laid over the fit grid, so the pattern keeps that grid.
    let reduced = if cloth.body_texture.is_some() { cloth.pattern.clone() } else { cloth.pattern.reduced() };
    let mut out_cloth = cloth.clone();
    out_cloth.pattern = reduced.clone();
    let scene = output_scene(&fit_scene, grid, (reduced.n_e(), reduced.n_a()), size, prep);
    let params = ParamFile { cloth: out_cloth, scene };
    params.validate().context("fitted parameter file does not validate")?;
    Ok(FinalState { cloth, params, render, psnr_db, fit_scene })
}

/// Scene rendering the input's framing for a cloth with `reduced` pattern when the fit grid is
/// `n_e × n_a` (unreduced).
fn output_scene(
    fit: &Scene,
    n: (usize, usize),
    reduced: (usize, usize),
    size: (u32, u32),
    prep: Option<&crate::prep::Prepared>,
) -> Scene {
    let (n_e, n_a) = n;
    let (re, ra) = reduced;
    let fx = n_a as f32 / ra as f32;
    let fy = n_e as f32 / re as f32;
    let mut s = fit.clone();
    s.width = size.0.max(8);
    s.height = size.1.max(8);
    match prep {
        None => {
            s.camera.tiles = fx;
            s.camera.offset = [0.5 * fx, 0.5 * fy];
        }
        Some(p) => {
            // One repeat of the fit grid spans `crop.w` pixels of the rectified image.
            let tiles_fit = s.width as f32 / p.crop.w.max(1) as f32;
            s.camera.tiles = (tiles_fit * fx).clamp(0.25, 64.0);
            // World x = 0 at crop.x; world y = ty at crop.y (image rows run downwards).
            let cx = (s.width as f32 / 2.0 - p.crop.x as f32) / p.crop.w.max(1) as f32;
            let cy = 1.0 - (s.height as f32 / 2.0 - p.crop.y as f32) / p.crop.h.max(1) as f32;
            s.camera.offset = [(cx * fx).clamp(-1e4, 1e4), (cy * fy).clamp(-1e4, 1e4)];
        }
    }
    s.spp = s.spp.max(16);
    s
}

/// Pixels per cell of the repeat rendered for [`registered_render`]: the photo's own cell size,
/// within these bounds (finer than 8 px the yarns' plies vanish; beyond 48 px the render costs
/// more than the photo's JPEG-soft detail is worth).
const REGISTER_PX_PER_CELL: (f32, f32) = (8.0, 48.0);

/// Samples per pixel of the repeat rendered for [`registered_render`].
const REGISTER_SPP: u32 = 32;

/// The fit rendered over the whole photo, registered to it: same size, and through the
/// preparation's homography the same rotation, perspective and phase, so that a user can flip
/// between the photo and the fit. `None` without preparation (the input is then one repeat,
/// which `params.scene` already frames).
///
/// The fit's view is orthographic and the cloth periodic, so one repeat of the fit grid, rendered
/// at about the photo's pixels per cell, holds every pixel: input pixel `(x, y)` maps to rectified
/// pixel `(u, v) = H⁻¹(x, y)`, whose position in the repeat is its offset from the crop's corner
/// as a fraction of the crop (`crop.w` × `crop.h`: warp and weft pitches may differ), wrapped,
/// after the preparation's drift `s(u)` is taken off (`u − s(u)`: where this repeat of the photo
/// sits, `prep::drift`); the repeat is sampled there bilinearly with wrap-around. The repeat is blurred by the
/// photo's own blur as the fit measured it: the fit's blur ([`FitResult::blur_px`]) less the one
/// preparation gave the target ([`FitResult::prep_blur_px`]), in quadrature.
pub fn registered_render(res: &FitResult, size: (u32, u32), threads: Option<usize>) -> Option<Image> {
    register(res, size, threads, true)
}

/// [`registered_render`] without the fit's blur: the cloth as the fit models it, seen by a sharp
/// camera. What a sharp input (a render by another renderer) is compared with pixel for pixel
/// (`renders::family_colours`): the blur moves colour across yarn edges, from the backdrop into the
/// yarns' edge pixels, which a sharp input does not have.
pub fn registered_render_sharp(res: &FitResult, size: (u32, u32), threads: Option<usize>) -> Option<Image> {
    register(res, size, threads, false)
}

/// [`registered_render`], the repeat blurred as the photo is when `blurred`.
fn register(res: &FitResult, size: (u32, u32), threads: Option<usize>, blurred: bool) -> Option<Image> {
    let tile = RegisteredTile::render(res, threads)?;
    Some(tile.sample(res, size, blurred))
}

/// The fit registered to the photo twice from one render of its repeat: as compared
/// ([`registered_render`]) and sharp ([`registered_render_sharp`]).
pub fn registered_pair(res: &FitResult, size: (u32, u32), threads: Option<usize>) -> Option<Registered> {
    let tile = RegisteredTile::render(res, threads)?;
    Some(Registered { blurred: tile.sample(res, size, true), sharp: tile.sample(res, size, false) })
}

/// The fit registered to the photo ([`registered_pair`]).
#[derive(Clone, Debug)]
pub struct Registered {
    /// [`registered_render`]: the repeat blurred as the photo is (`fit.png`).
    pub blurred: Image,
    /// [`registered_render_sharp`]: the repeat as a sharp camera sees it.
    pub sharp: Image,
}

/// One repeat of the fit grid rendered at about the photo's pixels per cell: every pixel of
/// [`registered_render`] is a sample of it (the view is orthographic and the cloth periodic).
struct RegisteredTile {
    tile: Image,
    /// Pixels per cell of `tile`.
    c: u32,
    /// `H⁻¹`: photo pixels to rectified pixels.
    inv: crate::math::linalg::Homography,
}

impl RegisteredTile {
    fn render(res: &FitResult, threads: Option<usize>) -> Option<Self> {
        let p = res.prep.as_ref()?;
        let inv = crate::math::linalg::mat3_inv(&p.homography)?;
        let (n_e, n_a) = (res.cloth.pattern.n_e(), res.cloth.pattern.n_a());
        let (cw, ch) = (p.crop.w.max(1) as f64, p.crop.h.max(1) as f64);
        // The crop is in working pixels (`prep::working_scale`); the photo has `scale` times more.
        let photo_c = ((cw / n_a as f64).max(ch / n_e as f64) * p.working_scale() as f64) as f32;
        let c = photo_c.clamp(REGISTER_PX_PER_CELL.0, REGISTER_PX_PER_CELL.1).round() as u32;
        let scene = Scene {
            width: n_a as u32 * c,
            height: n_e as u32 * c,
            spp: REGISTER_SPP,
            seed: res.fit_scene.seed.wrapping_add(11),
            ..res.fit_scene.clone()
        };
        let tile = render(&res.cloth, &scene, &RenderOptions { threads, ..Default::default() });
        Some(Self { tile, c, inv })
    }

    /// The photo-sized image: input pixel `(x, y)` maps to rectified pixel `(u, v) = H⁻¹(x, y)`,
    /// wrapped into the repeat; with `blurred`, the repeat first gets the photo's own blur.
    fn sample(&self, res: &FitResult, size: (u32, u32), blurred: bool) -> Image {
        let p = res.prep.as_ref().expect("a registered tile exists only with preparation");
        let (cw, ch) = (p.crop.w.max(1) as f64, p.crop.h.max(1) as f64);
        // The fit compared its renders with the target after a Gaussian blur of `blur_px` fit
        // pixels: the blur preparation gave the target (`prep_blur_px`, σ = pitch/16) plus the
        // photo's own. The photo never had the first, so the repeat gets the rest, the photo's
        // own blur: Gaussians compose in quadrature, σ² = blur_px² − prep_blur_px² (0 where the fit
        // saw no more than preparation's). Scaled from the fit's pixels per cell to this repeat's.
        // Why: with the whole `blur_px`, fit.png was blurred by preparation's σ on top of the
        // photo's and scored against the sharp photo: a twill 2/2 rendered by woven itself at 16 px
        // a yarn (4 × 4 repeats, no rotation) came back 23 dB against the photo where the mean of
        // its repeats scores 37 dB, the loss being the σ = 1 px blur alone.
        let n_a = res.cloth.pattern.n_a();
        let fit_c = res.render.width as f32 / n_a.max(1) as f32;
        let own = (res.blur_px.powi(2) - res.prep_blur_px.powi(2)).max(0.0).sqrt();
        let sigma = if blurred { own * self.c as f32 / fit_c.max(1e-3) } else { 0.0 };
        let tile = super::evaluator::blur_wrapped(&self.tile, sigma);
        let (tw, th) = (tile.width as f64, tile.height as f64);
        let (w, h) = size;
        let mut data = Vec::with_capacity((w * h) as usize);
        for y in 0..h {
            for x in 0..w {
                let (u, v) = crate::math::linalg::apply(&self.inv, x as f64, y as f64);
                // The photo's repeat at u sits shifted by the drift s(u) (`prep::drift`): the
                // mean repeat the fit matched is read at u − s(u).
                let s = p.drift.shift_at(u, v);
                // Pixel centres: rectified pixel u covers [u, u + 1) in edge coordinates.
                let a = (u - s[0] + 0.5 - p.crop.x as f64) / cw * tw - 0.5;
                let b = (v - s[1] + 0.5 - p.crop.y as f64) / ch * th - 0.5;
                data.push(tile.sample_wrapped(a, b));
            }
        }
        Image::new(w, h, data)
    }
}

/// How well the registered fit matches the whole photo.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct PhotoScores {
    /// PSNR (sRGB, peak 1) of the registered fit against the photo, dB.
    pub psnr_db: f32,
    /// Mean structural similarity (SSIM, Wang et al. 2004) of the sRGB luma, in [−1, 1].
    pub ssim: f32,
}

/// [`PhotoScores`] of `fit` (same size as `photo`, e.g. [`registered_render`]) against `photo`.
pub fn photo_scores(fit: &Image, photo: &Image) -> PhotoScores {
    PhotoScores { psnr_db: fit.psnr_srgb(photo), ssim: ssim(fit, photo) }
}

/// Mean SSIM of two images of the same size (Wang, Bovik, Sheikh and Simoncelli 2004): on the
/// sRGB-encoded luma (Rec. 709 weights), local statistics under a Gaussian window of σ = 1.5 px,
/// `C1 = (0.01)²`, `C2 = (0.03)²` for a peak of 1 — the standard constants of the paper.
pub fn ssim(a: &Image, b: &Image) -> f32 {
    use crate::image_io::linear_to_srgb;
    assert_eq!((a.width, a.height), (b.width, b.height), "ssim of images of different sizes");
    let luma = |img: &Image| -> Vec<f32> {
        img.data
            .iter()
            .map(|p| 0.2126 * linear_to_srgb(p[0]) + 0.7152 * linear_to_srgb(p[1]) + 0.0722 * linear_to_srgb(p[2]))
            .collect()
    };
    let (x, y) = (luma(a), luma(b));
    let (w, h) = (a.width as usize, a.height as usize);
    let blur = |v: &[f32]| crate::prep::image_ops::blur_interleaved(v, w, h, 1, 1.5);
    let prod = |p: &[f32], q: &[f32]| p.iter().zip(q).map(|(s, t)| s * t).collect::<Vec<f32>>();
    let (mx, my) = (blur(&x), blur(&y));
    let (sxx, syy, sxy) = (blur(&prod(&x, &x)), blur(&prod(&y, &y)), blur(&prod(&x, &y)));
    let (c1, c2) = (0.01f64 * 0.01, 0.03f64 * 0.03);
    let mut sum = 0.0f64;
    for k in 0..w * h {
        let (ux, uy) = (mx[k] as f64, my[k] as f64);
        let vx = (sxx[k] as f64 - ux * ux).max(0.0);
        let vy = (syy[k] as f64 - uy * uy).max(0.0);
        let cxy = sxy[k] as f64 - ux * uy;
        sum += ((2.0 * ux * uy + c1) * (2.0 * cxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2));
    }
    (sum / (w * h).max(1) as f64) as f32
}

/// Nearest-neighbour upscale by an integer factor.
fn upscale(img: &Image, f: u32) -> Image {
    let f = f.max(1);
    let (w, h) = (img.width * f, img.height * f);
    let data = (0..h).flat_map(|y| (0..w).map(move |x| (x, y))).map(|(x, y)| img.get(x / f, y / f)).collect();
    Image::new(w, h, data)
}

/// Absolute sRGB error ×4 as a grey image.
pub fn error_map(a: &Image, b: &Image) -> Image {
    use crate::image_io::{linear_to_srgb, srgb_to_linear};
    let data = a
        .data
        .iter()
        .zip(&b.data)
        .map(|(p, q)| {
            let e = (0..3).map(|k| (linear_to_srgb(p[k]) - linear_to_srgb(q[k])).abs()).fold(0.0f32, f32::max);
            [srgb_to_linear((4.0 * e).min(1.0)); 3]
        })
        .collect();
    Image::new(a.width, a.height, data)
}

/// `img` scaled to `height` pixels high, keeping its aspect (box resampling): a contact-sheet tile.
pub fn sheet_tile(img: &Image, height: u32) -> Image {
    let w = ((img.width as u64 * height as u64) / img.height.max(1) as u64).clamp(1, 4096) as u32;
    crate::math::resample::resample(img, w, height)
}

/// A contact-sheet row `a | b | error` ([`error_map`], as in `compare.png`), each [`sheet_tile`]d
/// to `height` pixels; `a` and `b` have the same size.
pub fn sheet_row(a: &Image, b: &Image, height: u32) -> Image {
    let err = error_map(a, b);
    Image::hstack(&[&sheet_tile(a, height), &sheet_tile(b, height), &sheet_tile(&err, height)], 2)
}

/// `compare.png`: target | fit as compared ([`FitResult::observed_render`]) | error (×4),
/// upscaled, with the PSNR written on it.
pub fn write_compare(res: &FitResult, path: &Path) -> Result<()> {
    register_font();
    let f = (256 / res.target.height.max(1)).clamp(1, 16);
    // The fit as it was compared (blurred like the target), so the error map is the one whose
    // PSNR is printed.
    let observed = res.observed_render();
    let err = error_map(&res.target, &observed);
    let (t, r, e) = (upscale(&res.target, f), upscale(&observed, f), upscale(&err, f));
    let strip = Image::hstack(&[&t, &r, &e], 4);
    let label_h = 28u32;
    let (w, h) = (strip.width.max(360), strip.height + label_h);
    let mut buf = vec![255u8; (w * h * 3) as usize];
    let rgb = strip.to_srgb8();
    for y in 0..strip.height {
        for x in 0..strip.width {
            let p = rgb.get_pixel(x, y).0;
            let i = (((y + label_h) * w + x) * 3) as usize;
            buf[i..i + 3].copy_from_slice(&p);
        }
    }
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        let txt = format!("input | fit | error x4     PSNR {:.2} dB", res.psnr_db);
        root.draw(&Text::new(txt, (6, 6), ("sans-serif", 16).into_font().color(&BLACK)))
            .map_err(|e| anyhow::anyhow!("drawing text: {e}"))?;
        root.present().map_err(|e| anyhow::anyhow!("drawing: {e}"))?;
    }
    write_png(path, w, h, buf)
}

/// `trace.png`: loss (log) with accepted discrete changes marked, and parameter traces.
pub fn write_trace(res: &FitResult, path: &Path) -> Result<()> {
    register_font();
    let (w, h) = (900u32, 700u32);
    let mut buf = vec![255u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(plot_err)?;
        let (top, bottom) = root.split_vertically(350);
        draw_loss(&top, res)?;
        draw_parameters(&bottom, res)?;
        root.present().map_err(plot_err)?;
    }
    write_png(path, w, h, buf)
}

/// A plotting error of `trace.png` as an error of the fit outputs.
fn plot_err(e: impl std::fmt::Display) -> anyhow::Error {
    anyhow::anyhow!("plotting the trace: {e}")
}

/// The loss chart of `trace.png`: current and best loss (log scale), accepted cell changes.
fn draw_loss<DB: DrawingBackend>(area: &DrawingArea<DB, plotters::coord::Shift>, res: &FitResult) -> Result<()> {
    let hist = &res.history;
    let n = hist.len().max(2) as f64;
    let loss: Vec<(f64, f64)> = hist.iter().map(|l| (l.iter as f64, (l.loss as f64).max(1e-9))).collect();
    let best: Vec<(f64, f64)> = hist.iter().map(|l| (l.iter as f64, (l.best_loss as f64).max(1e-9))).collect();
    let (lo, hi) = loss.iter().chain(&best).fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.1), b.max(p.1)));
    let (lo, hi) = if lo < hi { (lo * 0.8, hi * 1.25) } else { (1e-6, 1.0) };
    let mut chart = ChartBuilder::on(area)
        .caption(format!("fit loss (MSE + barrier), PSNR {:.2} dB", res.psnr_db), ("sans-serif", 20))
        .margin(12)
        .x_label_area_size(35)
        .y_label_area_size(70)
        .build_cartesian_2d(0.0..n, (lo..hi).log_scale())
        .map_err(plot_err)?;
    chart
        .configure_mesh()
        .x_desc("iteration")
        .y_desc("loss")
        .y_label_formatter(&|v| format!("{v:.1e}"))
        .label_style(("sans-serif", 12))
        .draw()
        .map_err(plot_err)?;
    chart
        .draw_series(LineSeries::new(loss.iter().copied(), BLUE.stroke_width(2)))
        .map_err(plot_err)?
        .label("current")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLUE.stroke_width(2)));
    chart
        .draw_series(LineSeries::new(best.iter().copied(), BLACK.stroke_width(1)))
        .map_err(plot_err)?
        .label("best")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK.stroke_width(1)));
    let acc: Vec<(f64, f64)> = hist
        .iter()
        .filter(|l| l.accepted && l.proposal.is_some_and(|p| p.is_cell()))
        .map(|l| (l.iter as f64, (l.loss as f64).max(1e-9)))
        .collect();
    chart
        .draw_series(PointSeries::of_element(acc, 4, RED.filled(), &|c, s, st| {
            EmptyElement::at(c) + Circle::new((0, 0), s, st)
        }))
        .map_err(plot_err)?
        .label("accepted pattern change")
        .legend(|(x, y)| Circle::new((x + 10, y), 4, RED.filled()));
    chart
        .configure_series_labels()
        .label_font(("sans-serif", 13))
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(plot_err)?;
    Ok(())
}

/// The parameter chart of `trace.png`: radii, counts, a few appearance scalars and the
/// temperature, each normalised to its range.
fn draw_parameters<DB: DrawingBackend>(area: &DrawingArea<DB, plotters::coord::Shift>, res: &FitResult) -> Result<()> {
    let hist = &res.history;
    let n = hist.len().max(2) as f64;
    let mut chart = ChartBuilder::on(area)
        .caption("parameters (normalised to their range)", ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(35)
        .y_label_area_size(70)
        .build_cartesian_2d(0.0..n, 0.0..1.0f64)
        .map_err(plot_err)?;
    chart.configure_mesh().x_desc("iteration").label_style(("sans-serif", 12)).draw().map_err(plot_err)?;
    type Getter = Box<dyn Fn(&super::joint::IterLog) -> f64>;
    use param::{M_R, N_F, N_P, R_A, R_B_A, R_B_E, R_E};
    let series: Vec<(&str, RGBColor, Getter)> = vec![
        (PARAMS[R_E].name, RGBColor(200, 0, 0), Box::new(|l| fraction(R_E, l.r_e as f64))),
        (PARAMS[R_A].name, RGBColor(0, 120, 0), Box::new(|l| fraction(R_A, l.r_a as f64))),
        (PARAMS[N_P].name, RGBColor(120, 0, 160), Box::new(|l| fraction(N_P, l.n_p as f64))),
        (PARAMS[N_F].name, RGBColor(160, 100, 0), Box::new(|l| fraction(N_F, l.n_f as f64))),
        (PARAMS[M_R].name, RGBColor(0, 0, 200), Box::new(|l| fraction(M_R, l.appearance[M_R] as f64))),
        (PARAMS[R_B_E].name, RGBColor(255, 80, 80), Box::new(|l| fraction(R_B_E, l.appearance[R_B_E] as f64))),
        (PARAMS[R_B_A].name, RGBColor(80, 160, 255), Box::new(|l| fraction(R_B_A, l.appearance[R_B_A] as f64))),
        ("T/T0", RGBColor(120, 120, 120), Box::new(|l| (l.temperature / super::anneal::T0).min(1.0))),
    ];
    for (name, col, get) in series {
        let pts: Vec<(f64, f64)> = hist.iter().map(|l| (l.iter as f64, get(l).clamp(0.0, 1.0))).collect();
        chart
            .draw_series(LineSeries::new(pts, col.stroke_width(2)))
            .map_err(plot_err)?
            .label(name)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], col.stroke_width(2)));
    }
    chart
        .configure_series_labels()
        .label_font(("sans-serif", 12))
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(plot_err)?;
    Ok(())
}

/// Position of `x` in the Table-1 range of parameter `k`, `(x − min)/span`, in f64 as plotted.
fn fraction(k: usize, x: f64) -> f64 {
    (x - PARAMS[k].min as f64) / PARAMS[k].span() as f64
}

/// Every output of a fit in `dir`: with preparation, noise post-estimation (paper §6.3) — the
/// residual rectified − regularized gives `noise.json`, whose synthesized noise is added to a
/// copy of `fit.png`, `fit_noise.png`, unless `add_noise` is false — then the files of
/// [`write_outputs`] and the yarn geometry in `export/` (PLY + Mitsuba 3 scene). Returns warnings (no noise model) and the
/// registered render (see [`Written`]).
pub fn write_fit_outputs(res: &FitResult, dir: &Path, add_noise: bool, threads: Option<usize>) -> Result<Written> {
    let mut warnings = Vec::new();
    let mut noise = None;
    if let Some(p) = &res.prep {
        let rect = Image::from_rgb32f(&p.rectified);
        // The periodic picture with each repeat where the photo has it (`prep::drift`): the
        // residual is then the photo's noise and fibre texture, not a misregistration.
        let reg = Image::from_rgb32f(&p.drift.apply(&p.regularized));
        match crate::noise::residual(&rect, &reg).and_then(|r| crate::noise::NoiseModel::fit(&r)) {
            Ok(model) => {
                std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
                model.save(&dir.join("noise.json"))?;
                noise = Some(model);
            }
            Err(e) => warnings.push(format!("no noise model ({e})")),
        }
    }
    let registered = write_outputs(res, dir, threads, noise.as_ref().filter(|_| add_noise))?;
    crate::export::export(&res.params, &dir.join("export"), &crate::export::ExportOptions::default())
        .context("exporting the yarn geometry")?;
    Ok(Written { warnings, registered })
}

/// What [`write_fit_outputs`] hands back besides the files.
pub struct Written {
    /// Warnings (no noise model).
    pub warnings: Vec<String>,
    /// With preparation, the fit registered at the photo's size: `blurred` is `fit.png` (without
    /// the photo noise of `fit_noise.png`), what the fit is scored with against the whole photo
    /// ([`photo_scores`]); `sharp` is what a sharp input's colours are compared with.
    pub registered: Option<Registered>,
}

/// Write the files of a fit into `dir` (created): `fit.json`, `prep.json` (with preparation),
/// `cues.json` (where the picture's cells met the fit, `FitResult::cue_contest`), `log.jsonl`,
/// `stages.json` (`FitResult::stages`), `fit.png`, `fit_sharp.png` (with preparation:
/// [`registered_render_sharp`]), `fit_noise.png` (`fit.png` with `noise` added, when given),
/// `compare.png`, `trace.png`. Returns the registered renders, the blurred one being
/// `fit.png` (`None` without preparation).
pub fn write_outputs(
    res: &FitResult,
    dir: &Path,
    threads: Option<usize>,
    noise: Option<&crate::noise::NoiseModel>,
) -> Result<Option<Registered>> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    res.params.save(&dir.join("fit.json")).with_context(|| format!("writing {}", dir.join("fit.json").display()))?;
    if let Some(p) = &res.prep {
        crate::io::write_atomic(&dir.join("prep.json"), p.to_json().as_bytes())?;
    }
    if let Some(c) = &res.cue_contest {
        crate::io::write_atomic(&dir.join("cues.json"), serde_json::to_string_pretty(c)?.as_bytes())?;
    }
    let mut log = String::new();
    for l in &res.history {
        log.push_str(&serde_json::to_string(l)?);
        log.push('\n');
    }
    crate::io::write_atomic(&dir.join("log.jsonl"), log.as_bytes())?;
    crate::io::write_atomic(&dir.join("stages.json"), serde_json::to_string_pretty(&res.stages)?.as_bytes())?;
    // With preparation, fit.png is registered to the photo (its size, rotation, perspective and
    // phase); without, the input is one repeat and `params.scene` frames it.
    let size = (res.params.scene.width, res.params.scene.height);
    let registered = registered_pair(res, size, threads);
    let full = match &registered {
        Some(r) => r.blurred.clone(),
        None => render(&res.params.cloth, &res.params.scene, &RenderOptions { threads, ..Default::default() }),
    };
    full.save_png(&dir.join("fit.png"))?;
    // The same registered replica seen by a sharp camera: what the fitted cloth looks like when
    // re-rendered (fibres and plies at the photo's resolution), beside fit.png, which carries the
    // photo's own blur as the fit measured it and is the image scored against the photo.
    if let Some(r) = &registered {
        r.sharp.save_png(&dir.join("fit_sharp.png"))?;
    }
    // The synthesized photo noise goes to its own file: on a real photo the residual it models
    // holds everything the periodic fit leaves out (hair, uneven yarns, misregistration), often a
    // standard deviation of 0.2–0.3, which buries the cloth; fit.png stays the image whose PSNR
    // and SSIM against the photo are reported, so the two can be flipped.
    if let Some(m) = noise {
        let mut noisy = full;
        let scale = res.prep.as_ref().map_or(1, |p| p.working_scale());
        m.add_to_scaled(&mut noisy, res.params.scene.seed, scale);
        noisy.save_png(&dir.join("fit_noise.png"))?;
    }
    write_compare(res, &dir.join("compare.png"))?;
    write_trace(res, &dir.join("trace.png"))?;
    Ok(registered)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::target::fit_scene;
    use crate::scene::LightRig;

    #[test]
    fn the_final_cloth_is_clamped_to_table_1() {
        let mut c = crate::fit::demo::demo_cloth();
        c.appearance.m_r = -1.0;
        c.appearance.r_b_e = [1.2, 0.5, -0.1];
        (c.r_e, c.r_a) = (PARAMS[param::R_E].max + 1.0, 4.0);
        let ev = Evaluator::new(fit_scene(4, 4, 4, 1, 1, &LightRig::default_rig()), Image::filled(16, 16, [0.3; 3]), 2);
        let settings = RenderSettings { px_per_cell: 4, spp: 1, final_spp: 1, ..RenderSettings::default() };
        let out = final_state(&c, &ev, &settings, (4, 4), (16, 16), None).unwrap();
        let k = &out.cloth;
        assert_eq!(k.appearance.m_r, PARAMS[param::M_R].min);
        assert_eq!(k.appearance.r_b_e, [1.0, 0.5, 0.0]);
        assert_eq!((k.r_e, k.r_a), (PARAMS[param::R_E].max, 4.0));
        k.validate().unwrap();
        out.params.validate().unwrap();
    }

    #[test]
    fn the_output_scene_frames_the_input_with_the_reduced_repeat() {
        let fit = fit_scene(4, 6, 10, 4, 1, &LightRig::default_rig());
        // A 4×6 fit grid whose pattern reduces to 2×3: the 60×40 px input shows two repeats a side.
        let s = output_scene(&fit, (4, 6), (2, 3), (60, 40), None);
        assert_eq!((s.width, s.height, s.spp), (60, 40, 16));
        assert_eq!(s.camera.tiles, 2.0);
        assert_eq!(s.camera.offset, [1.0, 1.0]);
        // Tiny inputs still render at least 8 px a side.
        let s = output_scene(&fit, (4, 6), (4, 6), (3, 5), None);
        assert_eq!((s.width, s.height, s.camera.tiles), (8, 8, 1.0));
    }
}
