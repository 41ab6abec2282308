//! Image preparation (paper §4, docs/design.md §3): turn one close-up photo of a woven
//! fabric into an axis-aligned, regularized image plus the yarn grid and the minimum repeating
//! pattern size.
//!
//! A photo larger than [`working_scale::WORK_SIDE`] is prepared on a box-averaged working view
//! ([`working_scale`]), the homography composed back to the photo's pixels. Steps, in the order
//! [`prepare`] runs them:
//! 1. [`rectify`] — Laplacian + Radon transform → dominant yarn angle, rotation, crop; then a
//!    RANSAC vanishing-point fit removes slight perspective (§4.1, \[Chaudhury14\]).
//! 2. A first pitch estimate from the integral projections of the rectified image ([`grid`]); its
//!    autocorrelation is the *periodicity strength* that rejects images without yarns; a pitch
//!    about half the other axis's whose fine lines the cells pair is doubled ([`halved_pitch`]).
//!    Both pitches half the yarns' (an open weave over a ground of another brightness) are doubled
//!    where the doubled lattice's corners and cells' middles differ ([`halved_both`]).
//! 3. Gaussian blur with σ = pitch/16 ([`regularize`]).
//! 4. [`period`] — superposed distance matching functions of all rows / columns → the
//!    minimum pattern size in pixels (§4.3, \[Asha12\]).
//! 5. Mean of the repeats, each aligned at sub-pixel on the period lattice, outlier repeats left
//!    out → the regularized ("ideal") image ([`regularize`], §4.2; replaces the paper's KPCA).
//! 6. [`grid`] — integral projections of the regularized image → yarn boundaries, pitch and
//!    phase; `n_a = round(period_x / pitch_x)`, `n_e = round(period_y / pitch_y)` (§4.4).
//!
//! Conventions: images are linear RGB `f32` ([`Rgb32FImage`]); the pattern has `n_e` rows (weft
//! yarns, running along image x) and `n_a` columns (warp yarns, running along image y).

pub mod cells;
pub mod colour_repeat;
pub mod drift;
pub mod finer_yarns;
pub mod grid;
pub mod halved_both;
pub mod halved_pitch;
pub mod image_ops;
pub mod period;
pub mod rectify;
pub mod regularize;
pub mod shear;
pub mod short_repeat;
pub mod survey;
#[cfg(test)]
pub(crate) mod testutil;
pub mod working_scale;

use image::Rgb32FImage;
use serde::Serialize;

pub use crate::math::linalg::Homography;
pub use drift::RepeatDrift;
pub use regularize::RepeatParams;
pub use working_scale::WorkingView;

use grid::{analyze_axis, AxisGrid};
use image_ops::{blur_gray, blur_rgb, median, Gray};
use period::{detect_period, PitchBaseline};

/// Smallest accepted image side, in pixels.
pub const MIN_SIZE: u32 = 32;

/// Errors of the preparation stage.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PrepError {
    /// The image (or what is left after rectification) is smaller than [`MIN_SIZE`].
    #[error("image too small: {width}x{height} px (need at least {min} px per side)")]
    TooSmall {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
        /// The minimum side.
        min: u32,
    },
    /// A pixel holds NaN or ±∞.
    #[error("image has a non-finite (NaN or infinite) value at pixel ({x}, {y})")]
    NonFinite {
        /// Column of the first offending pixel.
        x: u32,
        /// Row of the first offending pixel.
        y: u32,
    },
    /// Rectification (rotation to the yarn axes, then the largest axis-aligned crop) left less
    /// than [`MIN_SIZE`] of an input that was large enough, e.g. a long thin strip at an angle.
    #[error(
        "image too small: the {in_width}x{in_height} px input leaves only {width}x{height} px after rotating it by {angle_deg:.1}° to the yarn axes and cropping (need at least {min} px per side); use a less elongated crop, or one cut along the yarns"
    )]
    TooSmallAfterRectify {
        /// Input width in pixels.
        in_width: u32,
        /// Input height in pixels.
        in_height: u32,
        /// Width left after rectification.
        width: u32,
        /// Height left after rectification.
        height: u32,
        /// The rotation that was applied, degrees.
        angle_deg: f32,
        /// The minimum side.
        min: u32,
    },
    /// Uniform image, random noise, or anything else without a periodic grid of yarns.
    #[error(
        "no periodic yarn structure found: the image shows no regular grid of yarns (uniform, noise, or out of focus); try a sharp, evenly lit close-up showing at least 2 repeats of the weave each way"
    )]
    NoStructure,
    /// Neither axis repeats (period strength below [`PrepOptions::min_period_corr`]) and the
    /// yarn grid is too weak to take the whole image as a single repeat: what random noise gives.
    #[error(
        "no periodic yarn structure found: the pattern does not repeat inside the image (period strength {:.2} along x, {:.2} along y; a repeat needs {min_period:.2}) and the yarn grid is too weak ({:.2}; a single repeat needs {min_grid:.2}); try a sharp close-up showing at least 2 repeats of the weave each way, or fit a crop of exactly one repeat with `woven fit --no-prep --grid NExNA`",
        period_strength[0], period_strength[1], grid_strength[0].min(grid_strength[1])
    )]
    NoRepeat {
        /// DMF correlation of the best repeat along x and y (0: none).
        period_strength: [f32; 2],
        /// Periodicity strength of the integral projections along x and y.
        grid_strength: [f32; 2],
        /// [`PrepOptions::min_period_corr`].
        min_period: f32,
        /// [`PrepOptions::min_single_repeat_structure`].
        min_grid: f32,
    },
    /// No repeat was found along at least one axis and taking the whole image as one repeat gives
    /// more yarns a side than a weave photographed whole has ([`PrepOptions::max_photo_yarns`]):
    /// fitting such a grid takes minutes and recovers nothing.
    #[error(
        "no repeat of the weave found: {}; taking the whole image as one repeat would give {n_e}×{n_a} yarns (weft × warp), more than the {max} a side a weave repeats within; try a sharper, evenly lit close-up that shows at least 2 repeats each way (zoom out if each yarn spans more than ~60 px, in if less than ~8 px), straighten the cloth so the yarns run along the image edges, or fit a crop of exactly one repeat with `woven fit --no-prep --grid NExNA`",
        match repeated { [false, false] => "the pattern does not repeat along either axis", [true, false] => "the pattern does not repeat along y (the wefts)", _ => "the pattern does not repeat along x (the warps)" }
    )]
    TooManyYarns {
        /// Weft yarns (rows) the grid would hold.
        n_e: usize,
        /// Warp yarns (columns) the grid would hold.
        n_a: usize,
        /// [`PrepOptions::max_photo_yarns`].
        max: usize,
        /// Whether a repeat was found along x and y.
        repeated: [bool; 2],
    },
}

/// Options of [`prepare`].
#[derive(Clone, Debug)]
pub struct PrepOptions {
    /// Rotate so that yarns are axis-aligned (Radon transform).
    pub rectify: bool,
    /// Also remove slight perspective (needs `rectify`).
    pub perspective: bool,
    /// Average the aligned repeats (otherwise the regularized image is just the blurred one).
    pub regularize: bool,
    /// Settings of the mean of the aligned repeats ([`regularize::mean_of_repeats`]).
    pub repeats: RepeatParams,
    /// Minimum normalised autocorrelation at the pitch of both integral projections; below it the
    /// image is rejected with [`PrepError::NoStructure`].
    pub min_structure: f32,
    /// Minimum DMF correlation of a copy for it to count as a repeat (else: whole image).
    pub min_period_corr: f32,
    /// A copy whose correlation is below [`Self::min_period_corr`] still counts as a repeat when
    /// it exceeds the median correlation of the other yarn-pitch multiples by this much
    /// ([`period::PitchBaseline`]); 0 disables the relative test.
    pub min_period_excess: f32,
    /// Smallest correlation a copy accepted by the relative test may have.
    pub min_period_corr_relative: f32,
    /// When no repeat is found along either axis, the image is taken as one repeat only if the
    /// grid strength of both axes reaches this; below it the image is rejected with
    /// [`PrepError::NoRepeat`]. Measured on forward-model renders and noise: single repeats whose
    /// grid prep recovers exactly score ≥ 0.84 on both axes; white, blurred and coloured noise of
    /// 64–400 px score at most 0.64 on their weaker axis (and then yield random 2–6 yarn grids).
    pub min_single_repeat_structure: f32,
    /// Smallest yarn pitch considered, pixels.
    pub min_pitch: f32,
    /// Most yarns a side of the grid: more is refused with [`PrepError::TooManyYarns`]. The named
    /// weaves repeat within 8 yarns (satin 8) and a figured repeat a user crops by hand rarely
    /// exceeds 12; a larger grid means the repeat was not found and the whole photo became the
    /// pattern.
    pub max_photo_yarns: usize,
}

