//! Preparation at the resolution the yarns need, not the camera's.
//!
//! Every step of [`super::prepare`] costs time in proportion to the pixels it reads (the Radon
//! transform of the rectification, the edge energies of the grid, the mean of the aligned
//! repeats), while what it finds — the yarn angle, pitch, phase and the repeat — needs only a
//! few dozen pixels per yarn: the fit itself matches one repeat resampled to 16 pixels per cell.
//! A 640 × 480 microscope photo is prepared in about a second; a 4032 × 3024 phone photo of the
//! same cloth took 103 CPU s, most of it in `grid::edge_energy` and `regularize`, for the same
//! grid.
//!
//! So a photo larger than [`WORK_SIDE`] is prepared on a *working view* of it: the photo
//! box-averaged by an integer factor `k` (an area mean: the exact anti-aliasing filter for an
//! integer factor, so yarn edges alias no more than the camera's own pixels do), optionally a
//! window of it. Two views are tried, cheapest first:
//! 1. the whole photo at `k₀ = ⌈side / WORK_SIDE⌉`; kept where its finer yarn pitch is at least
//!    [`FINE_PITCH`] working pixels (enough for the pitch, the phase and the cells' cues);
//! 2. otherwise (yarns finer than that, or no grid found at `k₀`) a window at the photo's centre,
//!    at most [`WORK_SIDE`] working pixels a side, at the factor `k₁ = ⌊k₀·p₀ / WANT_PITCH⌋ ≥ 1`
//!    that gives its yarns about [`WANT_PITCH`] pixels (`k₁ = 1` where `k₀` found nothing); a
//!    window that size still holds dozens of such yarns, many repeats of any weave. Where the
//!    window finds no grid either, the whole view's answer (its grid, or its error) stands.
//!
//! The preparation's geometry stays in working pixels (the rectified image is the working
//! view's); only its homography is composed with the view's map `x = k·x' + x₀ + (k − 1)/2`
//! (pixel centres at integers on both sides), so it still maps rectified pixels to *photo*
//! pixels and `fit.png` is registered to the photo at the photo's size.

use super::{PrepError, Prepared};
use crate::math::linalg::{mat3_mul, Homography};
use image::Rgb32FImage;
use serde::Serialize;

/// Longest side, in pixels, of a photo prepared as it is; a larger one is prepared on a working
/// view of at most this side (about 1 MP at 4:3, a second or two of preparation).
pub const WORK_SIDE: u32 = 1024;

/// Finest yarn pitch, in working pixels, at which the whole-photo view is kept.
pub const FINE_PITCH: f32 = 12.0;

/// Yarn pitch, in working pixels, that the window's factor aims at when the whole-photo view's
/// yarns are finer than [`FINE_PITCH`] (within the real photos' usual 20–60 px).
pub const WANT_PITCH: f32 = 24.0;

/// Where the working view sits in the photo: working pixel `(x', y')` is the mean of the photo's
/// `k × k` block starting at `(x₀ + k·x', y₀ + k·y')`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct WorkingView {
    /// Photo pixels per working pixel along each axis (`k ≥ 1`).
    pub scale: u32,
    /// Photo column of the view's first block.
    pub x0: u32,
    /// Photo row of the view's first block.
    pub y0: u32,
    /// Width of the view, working pixels.
    pub width: u32,
    /// Height of the view, working pixels.
    pub height: u32,
}

impl WorkingView {
    /// The whole `w × h` photo at factor `k` (the last partial block row and column left out).
    pub fn whole(w: u32, h: u32, k: u32) -> Self {
        let k = k.max(1);
        Self { scale: k, x0: 0, y0: 0, width: (w / k).max(1), height: (h / k).max(1) }
    }

    /// A window of at most `side × side` working pixels at factor `k`, centred in the `w × h`
    /// photo.
    pub fn centre_window(w: u32, h: u32, k: u32, side: u32) -> Self {
        let k = k.max(1);
        let (vw, vh) = ((w / k).clamp(1, side.max(1)), (h / k).clamp(1, side.max(1)));
        Self { scale: k, x0: (w - vw * k) / 2, y0: (h - vh * k) / 2, width: vw, height: vh }
    }

    /// Whether the view is the photo itself (factor 1, no window).
    pub fn is_identity(&self, w: u32, h: u32) -> bool {
        self.scale == 1 && self.x0 == 0 && self.y0 == 0 && self.width == w && self.height == h
    }

    /// The view's pixels: each the mean of its `k × k` block of `img`.
    pub fn extract(&self, img: &Rgb32FImage) -> Rgb32FImage {
        let k = self.scale as usize;
        let (iw, src) = (img.width() as usize, img.as_raw());
        let norm = 1.0 / (k * k) as f32;
        let mut out = Vec::with_capacity(self.width as usize * self.height as usize * 3);
        for y in 0..self.height as usize {
            let py = self.y0 as usize + y * k;
            for x in 0..self.width as usize {
                let px = self.x0 as usize + x * k;
                let mut acc = [0.0f32; 3];
                for r in py..py + k {
                    let row = &src[(r * iw + px) * 3..(r * iw + px + k) * 3];
                    for p in row.chunks_exact(3) {
                        acc[0] += p[0];
                        acc[1] += p[1];
                        acc[2] += p[2];
                    }
                }
                out.extend(acc.map(|a| a * norm));
            }
        }
        Rgb32FImage::from_raw(self.width, self.height, out).expect("buffer sized to the view")
    }