impl Default for PrepOptions {
    fn default() -> Self {
        Self {
            rectify: true,
            perspective: true,
            regularize: true,
            repeats: RepeatParams::default(),
            min_structure: 0.35,
            min_period_corr: 0.7,
            min_period_excess: 0.15,
            min_period_corr_relative: 0.4,
            min_single_repeat_structure: 0.8,
            min_pitch: 4.0,
            max_photo_yarns: 12,
        }
    }
}

/// An axis-aligned pixel rectangle.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct CropRect {
    /// Left column.
    pub x: u32,
    /// Top row.
    pub y: u32,
    /// Width.
    pub w: u32,
    /// Height.
    pub h: u32,
}

/// Output of [`prepare`]. All geometry is in pixels of the rectified image.
#[derive(Clone, Debug, Serialize)]
pub struct Prepared {
    /// Rotated, perspective-corrected and cropped input.
    #[serde(skip)]
    pub rectified: Rgb32FImage,
    /// Blurred `rectified` replaced by the mean of its aligned repeats (same size; see
    /// [`regularize`]).
    #[serde(skip)]
    pub regularized: Rgb32FImage,
    /// Size of `rectified`.
    pub width: u32,
    /// Size of `rectified`.
    pub height: u32,
    /// Dominant weft direction in the input, degrees in [−45, 45) (weft along `(cos, sin)`).
    pub angle_deg: f32,
    /// Maps rectified pixel `(u, v, 1)` to input pixel coordinates.
    pub homography: Homography,
    /// Whether a perspective correction is part of `homography`.
    pub perspective_applied: bool,
    /// Warp yarn pitch (centre to centre), i.e. spacing of boundaries along x.
    pub pitch_x: f32,
    /// Weft yarn pitch, spacing of boundaries along y.
    pub pitch_y: f32,
    /// x of the first warp boundary, in `[0, pitch_x)`.
    pub phase_x: f32,
    /// y of the first weft boundary, in `[0, pitch_y)`.
    pub phase_y: f32,
    /// Minimum pattern width in pixels (whole width when `repeated_x` is false).
    pub period_x: f32,
    /// Minimum pattern height in pixels (whole height when `repeated_y` is false).
    pub period_y: f32,
    /// Whether a repeat was found along x.
    pub repeated_x: bool,
    /// Whether a repeat was found along y.
    pub repeated_y: bool,
    /// DMF correlation of the repeat along x / y (0 when not repeated).
    pub period_strength: [f32; 2],
    /// Periodicity strength of the integral projections along x / y.
    pub grid_strength: [f32; 2],
    /// Number of weft yarns (pattern rows).
    pub n_e: usize,
    /// Number of warp yarns (pattern columns).
    pub n_a: usize,
    /// The weave's own repeat `[n_e, n_a]` where the colours repeat over more yarns
    /// (`colour_repeat`: yarn-dyed stripes and checks; then `n_e`, `n_a` are the colours' repeat,
    /// a multiple of it); `None` where the weave's repeat is the crop's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub weave_repeat: Option<[usize; 2]>,
    /// Minimum-pattern crop aligned to the yarn boundaries: `n_a` pitches by `n_e` pitches.
    pub crop: CropRect,
    /// Where each repeat of the rectified photo sits against the mean repeat ([`RepeatDrift`]):
    /// what `regularized` leaves out and the registered fit puts back.
    pub drift: RepeatDrift,
    /// The working view of a large photo that was prepared instead of the photo itself
    /// ([`working_scale`]: the photo box-averaged, perhaps a window of it); all the geometry above
    /// is in its pixels except `homography`, which maps to the photo's. `None`: the photo itself.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub working: Option<WorkingView>,
}

fn check_input(img: &Rgb32FImage) -> Result<(), PrepError> {
    let (w, h) = img.dimensions();
    if w < MIN_SIZE || h < MIN_SIZE {
        return Err(PrepError::TooSmall { width: w, height: h, min: MIN_SIZE });
    }
    if let Some(i) = img.as_raw().iter().position(|v| !v.is_finite()) {
        let p = (i / 3) as u32;
        return Err(PrepError::NonFinite { x: p % w, y: p / w });
    }
    Ok(())
}

/// Start and length of the crop along one axis: `n` pitches starting on a yarn boundary, the
/// candidate closest to the image centre.
fn crop_axis(phase: f32, pitch: f32, n: usize, extent: u32) -> (u32, u32) {
    let len = ((n as f32 * pitch).round() as u32).clamp(1, extent);
    let mut best: Option<(f32, u32)> = None;
    let mut k = -1i32;
    loop {
        let s = phase + k as f32 * pitch;
        if s + len as f32 > extent as f32 + 0.5 {
            break;
        }
        if s >= -0.5 {
            let d = (s + len as f32 / 2.0 - extent as f32 / 2.0).abs();
            let start = (s.round().max(0.0) as u32).min(extent - len);
            if best.is_none_or(|(bd, _)| d < bd) {
                best = Some((d, start));
            }
        }
        k += 1;
    }
    (best.map_or((extent - len) / 2, |b| b.1), len)
}

/// Runs the whole preparation stage on a linear RGB image. See the module docs.
///
/// Errors: [`PrepError::TooSmall`] (< 32 px) and [`PrepError::TooSmallAfterRectify`],
/// [`PrepError::NonFinite`], and — both starting with "no periodic yarn structure found" —
/// [`PrepError::NoStructure`] for uniform images or anything whose integral projections are not
/// periodic, [`PrepError::NoRepeat`] for images (noise) with neither a repeat nor a strong grid.
///
/// A photo larger than [`working_scale::WORK_SIDE`] is prepared on a box-averaged working view of
/// it ([`working_scale`]), in seconds instead of minutes; the homography still maps to the photo.
pub fn prepare(img: &Rgb32FImage, opts: &PrepOptions) -> Result<Prepared, PrepError> {
    check_input(img)?;
    working_scale::prepare_scaled(img, |view| prepare_view(view, opts))
}

/// [`prepare`] on the pixels given (the photo, or a working view of it).
fn prepare_view(img: &Rgb32FImage, opts: &PrepOptions) -> Result<Prepared, PrepError> {
    // 1. Rectification.
    let rect = if opts.rectify {
        rectify::rectify(img, opts.perspective)
    } else {
        rectify::Rectified {
            image: img.clone(),
            angle_deg: 0.0,
            homography: crate::math::linalg::IDENTITY,
            perspective_applied: false,
            shear_deg: 0.0,
        }
    };
    let r = &rect.image;
    let (w, h) = r.dimensions();
    if w < MIN_SIZE || h < MIN_SIZE {
        let (in_width, in_height) = img.dimensions();
        return Err(PrepError::TooSmallAfterRectify {
            in_width,
            in_height,
            width: w,
            height: h,
            angle_deg: rect.angle_deg,
            min: MIN_SIZE,
        });
    }
    // 2. First pitch estimate and periodicity strength (before any regularization, which
    //    could impose structure on noise).
    let g = Gray::from_rgb(r);
    let (_, std) = g.mean_std();
    if std < 1e-4 {
        return Err(PrepError::NoStructure);
    }
    let gb = blur_gray(&g, 1.0);
    let min_pitch = opts.min_pitch as f64;
    // An axis whose integral projection is not periodic (twills, satins: see
    // `grid::superposed_pitch`) gets its first pitch from the per-line autocorrelations instead.
    // The band level of an axis whose grid was found only with its colour bands divided out
    // (`grid::analyze_axis_banded`): the later steps see the image with those bands removed too.
    let axis0 = |axis_x: bool| -> Option<(AxisGrid, Option<Vec<f64>>, bool)> {
        let a = analyze_axis(&gb, axis_x, min_pitch);
        if a.as_ref().is_some_and(|a| a.strength >= opts.min_structure) {
            return a.map(|a| (a, None, false));
        }
        let best = match (a, grid::analyze_axis_superposed(&gb, axis_x, min_pitch)) {
            (Some(a), Some(b)) => Some(if b.strength > a.strength { b } else { a }),
            (a, b) => a.or(b),
        };
        if best.as_ref().is_some_and(|a| a.strength >= opts.min_structure) {
            return best.map(|a| (a, None, false));
        }
        // Still no periodic profile: a yarn-dyed stripe or check may hide the yarns under its
        // colour steps (`grid::analyze_axis_banded` divides them out with a running median).
        let best = match (best, grid::analyze_axis_banded(&gb, axis_x, min_pitch)) {
            (Some(a), Some((b, level))) if b.strength > a.strength => Some((b, Some(level))),
            (None, Some((b, level))) => Some((b, Some(level))),
            (a, _) => a.map(|a| (a, None)),
        };
        if best.as_ref().is_some_and(|(a, _)| a.strength >= opts.min_structure) {
            return best.map(|(a, level)| (a, level, false));
        }
        // Still none: dark yarns whose profile ripple is swamped by bright floats of the other
        // family in irregular runs repeat in the log luminance (`grid::analyze_axis_log`).
        match (best, grid::analyze_axis_log(&gb, axis_x, min_pitch)) {
            (Some((a, _)), Some(b)) if b.strength > a.strength => Some((b, None, true)),
            (None, Some(b)) => Some((b, None, true)),
            (a, _) => a.map(|(a, level)| (a, level, false)),
        }
    };
    let (mut ax0, band_x, log_x) = axis0(true).ok_or(PrepError::NoStructure)?;
    let (mut ay0, band_y, log_y) = axis0(false).ok_or(PrepError::NoStructure)?;
    // An axis found only in the log luminance is read there again on the regularized picture
    // (below): its luminance profile is the other family's floats, not these yarns.
    let from_log = [log_x, log_y];
    if ax0.strength < opts.min_structure || ay0.strength < opts.min_structure {
        return Err(PrepError::NoStructure);
    }
    let (mut g, mut gb) = (g, gb);
    for (axis_x, level) in [(true, band_x), (false, band_y)] {
        if let Some(level) = level {
            g = grid::divide_lines(&g, axis_x, &level);
            gb = grid::divide_lines(&gb, axis_x, &level);
        }
    }
    // A pitch that spans several yarns (a float's or a repeat's length on twills and satins) is
    // replaced by the one the shifts between the lines of the other family give
    // (`grid::line_shift_yarns`); only the coarser axis is examined, against the finer one. The
    // shift fits its smallest yarn count and every multiple of it; a multiple is taken where the
    // cells hold yarns of their own (thin yarns hidden under the floats: `finer_yarns`), also
    // where the smallest count is the pitch already found (two thin wefts read as one by the
    // profile, as the line shift reads them).
    let coarse_x = ax0.pitch > ay0.pitch;
    let (coarse, fine) = if coarse_x { (&ax0, &ay0) } else { (&ay0, &ax0) };
    if let Some((period, n, _)) = grid::line_shift_yarns(&gb, coarse_x, fine, min_pitch) {
        let (p, cell_phase) = finer_count(r, &gb, coarse_x, fine, period, n, min_pitch);
        if p < 0.7 * coarse.pitch as f64 {
            let (ep, ephase, conf) = grid::edge_grid(&gb, coarse_x, p);
            let (pitch, phase) = if conf >= grid::MIN_EDGE_CONFIDENCE {
                (ep, ephase)
            } else {
                (p, cell_phase.unwrap_or(coarse.phase as f64))
            };
            let fixed = AxisGrid { pitch: pitch as f32, phase: phase as f32, ..coarse.clone() };
            if coarse_x {
                ax0 = fixed;
            } else {
                ay0 = fixed;
            }
        }
    }
    // A pitch that is half the yarns (each yarn cut in two: its halves, or its body and the gap
    // beside it): the finer axis, where it is about half the other, is doubled where the cells'
    // orientations pair its fine lines (`halved_pitch`).
    let fine_x = ax0.pitch < ay0.pitch;
    let doubled = if fine_x {
        halved_pitch::doubled(&gb, &ax0, &ay0, true)
    } else {
        halved_pitch::doubled(&gb, &ay0, &ax0, false)
    };
    let mut doubled_axis = [fine_x && doubled.is_some(), !fine_x && doubled.is_some()];
    if let Some(a) = doubled {
        if fine_x {
            ax0 = a;
        } else {
            ay0 = a;
        }
    } else if let Some((a, b)) = halved_both::doubled(&gb, &ax0, &ay0) {
        // Both pitches half the yarns (an open weave over a ground of another brightness: holes
        // in the gaps and bright crowns alike): the fine lattice's corners alternate along both
        // axes (`halved_both`).
        (ax0, ay0) = (a, b);
        doubled_axis = [true, true];
    }
    // 3. Blur, σ = pitch / 16.
    let pitch0 = 0.5 * (ax0.pitch + ay0.pitch);
    let blurred = blur_rgb(r, pitch0 / 16.0);
    // 4. Minimum pattern size (DMF).
    let (mut per_x, mut per_y) = detect_period(
        &flatten_for_period(&g, ax0.pitch.max(ay0.pitch) as f64, pitch0 as f64),
        // A repeat holds at least two yarns each way (n = 1 would mean the yarns never
        // interlace), so lags below 1.5 pitches are not candidates.
        1.5 * ax0.pitch as f64,
        1.5 * ay0.pitch as f64,
        opts.min_period_corr as f64,
        [ax0.pitch, ay0.pitch].map(|pitch| {
            (opts.min_period_excess > 0.0).then_some(PitchBaseline {
                pitch: pitch as f64,
                min_excess: opts.min_period_excess as f64,
                min_corr: opts.min_period_corr_relative as f64,
            })
        }),
    );
    // 4b. The repeat of the cells (which yarn is on top), where it is clear: it overrides the
    //     pixel DMF, whose minima are set by what all cells share (see `cells`).
    let cm =
        cells::crossing_centred_matrix(&gb, [ax0.pitch as f64, ay0.pitch as f64], [ax0.phase as f64, ay0.phase as f64]);
    let mut n_cells = [None; 2];
    if let Some(m) = &cm {
        for (k, (axis_x, per, a)) in [(true, &mut per_x, &ax0), (false, &mut per_y, &ay0)].into_iter().enumerate() {
            let n_dmf = (per.period / a.pitch).round() as usize;
            // A repeat seen only 1.5–2 times is weaker evidence than the pixel period (a drifting
            // grid can pass it), so it is taken only where there is no pixel repeat or the cells
            // contradict it: the pixel period's shift is no copy of the cells (a satin's rows
            // all look alike in the pixels, its cells shifted by 2 rows correlate below 0).
            // So is a pixel period whose multiple is a far better copy of the cells (a twill's
            // repeat inside a herringbone: `cells::CellMatrix::partial_copy`).
            let dmf_contradicted = !per.repeated
                || m.shift_corr(axis_x, n_dmf).is_none_or(|c| c < cells::MIN_CELL_CORR)
                || m.partial_copy(axis_x, n_dmf);
            let found = m
                .repeat(axis_x, opts.max_photo_yarns)
                .or_else(|| dmf_contradicted.then(|| m.partial_repeat(axis_x, opts.max_photo_yarns)).flatten());
            if std::env::var_os("WOVEN_TRACE_PREP").is_some() {
                let c: Vec<String> = (1..=m.cols.max(m.rows))
                    .filter_map(|n| m.shift_corr(axis_x, n).map(|c| format!("{n}:{c:.2}")))
                    .collect();
                eprintln!(
                    "prep 4b axis_x={axis_x} n_dmf={n_dmf} pixel_repeated={} dmf_contradicted={dmf_contradicted} found={found:?} shifts {}",
                    per.repeated,
                    c.join(" ")
                );
            }
            if let Some((n, c)) = found {
                let at_dmf = m.shift_corr(axis_x, n_dmf);
                if pixel_period_stands(per.repeated && !dmf_contradicted, n_dmf, (n, c), at_dmf) {
                    n_cells[k] = Some(n_dmf);
                } else {
                    if !per.repeated || n_dmf != n {
                        *per = period::AxisPeriod { period: n as f32 * a.pitch, strength: c as f32, repeated: true };
                    }
                    n_cells[k] = Some(n);
                }
            }
        }
    }
    // 4c. A repeat found along one axis only: the named weaves repeat in a square (n × n cells),
    //     so the other axis's one predicted shift is tested on the cells (`cells::CellMatrix::
    //     square_repeat`), where the image is too short along it for a search over every shift.
    if let Some(m) = &cm {
        let n_of = |per: &period::AxisPeriod, a: &AxisGrid, k: usize| {
            per.repeated.then(|| n_cells[k].unwrap_or_else(|| (per.period / a.pitch).round() as usize))
        };
        let (nx, ny) = (n_of(&per_x, &ax0, 0), n_of(&per_y, &ay0, 1));
        for (k, (axis_x, per, a, n_other)) in
            [(true, &mut per_x, &ax0, ny), (false, &mut per_y, &ay0, nx)].into_iter().enumerate()
        {
            if per.repeated {
                continue;
            }
            if let Some(n) = n_other {
                // Or the step from line to line of a twill or satin, which needs no copy of the
                // whole repeat in view (`cells::CellMatrix::step_repeat`).
                let found = m.square_repeat(axis_x, n).map(|c| (n, c)).or_else(|| m.step_repeat(axis_x, n));
                if let Some((n, c)) = found {
                    *per = period::AxisPeriod { period: n as f32 * a.pitch, strength: c as f32, repeated: true };
                    n_cells[k] = Some(n);
                }
            }
        }
    }
    // 4c'. An axis seen less than 1.5 repeats whose lines are not shifted copies (a basket, a
    //      rib), with no repeat or a pixel repeat the cells contradict: the other axis's repeat
    //      taken where its few lines of overlap are a copy and no shorter period fits the lines
    //      in view (`short_repeat`).
    if let Some(m) = &cm {
        let confirmed = |axis_x: bool, per: &period::AxisPeriod, a: &AxisGrid, k: usize| -> Option<usize> {
            if let Some(n) = n_cells[k] {
                return Some(n);
            }
            let n = (per.period / a.pitch).round() as usize;
            (per.repeated && m.shift_corr(axis_x, n).is_some_and(|c| c >= cells::MIN_CELL_CORR)).then_some(n)
        };
        let (nx, ny) = (confirmed(true, &per_x, &ax0, 0), confirmed(false, &per_y, &ay0, 1));
        for (k, (axis_x, per, a, n_other)) in
            [(true, &mut per_x, &ax0, ny), (false, &mut per_y, &ay0, nx)].into_iter().enumerate()
        {
            let own = if k == 0 { nx } else { ny };
            if own.is_some() {
                continue;
            }
            if let Some(n) = n_other {
                if let Some(c) = short_repeat::square_over_few_lines(m, axis_x, n) {
                    *per = period::AxisPeriod { period: n as f32 * a.pitch, strength: c as f32, repeated: true };
                    n_cells[k] = Some(n);
                }
            }
        }
    }
    // 4d. Still no repeat on either axis: a weft- (or warp-) faced weave whose cells all show the
    //     same family on top, read from where its floats end (`cells::float_end_matrix`).
    if !per_x.repeated && !per_y.repeated {
        if let Some(m) = &cm {
            let floats_x = median(m.o.clone()) > 0.0;
            let pitch = [ax0.pitch as f64, ay0.pitch as f64];
            if let Some(f) = cells::float_end_matrix(&gb, pitch, [ax0.phase as f64, ay0.phase as f64], floats_x) {
                let found = [true, false].map(|axis_x| f.repeat(axis_x, opts.max_photo_yarns));
                let found = match found {
                    [Some(x), None] => [Some(x), f.square_repeat(false, x.0).map(|c| (x.0, c))],
                    [None, Some(y)] => [f.square_repeat(true, y.0).map(|c| (y.0, c)), Some(y)],
                    other => other,
                };
                for (k, (per, a)) in [(&mut per_x, &ax0), (&mut per_y, &ay0)].into_iter().enumerate() {
                    if let Some((n, c)) = found[k] {
                        *per = period::AxisPeriod { period: n as f32 * a.pitch, strength: c as f32, repeated: true };
                        n_cells[k] = Some(n);
                    }
                }
            }
        }
    }
    // 4e. Yarn-dyed stripes and checks: the colours may repeat over a multiple of the weave's
    //     repeat, which the grey, flattened search above does not see (`colour_repeat`).
    let (mut weave_n, mut coloured) = ([0usize; 2], false);
    for (k, (along_y, per, a)) in [(false, &mut per_x, &ax0), (true, &mut per_y, &ay0)].into_iter().enumerate() {
        if !per.repeated {
            continue;
        }
        let n = n_cells[k].unwrap_or_else(|| (per.period / a.pitch).round() as usize);
        let c = colour_repeat::yarn_colours(
            &blurred,
            [ax0.pitch as f64, ay0.pitch as f64],
            [ax0.phase as f64, ay0.phase as f64],
            along_y,
        );
        weave_n[k] = n;
        if let Some(q) = colour_repeat::colour_repeat(&c, n, opts.max_photo_yarns) {
            *per =
                period::AxisPeriod { period: q as f32 * per.period / n as f32, strength: per.strength, repeated: true };
            n_cells[k] = Some(q);
            coloured = true;
        }
    }
    // Without a repeat on either axis the whole image is one repeat, which only a strong yarn grid
    // justifies: noise passes the first structure test often enough (its integral projections
    // have some autocorrelation at any lag) and would otherwise come out as a small random grid.
    if !per_x.repeated && !per_y.repeated && ax0.strength.min(ay0.strength) < opts.min_single_repeat_structure {
        return Err(PrepError::NoRepeat {
            period_strength: [per_x.strength, per_y.strength],
            grid_strength: [ax0.strength, ay0.strength],
            min_period: opts.min_period_corr,
            min_grid: opts.min_single_repeat_structure,
        });
    }
    // 5. Mean of the aligned repeats.
    let (regularized, drift) = if opts.regularize {
        regularize::mean_of_repeats(&blurred, [ax0.pitch, ay0.pitch], per_x.period, per_y.period, &opts.repeats)
    } else {
        (blurred, RepeatDrift::default())
    };
    // 6. Grid on the regularized image (falls back to the first estimate if inconsistent).
    let gr = Gray::from_rgb(&regularized);
    let pick = |a: Option<AxisGrid>, a0: &AxisGrid| -> AxisGrid {
        a.filter(|a| (a.pitch / a0.pitch - 1.0).abs() < 0.2).unwrap_or_else(|| a0.clone())
    };
    // A repeat read from the cells fixes the yarn count: a second-pass pitch that would change it
    // is a different lattice of the regularized image (e.g. floats), not a finer estimate.
    let keep_n = |a: AxisGrid, a0: &AxisGrid, per: &period::AxisPeriod, n: Option<usize>| -> AxisGrid {
        match n {
            Some(n) if (per.period / a.pitch).round() as usize != n => a0.clone(),
            _ => a,
        }
    };
    // An axis doubled by `halved_pitch` keeps the cells' grid where this second pass puts its
    // boundaries more than a quarter of a yarn off it: the profile read here is the one that was
    // read at half the yarns, and on the regularized picture its boundaries can still fall on the
    // half-yarn lines (the seed-2525 satin 5's weft boundaries came back through the middle of
    // the wefts). Where the two agree the second pass refines the grid as on any axis.
    let second = |axis_x: bool, a0: &AxisGrid, per: &period::AxisPeriod, n: Option<usize>| -> AxisGrid {
        let again = if from_log[usize::from(!axis_x)] { grid::analyze_axis_log } else { analyze_axis };
        let a = keep_n(pick(again(&gr, axis_x, min_pitch), a0), a0, per, n);
        let off = (a.phase - a0.phase).rem_euclid(a0.pitch);
        if doubled_axis[usize::from(!axis_x)] && off.min(a0.pitch - off) > 0.25 * a0.pitch {
            return a0.clone();
        }
        a
    };
    let ax = second(true, &ax0, &per_x, n_cells[0]);
    let ay = second(false, &ay0, &per_y, n_cells[1]);
    let n_a = ((per_x.period / ax.pitch).round() as usize).max(1);
    let n_e = ((per_y.period / ay.pitch).round() as usize).max(1);
    if n_e.max(n_a) > opts.max_photo_yarns {
        return Err(PrepError::TooManyYarns {
            n_e,
            n_a,
            max: opts.max_photo_yarns,
            repeated: [per_x.repeated, per_y.repeated],
        });
    }
    // The crop spans one period: when a repeat was found its length is the DMF period (measured
    // over the whole image, finer than n pitches of the local grid); the start is a boundary.
    let span =
        |per: &period::AxisPeriod, pitch: f32, n: usize| if per.repeated { per.period / n as f32 } else { pitch };
    let (cx, cw) = crop_axis(ax.phase, span(&per_x, ax.pitch, n_a), n_a, w);
    let (cy, ch) = crop_axis(ay.phase, span(&per_y, ay.pitch, n_e), n_e, h);
    Ok(Prepared {
        rectified: rect.image.clone(),
        regularized,
        width: w,
        height: h,
        angle_deg: rect.angle_deg,
        homography: rect.homography,
        perspective_applied: rect.perspective_applied,
        pitch_x: ax.pitch,
        pitch_y: ay.pitch,
        phase_x: ax.phase,
        phase_y: ay.phase,
        period_x: per_x.period,
        period_y: per_y.period,
        repeated_x: per_x.repeated,
        repeated_y: per_y.repeated,
        period_strength: [per_x.strength, per_y.strength],
        grid_strength: [ax0.strength, ay0.strength],
        n_e,
        n_a,
        weave_repeat: coloured.then_some([weave_n[1], weave_n[0]]),
        crop: CropRect { x: cx, y: cy, w: cw, h: ch },
        drift,
        working: None,
    })
}