    /// Working pixel → photo pixel, pixel centres at integers: `x = k·x' + x₀ + (k − 1)/2`.
    pub fn to_photo(&self) -> Homography {
        let k = self.scale as f64;
        let off = (k - 1.0) / 2.0;
        [[k, 0.0, self.x0 as f64 + off], [0.0, k, self.y0 as f64 + off], [0.0, 0.0, 1.0]]
    }
}

/// Runs `prepare_view` (the preparation proper) on the photo itself when its [`overview`] is the
/// photo (longest side at most [`WORK_SIDE`], or a short side too small to shrink), else on the
/// working views of the module docs; the result's homography maps rectified pixels to photo
/// pixels and `working` records the view used.
pub fn prepare_scaled(
    img: &Rgb32FImage,
    prepare_view: impl Fn(&Rgb32FImage) -> Result<Prepared, PrepError>,
) -> Result<Prepared, PrepError> {
    let (w, h) = img.dimensions();
    let whole = overview(w, h);
    let k0 = whole.scale;
    if k0 == 1 {
        return prepare_view(img);
    }
    let coarse = prepare_view(&whole.extract(img)).map(|p| in_photo(p, whole)).map_err(|e| photo_error(e, whole, w, h));
    let p0 = coarse.as_ref().ok().map(|p| p.pitch_x.min(p.pitch_y));
    if p0.is_some_and(|p| p >= FINE_PITCH) {
        return coarse;
    }
    // Here `p0 < FINE_PITCH < WANT_PITCH` (or no grid), so `k1 < k0`: always a finer view.
    let k1 = p0.map_or(1, |p| ((k0 as f32 * p / WANT_PITCH).floor() as u32).clamp(1, k0));
    let window = WorkingView::centre_window(w, h, k1, WORK_SIDE);
    match prepare_view(&window.extract(img)) {
        Ok(p) => Ok(in_photo(p, window)),
        Err(_) => coarse,
    }
}

/// The whole photo of `w × h` pixels at the least integer factor that brings its longest side to
/// [`WORK_SIDE`] or less (the photo itself when it is that small): what a picture of the whole
/// photo, such as the refusal's overlay, is drawn on.
/// The factor never takes the shorter side below [`super::MIN_SIZE`] (a long strip is prepared as
/// it is).
pub fn overview(w: u32, h: u32) -> WorkingView {
    let k = w.max(h).div_ceil(WORK_SIDE).min(w.min(h) / super::MIN_SIZE).max(1);
    WorkingView::whole(w, h, k)
}

/// An error of the preparation of `view` told in the photo's pixels (`w × h`): the sizes it names
/// are the photo's, not the view's.
fn photo_error(e: PrepError, view: WorkingView, w: u32, h: u32) -> PrepError {
    match e {
        PrepError::TooSmallAfterRectify { width, height, angle_deg, min, .. } => PrepError::TooSmallAfterRectify {
            in_width: w,
            in_height: h,
            width: width * view.scale,
            height: height * view.scale,
            angle_deg,
            min,
        },
        other => other,
    }
}

/// `p`, prepared on `view`, with its homography mapping rectified pixels to photo pixels.
fn in_photo(mut p: Prepared, view: WorkingView) -> Prepared {
    p.homography = mat3_mul(&view.to_photo(), &p.homography);
    p.working = Some(view);
    p
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::linalg::apply;

    fn ramp(w: u32, h: u32) -> Rgb32FImage {
        Rgb32FImage::from_fn(w, h, |x, y| image::Rgb([x as f32, y as f32, (x + y) as f32]))
    }

    #[test]
    fn a_view_pixel_is_the_mean_of_its_block_and_maps_to_the_block_centre() {
        let img = ramp(10, 7);
        let v = WorkingView::whole(10, 7, 3);
        assert_eq!((v.width, v.height), (3, 2));
        let out = v.extract(&img);
        // Block (1, 1) covers photo columns 3..6 and rows 3..6: means 4 and 4.
        assert_eq!(out.get_pixel(1, 1).0, [4.0, 4.0, 8.0]);
        // Its centre in photo pixels is (4, 4): the map and the mean agree.
        let (x, y) = apply(&v.to_photo(), 1.0, 1.0);
        assert!((x - 4.0).abs() < 1e-12 && (y - 4.0).abs() < 1e-12);
    }

    #[test]
    fn a_centre_window_is_centred_and_bounded() {
        let v = WorkingView::centre_window(4032, 3024, 2, WORK_SIDE);
        assert_eq!((v.width, v.height), (WORK_SIDE, WORK_SIDE));
        assert_eq!((v.x0, v.y0), ((4032 - 2048) / 2, (3024 - 2048) / 2));
        let out = v.extract(&ramp(4032, 3024));
        // Working pixel (0, 0) is the block at (x0, y0): mean x0 + 0.5.
        assert_eq!(out.get_pixel(0, 0).0[0], v.x0 as f32 + 0.5);
        let (x, _) = apply(&v.to_photo(), 0.0, 0.0);
        assert_eq!(x, v.x0 as f64 + 0.5);
        assert!(!v.is_identity(4032, 3024));
        assert!(WorkingView::whole(640, 480, 1).is_identity(640, 480));
    }
}