/// The yarn pitch along `axis_x` from the line shift's repeat `period` and its smallest yarn
/// count `n`: the count is doubled while the lattice twice as fine holds yarns of its own
/// ([`finer_yarns::holds_yarns_of_its_own`]; at most 8 yarns, at least `min_pitch` and 4 px a
/// yarn), with the phase that puts the finest accepted lattice's cells on the crossings (`None`
/// where the count stays `n`). `other` is the grid across the lines.
fn finer_count(
    img: &Rgb32FImage,
    g: &Gray,
    axis_x: bool,
    other: &AxisGrid,
    period: f64,
    n: usize,
    min_pitch: f64,
) -> (f64, Option<f64>) {
    let (mut n, mut phase) = (n, None);
    while 2 * n <= 8 && period / (2 * n) as f64 >= min_pitch.max(4.0) {
        let q = period / (2 * n) as f64;
        let (_, edge_phase, _) = grid::edge_grid(g, axis_x, q);
        let (op, oph) = (other.pitch as f64, other.phase as f64);
        let (pitch, start) = if axis_x { ([q, op], [edge_phase, oph]) } else { ([op, q], [oph, edge_phase]) };
        match finer_yarns::holds_yarns_of_its_own(img, g, pitch, start, axis_x, 2 * n) {
            Some(p) => (n, phase) = (2 * n, Some(p)),
            None => break,
        }
    }
    (period / n as f64, phase)
}

/// The grey image the repeat is searched on: fibre texture smoothed out (Gaussian σ = pitch/6)
/// and the illumination flattened (divided by a Gaussian blur at σ = 2 × the larger pitch,
/// which keeps the yarn-scale pattern and removes vignetting and uneven light).
///
/// Why: the repeat's correlation `ρ` is limited on real photos by what is not the weave: hairs
/// and fibre twist (different in every repeat) and slow brightness changes across the photo
/// (a vignetted repeat is darker than its copy). Real repeats came out at ρ = 0.5–0.66 against
/// the 0.7 that separates them from partial copies on clean renders; both effects lower ρ of
/// true and partial copies alike, so they are removed rather than lowering the threshold.
fn flatten_for_period(g: &Gray, max_pitch: f64, pitch: f64) -> Gray {
    let fine = blur_gray(g, (pitch / 16.0) as f32);
    let coarse = blur_gray(g, (2.0 * max_pitch) as f32);
    let mut out = fine;
    for (o, c) in out.data.iter_mut().zip(&coarse.data) {
        *o /= c.max(1e-4);
    }
    out
}

/// A picture of what preparation found in `img`, for a user whose photo [`prepare`] refused: the
/// grid overlay ([`Prepared::grid_overlay`]) when preparation succeeds without the grid-size
/// limit, else the rectified image with the yarn boundaries of the first pitch estimate drawn in
/// red along the axes where one was found, else the rectified image alone. `None` only for an
/// image too small or non-finite to rectify.
///
/// A photo larger than [`working_scale::WORK_SIDE`] is drawn at its overview scale
/// ([`working_scale::overview`]).
pub fn diagnostic_overlay(img: &Rgb32FImage, opts: &PrepOptions) -> Option<Rgb32FImage> {
    check_input(img).ok()?;
    let view = working_scale::overview(img.width(), img.height());
    let small;
    let img = if view.is_identity(img.width(), img.height()) {
        img
    } else {
        small = view.extract(img);
        &small
    };
    let unlimited = PrepOptions { max_photo_yarns: usize::MAX, ..opts.clone() };
    if let Ok(p) = prepare(img, &unlimited) {
        return Some(p.grid_overlay());
    }
    let rect = if opts.rectify { rectify::rectify(img, opts.perspective).image } else { img.clone() };
    let (w, h) = rect.dimensions();
    if w < 2 || h < 2 {
        return Some(rect);
    }
    let gb = blur_gray(&Gray::from_rgb(&rect), 1.0);
    let mut out = rect;
    let red = image::Rgb([1.0f32, 0.05, 0.05]);
    for axis_x in [true, false] {
        if let Some(a) = analyze_axis(&gb, axis_x, opts.min_pitch as f64) {
            let extent = if axis_x { w } else { h };
            let mut p = a.phase.rem_euclid(a.pitch.max(1.0));
            while p < extent as f32 {
                let k = (p.round() as u32).min(extent - 1);
                for t in 0..if axis_x { h } else { w } {
                    if axis_x {
                        out.put_pixel(k, t, red);
                    } else {
                        out.put_pixel(t, k, red);
                    }
                }
                p += a.pitch.max(1.0);
            }
        }
    }
    Some(out)
}

impl Prepared {
    /// The rectified image with the yarn boundaries (red, 1 px) and the minimum-pattern box
    /// (green, 2 px) drawn on it.
    pub fn grid_overlay(&self) -> Rgb32FImage {
        let mut img = self.rectified.clone();
        let (w, h) = img.dimensions();
        let red = image::Rgb([1.0f32, 0.05, 0.05]);
        let green = image::Rgb([0.05f32, 1.0, 0.05]);
        let lines = |phase: f32, pitch: f32, extent: u32| -> Vec<u32> {
            let mut v = Vec::new();
            if pitch <= 0.5 {
                return v;
            }
            let mut p = phase;
            while p < extent as f32 {
                if p >= 0.0 {
                    v.push((p.round() as u32).min(extent - 1));
                }
                p += pitch;
            }
            v
        };
        for x in lines(self.phase_x, self.pitch_x, w) {
            for y in 0..h {
                img.put_pixel(x, y, red);
            }
        }
        for y in lines(self.phase_y, self.pitch_y, h) {
            for x in 0..w {
                img.put_pixel(x, y, red);
            }
        }
        let c = self.crop;
        for t in 0..2u32 {
            let (x0, y0) = (c.x + t, c.y + t);
            let x1 = (c.x + c.w).saturating_sub(1 + t).min(w - 1);
            let y1 = (c.y + c.h).saturating_sub(1 + t).min(h - 1);
            for x in x0.min(w - 1)..=x1 {
                img.put_pixel(x, y0.min(h - 1), green);
                img.put_pixel(x, y1, green);
            }
            for y in y0.min(h - 1)..=y1 {
                img.put_pixel(x0.min(w - 1), y, green);
                img.put_pixel(x1, y, green);
            }
        }
        img
    }

    /// Photo pixels per pixel of the preparation's geometry: the working view's factor
    /// ([`working_scale`]), 1 where the photo itself was prepared.
    pub fn working_scale(&self) -> u32 {
        self.working.map_or(1, |v| v.scale)
    }

    /// Everything except the images, as pretty JSON (for `prep.json`).
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("Prepared serializes")
    }

    /// Write the outputs of `woven prep` into `dir` (created if needed): `rectified.png`,
    /// `regularized.png`, `grid.png` ([`Prepared::grid_overlay`]), `crop.png` (the minimum-pattern
    /// crop of the regularized image) and `prep.json`; each file atomically.
    pub fn save(&self, dir: &std::path::Path) -> anyhow::Result<()> {
        use crate::image_io::Image;
        use anyhow::Context;
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        Image::from_rgb32f(&self.rectified).save_png(&dir.join("rectified.png"))?;
        let reg = Image::from_rgb32f(&self.regularized);
        reg.save_png(&dir.join("regularized.png"))?;
        Image::from_rgb32f(&self.grid_overlay()).save_png(&dir.join("grid.png"))?;
        reg.crop(self.crop.x, self.crop.y, self.crop.w, self.crop.h).save_png(&dir.join("crop.png"))?;
        let json = dir.join("prep.json");
        crate::io::write_atomic(&json, self.to_json().as_bytes()).with_context(|| format!("writing {}", json.display()))
    }
}

/// Whether the pixel period of `n_dmf` cells stands against the repeat the cells found
/// (`found`: cells and correlation), given the cells' own correlation at `n_dmf` (`at_dmf`) and
/// whether the pixel period is a repeat the cells do not contradict (`pixel_ok`). It stands
/// where the cells copy it clearly better than the repeat they found, by the excess a repeat
/// needs over the other shifts ([`cells::MIN_CELL_EXCESS`]). Why: the cells' repeat is the
/// smallest shift that passes their tests, and over few columns a shift can pass at the floor
/// by chance: a basket 2 seen over 7 columns found 3 at 0.40 against 0.99 at the pixel period's
/// 4, and preparation cut a 4 × 3 crop (fresh Mitsuba set seed 3434, scene 12). A smaller true
/// repeat inside the pixel period (2 inside 4) copies the cells as well as the period does, so
/// it still wins.
fn pixel_period_stands(pixel_ok: bool, n_dmf: usize, found: (usize, f64), at_dmf: Option<f64>) -> bool {
    pixel_ok && found.0 != n_dmf && at_dmf.is_some_and(|cd| cd > found.1 + cells::MIN_CELL_EXCESS)
}

#[cfg(test)]
mod tests {
    use super::testutil::*;
    use super::*;
    use crate::math::linalg::{apply, mat3_inv, mat3_mul, translation};

    /// The pixel period stands against a cells' repeat that passed at the floor where the cells
    /// copy the period far better (the basket 2 seen over 7 columns), not against a smaller
    /// repeat inside it that copies the cells as well, nor where the cells contradict it.
    #[test]
    fn the_pixel_period_stands_only_where_the_cells_copy_it_clearly_better() {
        assert!(pixel_period_stands(true, 4, (3, 0.40), Some(0.99)));
        assert!(!pixel_period_stands(true, 4, (2, 0.98), Some(0.99)), "a true repeat inside the period");
        assert!(!pixel_period_stands(false, 4, (3, 0.40), Some(0.99)), "cells contradict the period");
        assert!(!pixel_period_stands(true, 4, (3, 0.75), Some(0.99)), "within the excess");
        assert!(!pixel_period_stands(true, 4, (3, 0.40), None), "the period lies beyond the cells");
        assert!(!pixel_period_stands(true, 4, (4, 0.99), Some(0.99)), "the same repeat");
    }

    fn opts_no_persp() -> PrepOptions {
        PrepOptions { perspective: false, ..Default::default() }
    }

    #[test]
    fn rotation_is_recovered_within_half_a_degree() {
        let p = twill22();
        for (i, &a) in [-15.0, -9.7, -3.2, 0.0, 0.8, 6.4, 12.5, 15.0].iter().enumerate() {
            let pitch = [12.0, 16.0, 20.0][i % 3];
            let img = render_rotated(&p, pitch, 256, 256, a);
            let r = rectify::rectify(&img, false);
            assert!((r.angle_deg as f64 - a).abs() < 0.5, "angle {a}: found {}", r.angle_deg);
        }
        // Plain weave and a non-square image.
        let img = render_rotated(&plain(), 14.0, 300, 220, -11.0);
        let r = rectify::rectify(&img, false);
        assert!((r.angle_deg + 11.0).abs() < 0.5, "{}", r.angle_deg);
    }

    /// Camera homography K R K⁻¹ (tilt about x by `pitch_deg`, about y by `yaw_deg`), mapping flat
    /// cloth pixels to image pixels.
    fn camera(w: f64, h: f64, f: f64, pitch_deg: f64, yaw_deg: f64) -> Homography {
        let (sp, cp) = pitch_deg.to_radians().sin_cos();
        let (sy, cy) = yaw_deg.to_radians().sin_cos();
        let rx = [[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]];
        let ry = [[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]];
        let k = [[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]];
        let kinv = mat3_inv(&k).unwrap();
        mat3_mul(&k, &mat3_mul(&mat3_mul(&rx, &ry), &kinv))
    }

    /// Angles (degrees) of the weft lines (t_y = const) and warp lines (t_x = const, measured from
    /// the vertical) in output space, for `c` (output px → texture px) over an output of size w×h.
    fn line_angles(c: &Homography, w: f64, h: f64) -> (Vec<f64>, Vec<f64>) {
        let (_, ty0) = apply(c, w / 2.0, 0.0);
        let (_, ty1) = apply(c, w / 2.0, h);
        let (tx0, _) = apply(c, 0.0, h / 2.0);
        let (tx1, _) = apply(c, w, h / 2.0);
        let mut weft = Vec::new();
        let mut warp = Vec::new();
        for i in 0..5 {
            let f = (i as f64 + 0.5) / 5.0;
            // Line in texture space l → line in output space Cᵀ l; direction (b, −a).
            for is_warp in [false, true] {
                let l =
                    if is_warp { [1.0, 0.0, -(tx0 + f * (tx1 - tx0))] } else { [0.0, 1.0, -(ty0 + f * (ty1 - ty0))] };
                let a = c[0][0] * l[0] + c[1][0] * l[1] + c[2][0] * l[2];
                let b = c[0][1] * l[0] + c[1][1] * l[1] + c[2][1] * l[2];
                let mut ang = (-a).atan2(b).to_degrees();
                if is_warp {
                    ang -= 90.0;
                }
                let ang = (ang + 90.0).rem_euclid(180.0) - 90.0;
                if is_warp {
                    warp.push(ang);
                } else {
                    weft.push(ang);
                }
            }
        }
        (weft, warp)
    }

    fn spread(v: &[f64]) -> f64 {
        v.iter().cloned().fold(f64::MIN, f64::max) - v.iter().cloned().fold(f64::MAX, f64::min)
    }

    #[test]
    fn perspective_tilt_is_removed() {
        let (w, h) = (320u32, 320u32);
        for (k, &(tp, ty, rot)) in [(10.0, 0.0, 0.0), (-7.0, 6.0, 4.0), (3.0, -10.0, -2.0)].iter().enumerate() {
            let pat = if k == 1 { plain() } else { twill22() };
            let pitch = 13.0;
            let cam = camera(w as f64, h as f64, 1.1 * w as f64, tp, ty);
            let (s, c) = f64::to_radians(rot).sin_cos();
            // Cloth frame → image: rotate about the centre, then the camera homography.
            let rotm = mat3_mul(
                &translation(w as f64 / 2.0, h as f64 / 2.0),
                &mat3_mul(
                    &[[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]],
                    &translation(-(w as f64) / 2.0, -(h as f64) / 2.0),
                ),
            );
            let to_img = mat3_mul(&cam, &rotm);
            let to_tex = mat3_inv(&to_img).unwrap();
            let img = render(&pat, pitch, w, h, |x, y| apply(&to_tex, x, y));
            // Without correction the lines visibly converge (the test can fail).
            let (weft0, warp0) = line_angles(&to_tex, w as f64, h as f64);
            assert!(spread(&weft0).max(spread(&warp0)) > 2.0, "{weft0:?} {warp0:?}");
            let pr = prepare(&img, &PrepOptions::default()).expect("prepare");
            assert!(pr.perspective_applied, "case {k}");
            let comp = mat3_mul(&to_tex, &pr.homography);
            let (weft, warp) = line_angles(&comp, pr.width as f64, pr.height as f64);
            assert!(spread(&weft) < 0.5 && spread(&warp) < 0.5, "case {k}: {weft:?} {warp:?}");
            let worst = weft.iter().chain(&warp).fold(0.0f64, |m, a| m.max(a.abs()));
            assert!(worst < 1.0, "case {k}: not axis aligned {weft:?} {warp:?}");
        }
    }

    #[test]
    fn pitch_and_pattern_size_for_four_weaves_at_three_scales() {
        let cases: [(&str, Vec<Vec<u8>>); 4] =
            [("plain", plain()), ("basket2", basket2()), ("twill22", twill22()), ("satin5", satin5())];
        for (name, p) in &cases {
            let (ne, na) = (p.len(), p[0].len());
            for (k, &pitch) in [12.0, 20.0, 32.0].iter().enumerate() {
                let period = pitch * na.max(ne) as f64;
                let size = ((2.3 * period / 0.95).ceil() as u32).max(256);
                let angle = [2.5, -1.5, 0.0][k];
                let img = render_rotated(p, pitch, size, size, angle);
                let pr = prepare(&img, &PrepOptions::default()).unwrap_or_else(|e| panic!("{name} pitch {pitch}: {e}"));
                let msg = format!("{name} pitch {pitch}: {}", pr.to_json());
                assert!((pr.pitch_x as f64 / pitch - 1.0).abs() < 0.02, "{msg}");
                assert!((pr.pitch_y as f64 / pitch - 1.0).abs() < 0.02, "{msg}");
                assert_eq!((pr.n_e, pr.n_a), (ne, na), "{msg}");
                assert!(pr.repeated_x && pr.repeated_y, "{msg}");
            }
        }
    }

    /// Weft-faced satins of hairy yarns (`testutil::hairy_weft_satin`) through the whole path:
    /// the satin's `n × n` and both pitches (the cells' part is tested in
    /// `cells::tests::a_hairy_weft_faced_satin_repeats_in_its_float_ends`).
    #[test]
    fn a_hairy_weft_faced_satin_is_prepared() {
        for seed in 0..3 {
            let img = hairy_weft_satin(5, 2, [40.0, 24.0], 560, 400, 0.06, seed);
            let pr = prepare(&img, &PrepOptions::default()).unwrap_or_else(|e| panic!("seed {seed}: {e}"));
            let j = pr.to_json();
            assert!((pr.pitch_x / 40.0 - 1.0).abs() < 0.03, "seed {seed}: {j}");
            assert!((pr.pitch_y / 24.0 - 1.0).abs() < 0.03, "seed {seed}: {j}");
            assert_eq!((pr.n_e, pr.n_a), (5, 5), "seed {seed}: {j}");
        }
    }

    #[test]
    fn single_repeat_image() {
        // A custom (logo-like) 12×10 pattern with no repeat inside the image.
        use rand::prelude::*;
        let mut rng = StdRng::seed_from_u64(3);
        let custom: Vec<Vec<u8>> = (0..12).map(|_| (0..10).map(|_| rng.random_range(0..2u8)).collect()).collect();
        let img = render_rotated(&custom, 16.0, 160, 192, 3.0);
        let pr = prepare(&img, &PrepOptions::default()).expect("custom single repeat");
        assert!((pr.angle_deg - 3.0).abs() < 0.5, "{}", pr.to_json());
        assert!((pr.pitch_x / 16.0 - 1.0).abs() < 0.02, "{}", pr.to_json());
        assert!(!pr.repeated_x && !pr.repeated_y, "{}", pr.to_json());
        let img = render_flat(&custom, 16.0, 160, 192);
        let pr = prepare(&img, &PrepOptions::default()).expect("custom, axis aligned");
        assert_eq!((pr.n_e, pr.n_a), (12, 10), "{}", pr.to_json());
        // Small single repeats of regular weaves (angle estimation skipped: with only 4–5 yarns
        // a satin's diagonal biases the Radon peak by ~1°, see docs/prep.md).
        let opts = PrepOptions { rectify: false, ..Default::default() };
        let img = render_flat(&satin5(), 32.0, 160, 160);
        let pr = prepare(&img, &opts).expect("single satin repeat");
        assert!(!pr.repeated_x && !pr.repeated_y, "{}", pr.to_json());
        assert_eq!((pr.n_e, pr.n_a), (5, 5), "{}", pr.to_json());
        assert!((pr.pitch_x / 32.0 - 1.0).abs() < 0.02, "{}", pr.to_json());
        let img = render_flat(&twill22(), 20.0, 80, 80);
        let pr = prepare(&img, &opts).expect("single twill repeat");
        assert_eq!((pr.n_e, pr.n_a), (4, 4), "{}", pr.to_json());
    }

    #[test]
    fn a_whole_photo_of_too_many_yarns_is_refused_with_what_to_try() {
        // A figured 16×14 repeat seen once: no repeat, and 16 yarns a side is more than a photo's
        // weave repeats within, so it is refused instead of becoming a minutes-long fit.
        use rand::prelude::*;
        let mut rng = StdRng::seed_from_u64(5);
        let custom: Vec<Vec<u8>> = (0..16).map(|_| (0..14).map(|_| rng.random_range(0..2u8)).collect()).collect();
        let img = render_flat(&custom, 12.0, 14 * 12, 16 * 12);
        let e = prepare(&img, &PrepOptions::default()).unwrap_err();
        assert!(matches!(e, PrepError::TooManyYarns { n_e: 16, n_a: 14, max: 12, .. }), "{e:?}");
        let msg = e.to_string();
        assert!(
            msg.starts_with("no repeat of the weave found") && msg.contains("16×14") && msg.contains("try "),
            "{msg}"
        );
        // Without the limit the same image is one 16×14 repeat; the overlay draws that grid.
        let big = PrepOptions { max_photo_yarns: 16, ..Default::default() };
        let pr = prepare(&img, &big).unwrap();
        assert_eq!((pr.n_e, pr.n_a), (16, 14));
        let ov = diagnostic_overlay(&img, &PrepOptions::default()).unwrap();
        assert_eq!(ov.dimensions(), pr.rectified.dimensions());
        assert_eq!(ov.as_raw(), pr.grid_overlay().as_raw());
        // A uniform image has no grid: the overlay is the rectified image, with no line drawn.
        let uni = Rgb32FImage::from_pixel(64, 48, image::Rgb([0.4, 0.5, 0.6]));
        let ov = diagnostic_overlay(&uni, &PrepOptions::default()).unwrap();
        assert!(ov.pixels().all(|p| (p.0[1] - 0.5).abs() < 1e-3), "no red line on a uniform image");
        assert!(diagnostic_overlay(&Rgb32FImage::new(8, 8), &PrepOptions::default()).is_none());
    }

    #[test]
    fn a_plain_under_a_wide_stripe_is_prepared() {
        // A cream band over 40 % of a dark plain of soft yarns: the row profile is the band's
        // step (refused as "no regular grid of yarns" before `grid::analyze_axis_banded`).
        for (band, gain) in [((0.3, 0.7), 4.0f32), ((0.15, 0.5), 5.0)] {
            let img = striped_plain([19.0, 14.0], 320, 240, band, gain, 0.3);
            let pr = prepare(&img, &opts_no_persp()).unwrap_or_else(|e| panic!("{band:?}: {e}"));
            let msg = pr.to_json();
            assert!((pr.pitch_y / 14.0 - 1.0).abs() < 0.03 && (pr.pitch_x / 19.0 - 1.0).abs() < 0.03, "{msg}");
            assert_eq!((pr.n_e, pr.n_a), (2, 2), "{msg}");
        }
    }

    #[test]
    fn a_wavy_weave_gets_its_drift_and_the_periodic_picture_follows_it() {
        // A 2/2 twill whose yarns wander by up to 0.25 pitch (3 px), slowly across the image: the mean
        // repeat is one straight repeat, and only the drift puts each repeat back where it lies.
        let pitch = 12.0;
        let tau = std::f64::consts::TAU;
        let wave = |x: f64, y: f64| (x + 3.0 * (tau * y / 300.0).sin(), y + 3.0 * (tau * x / 260.0).sin());
        let img = render(&twill22(), pitch, 320, 320, wave);
        let opts = PrepOptions { rectify: false, ..Default::default() };
        let pr = prepare(&img, &opts).expect("prepare");
        let shift = pr.drift.max_shift();
        assert!((1.5..=4.0).contains(&shift), "largest drift {shift:.2} px; {}", pr.to_json());
        // Against the photo blurred as the regularized image is (σ = pitch/16).
        let reference = blur_rgb(&img, (pitch / 16.0) as f32);
        let straight = psnr(&pr.regularized, &reference);
        let drifted = psnr(&pr.drift.apply(&pr.regularized), &reference);
        assert!(drifted > straight + 2.0, "straight lattice {straight:.2} dB, with the drift {drifted:.2} dB");
        // A straight weave has (almost) none.
        let flat = prepare(&render_flat(&twill22(), pitch, 320, 320), &opts).expect("prepare");
        assert!(flat.drift.max_shift() < 0.3, "{}", flat.drift.max_shift());
    }

    #[test]
    fn regularization_gains_psnr_on_noisy_blurred_input() {
        let clean = render_flat(&twill22(), 12.0, 240, 240);
        let blurred = blur_rgb(&clean, 0.7);
        let noisy = add_noise(&blurred, 0.12, 7);
        let base = psnr(&noisy, &clean);
        // Direct call with the known pitch and period.
        let reg = regularize::regularize(&noisy, [12.0, 12.0], 48.0, 48.0, &RepeatParams::default());
        let gain = psnr(&reg, &clean) - base;
        assert!(gain >= 3.0, "direct: input {base:.2} dB, gain {gain:.2} dB");
        // Whole chain without rectification (same pixel frame).
        let opts = PrepOptions { rectify: false, ..Default::default() };
        let pr = prepare(&noisy, &opts).expect("prepare");
        let gain = psnr(&pr.regularized, &clean) - base;
        assert!(gain >= 3.0, "prepare: gain {gain:.2} dB; {}", pr.to_json());
        // The gain is not just the blur: the mean of the repeats removes most of the noise (measured against the
        // blurred clean image, which is all a denoiser can hope to recover).
        let blur_only = blur_rgb(&noisy, 12.0 / 16.0);
        let (p_noisy, p_blur, p_kpca) =
            (psnr(&noisy, &blurred), psnr(&blur_only, &blurred), psnr(&pr.regularized, &blurred));
        println!("vs blurred clean: noisy {p_noisy:.2} dB, blur only {p_blur:.2} dB, repeat mean {p_kpca:.2} dB");
        assert!(
            p_kpca > p_blur + 6.0 && p_kpca > p_noisy + 10.0,
            "vs blurred clean: noisy {p_noisy:.2}, blur only {p_blur:.2}, kpca {p_kpca:.2}"
        );
    }

    #[test]
    fn uniform_and_noise_are_rejected() {
        let msg = "no periodic yarn structure found: ";
        let uni = Rgb32FImage::from_pixel(128, 96, image::Rgb([0.4, 0.5, 0.6]));
        let e = prepare(&uni, &PrepOptions::default()).unwrap_err();
        assert_eq!(e, PrepError::NoStructure);
        assert!(e.to_string().starts_with(msg) && e.to_string().contains("try "), "{e}");
        for seed in 0..4u64 {
            for size in [(200, 180), (64, 64), (96, 128)] {
                let base = Rgb32FImage::from_pixel(size.0, size.1, image::Rgb([0.5, 0.5, 0.5]));
                let noise = add_noise(&base, 0.2, seed);
                let e = prepare(&noise, &PrepOptions::default()).unwrap_err();
                assert!(e.to_string().starts_with(msg), "seed {seed} {size:?}: {e}");
                // Blurred noise (spatially correlated) too.
                let e = prepare(&blur_rgb(&noise, 2.0), &PrepOptions::default()).unwrap_err();
                assert!(e.to_string().starts_with(msg), "blurred, seed {seed} {size:?}: {e}");
            }
        }
    }

    #[test]
    fn bad_inputs() {
        let small = Rgb32FImage::new(31, 100);
        assert!(matches!(prepare(&small, &PrepOptions::default()), Err(PrepError::TooSmall { width: 31, .. })));
        // A long strip at an angle: the message names the input's own size, not only what is left.
        let strip = render_rotated(&twill22(), 12.0, 2000, 40, 10.0);
        let e = prepare(&strip, &PrepOptions::default()).unwrap_err();
        assert!(matches!(e, PrepError::TooSmallAfterRectify { in_width: 2000, in_height: 40, .. }), "{e:?}");
        assert!(e.to_string().contains("2000x40 px input"), "{e}");
        let mut img = render_flat(&plain(), 12.0, 64, 64);
        img.put_pixel(5, 7, image::Rgb([0.1, f32::NAN, 0.2]));
        assert_eq!(prepare(&img, &PrepOptions::default()).unwrap_err(), PrepError::NonFinite { x: 5, y: 7 });
        img.put_pixel(5, 7, image::Rgb([0.1, f32::INFINITY, 0.2]));
        assert!(prepare(&img, &PrepOptions::default()).is_err());
    }

    #[test]
    fn overlay_and_json() {
        let img = render_flat(&twill22(), 16.0, 200, 200);
        let pr = prepare(&img, &opts_no_persp()).unwrap();
        let ov = pr.grid_overlay();
        assert_eq!(ov.dimensions(), pr.rectified.dimensions());
        let c = pr.crop;
        assert_eq!(ov.get_pixel(c.x, c.y + c.h / 2).0, [0.05, 1.0, 0.05]);
        assert!(c.x + c.w <= pr.width && c.y + c.h <= pr.height);
        assert!((c.w as f32 - 4.0 * pr.pitch_x).abs() <= 1.0);
        let v: serde_json::Value = serde_json::from_str(&pr.to_json()).unwrap();
        assert_eq!(v["n_e"], 4);
        assert_eq!(v["n_a"], 4);
        assert!(v["homography"][2][2].as_f64().is_some());
        assert!(v.get("rectified").is_none());
    }

    /// Length in photo pixels of a step of `d` rectified pixels from `(u, v)` along x (or y).
    fn photo_step(pr: &Prepared, u: f64, v: f64, d: f64, along_x: bool) -> f64 {
        use crate::math::linalg::apply;
        let (x0, y0) = apply(&pr.homography, u, v);
        let (x1, y1) = if along_x { apply(&pr.homography, u + d, v) } else { apply(&pr.homography, u, v + d) };
        (x1 - x0).hypot(y1 - y0)
    }

    /// A photo larger than `WORK_SIDE` whose yarns are wide is prepared on the whole photo
    /// box-averaged (here by 3): the same grid, pitches in working pixels, the homography in the
    /// photo's (a pitch maps to the photo's 72 px, at the photo's angle).
    #[test]
    fn a_large_photo_is_prepared_on_its_box_averaged_view() {
        let img = render_rotated(&twill22(), 72.0, 2400, 1800, 2.0);
        let pr = prepare(&img, &PrepOptions::default()).unwrap();
        let j = pr.to_json();
        let v = pr.working.unwrap_or_else(|| panic!("no working view: {j}"));
        assert_eq!((v.scale, v.x0, v.y0, v.width, v.height), (3, 0, 0, 800, 600), "{j}");
        assert_eq!((pr.n_e, pr.n_a), (4, 4), "{j}");
        assert!((pr.pitch_x / 24.0 - 1.0).abs() < 0.02 && (pr.pitch_y / 24.0 - 1.0).abs() < 0.02, "{j}");
        let (u, v) = (pr.width as f64 / 2.0, pr.height as f64 / 2.0);
        let px = photo_step(&pr, u, v, pr.pitch_x as f64, true);
        assert!((px / 72.0 - 1.0).abs() < 0.02, "a pitch is {px} photo px: {j}");
        let (x0, y0) = crate::math::linalg::apply(&pr.homography, u, v);
        let (x1, y1) = crate::math::linalg::apply(&pr.homography, u + 100.0, v);
        let angle = (y1 - y0).atan2(x1 - x0).to_degrees();
        assert!((angle - 2.0).abs() < 0.5, "weft at {angle}° in the photo: {j}");
        // The refusal's overlay of such a photo is drawn at the same scale.
        let overlay = diagnostic_overlay(&img, &PrepOptions::default()).unwrap();
        assert!(overlay.width() <= working_scale::WORK_SIDE && overlay.height() <= working_scale::WORK_SIDE);
    }

    /// Yarns too fine for the box-averaged whole photo (16 px at full size, 5 px at a third) are
    /// prepared on a window at the photo's centre at the scale that keeps them ~16 px wide.
    #[test]
    fn fine_yarns_of_a_large_photo_are_prepared_on_a_window_at_full_scale() {
        let img = render_rotated(&plain(), 16.0, 2200, 1400, -1.0);
        let pr = prepare(&img, &PrepOptions::default()).unwrap();
        let j = pr.to_json();
        let v = pr.working.unwrap_or_else(|| panic!("no working view: {j}"));
        assert_eq!((v.scale, v.width, v.height), (1, 1024, 1024), "{j}");
        assert_eq!((v.x0, v.y0), ((2200 - 1024) / 2, (1400 - 1024) / 2), "{j}");
        assert_eq!((pr.n_e, pr.n_a), (2, 2), "{j}");
        assert!((pr.pitch_x / 16.0 - 1.0).abs() < 0.02, "{j}");
        let (u, w) = (pr.width as f64 / 2.0, pr.height as f64 / 2.0);
        let py = photo_step(&pr, u, w, pr.pitch_y as f64, false);
        assert!((py / 16.0 - 1.0).abs() < 0.02, "a pitch is {py} photo px: {j}");
        // The rectified centre lies near the photo's centre (the window is centred).
        let (x, y) = crate::math::linalg::apply(&pr.homography, u, w);
        assert!((x - 1100.0).abs() < 40.0 && (y - 700.0).abs() < 40.0, "centre at ({x}, {y}): {j}");
    }

    #[test]
    fn a_basket_seen_once_and_a_quarter_along_its_wider_wefts_gets_the_warps_repeat() {
        // A 3 × 3 basket (6 × 6 cells) with wefts 1.27× the warps' spacing apart (21.3 and 27.1
        // px, the seed-2525 scene 11 layout): 10.6 columns, 8.3 rows of cells in view. Along x
        // the repeat is seen 1.8 times; along y only the other axis's repeat explains the rows.
        // The phases are the render's: its 7 whole rows of cells read A B B B A A A (A, B: the
        // basket's two kinds of row), which a period of 5 rows does not fit. (Read A A B B B A A,
        // 5 rows fit as well as 6 and nothing in view tells them apart.)
        let basket3: Vec<Vec<u8>> = ["001110", "110001", "110001", "110001", "001110", "001110"]
            .iter()
            .map(|r| r.bytes().map(|b| b - b'0').collect())
            .collect();
        let img = render(&basket3, 21.3, 226, 226, |x, y| (x + 39.6, (y - 15.0) * 21.3 / 27.1));
        let pr = prepare(&img, &opts_no_persp()).expect("basket 3 prepared");
        assert_eq!((pr.n_e, pr.n_a), (6, 6), "{}", pr.to_json());
        assert!((pr.pitch_y / 27.1 - 1.0).abs() < 0.03, "{}", pr.pitch_y);
    }

    /// Timing on a 1024² synthetic plain weave at pitch 12 (worst case for the repeat mean: ~1700 repeats).
    /// Run with `cargo test --release -- --ignored timing --nocapture`.
    #[test]
    #[ignore]
    fn timing_1024() {
        let img = render_rotated(&plain(), 12.0, 1024, 1024, 4.0);
        for _ in 0..3 {
            let t = std::time::Instant::now();
            let pr = prepare(&img, &PrepOptions::default()).unwrap();
            println!(
                "1024² plain pitch 12: {:.3} s, n {}×{}, pitch {:.2}",
                t.elapsed().as_secs_f64(),
                pr.n_e,
                pr.n_a,
                pr.pitch_x
            );
        }
    }
}
