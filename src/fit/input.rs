//! The fit's input stage: check the image, prepare it (rectify, regularize, find the grid and the
//! minimum-pattern crop) or take it as one repeat, settle the yarn grid, and resample the crop to
//! the fit's pixels per cell.

use super::capture::{MAX_HOLE_REACH, SPOT_REACH};
use super::options::InputOptions;
use super::target::{
    boundary_phase, cell_phase_given, corner_reach, detect_grid, hole_phase, resample, shift_periodic,
};
use crate::image_io::Image;
use crate::pattern::MAX_SIDE;
use anyhow::{bail, Context, Result};

/// Smallest accepted input side in pixels.
pub const MIN_INPUT_SIDE: u32 = 16;

/// Largest linear value accepted in an input image. The fit compares the input with renders of
/// unit-exposure lights, whose values lie around 0–1 (a bright specular highlight reaches a few
/// tens); an image with values beyond this was not stored in that scale (a sensor's raw counts, a
/// badly exported EXR) and would be fitted as a burnt-out white with a meaningless PSNR.
pub const MAX_INPUT_VALUE: f32 = 1e6;

/// Check an input image before fitting it: at least [`MIN_INPUT_SIDE`] pixels a side, finite
/// values, at least one positive value (an all-black or all-negative image holds no cloth, and
/// its PSNR against a black render would be meaningless) and no value above
/// [`MAX_INPUT_VALUE`] (not a linear image in the renderer's scale).
pub fn check_input(img: &Image) -> Result<()> {
    if img.width < MIN_INPUT_SIDE || img.height < MIN_INPUT_SIDE {
        bail!(
            "input image is {}×{} px; the fit needs at least {MIN_INPUT_SIDE}×{MIN_INPUT_SIDE} (one pattern repeat at a few pixels per yarn)",
            img.width,
            img.height
        );
    }
    img.check_finite("input image").map_err(|e| anyhow::anyhow!("{e}"))?;
    let max = img.data.iter().flatten().copied().fold(f32::NEG_INFINITY, f32::max);
    if max <= 0.0 {
        bail!(
            "input image has no positive value (its largest is {max}): nothing to fit; \
             a photo of cloth needs some light (an EXR with negative or zero values only is not a photo)"
        );
    }
    if max > MAX_INPUT_VALUE {
        bail!(
            "input image has values up to {max:.3e}; is this a linear image? rescale it so that the cloth's \
             values lie around 0–1 (the fit's renders use unit-exposure lights; values above {MAX_INPUT_VALUE:e} are refused)"
        );
    }
    Ok(())
}

/// Preparation's blur σ as a fraction of the yarn pitch (the paper's σ = pitch/16; `prep::prepare`
/// step 3).
pub(crate) const PREP_BLUR_PER_PITCH: f32 = 1.0 / 16.0;

/// The target of a fit.
pub(crate) struct FitTarget {
    /// One repeat of the input (the minimum-pattern crop after preparation).
    pub crop: Image,
    /// Preparation result (when prep ran).
    pub prep: Option<crate::prep::Prepared>,
    /// Yarn grid `(n_e, n_a)` of the crop.
    pub grid: (usize, usize),
    /// The crop resampled to the fit's pixels per cell.
    pub image: Image,
    /// Warnings (a fixed pattern that disagrees with the grid prep found).
    pub warnings: Vec<String>,
    /// Gaussian σ, in pixels of `image`, of the blur the target went through before it was
    /// cropped: preparation's σ = pitch/16 (paper §4, docs/design.md §3 step 4), which is
    /// `c/16` once a pitch is resampled to `c` pixels; 0 without preparation.
    pub blur_px: f32,
}

/// The target of `input` at `c` pixels per cell (see the module docs); with `opts.prep`, the
/// preparation `prepared` when given (done by the caller on `input`), else prepared here.
pub(crate) fn prepare_target(
    input: &Image,
    prepared: Option<crate::prep::Prepared>,
    opts: &InputOptions,
    c: u32,
) -> Result<FitTarget> {
    let (crop, prep, found) = if opts.prep {
        let p = match prepared {
            Some(p) => p,
            None => crate::prep::prepare(&input.to_rgb32f(), &crate::prep::PrepOptions::default())
                .context("preparing the input (use --no-prep for a clean one-repeat crop)")?,
        };
        let reg = Image::from_rgb32f(&p.regularized);
        let crop = reg.crop(p.crop.x, p.crop.y, p.crop.w, p.crop.h);
        let g = (p.n_e, p.n_a);
        (crop, Some(p), Some(g))
    } else {
        (input.clone(), None, opts.grid)
    };
    let mut warnings = Vec::new();
    let grid = settle_grid(&crop, found, opts, &mut warnings)?;
    let image = resample(&crop, grid.1 as u32 * c, grid.0 as u32 * c);
    let blur_px = if prep.is_some() { c as f32 * PREP_BLUR_PER_PITCH } else { 0.0 };
    Ok(FitTarget { crop, prep, grid, image, warnings, blur_px })
}

/// Least strength (see [`boundary_phase`]) of an axis's image cue that decides its phase; below
/// it, the edges do not gather on the yarn boundaries (a front-lit weave whose ply stripes are as
/// strong as its silhouettes, thin yarns well inside their cells) and the model's fold decides.
/// Measured on own renders of six presets under three rigs and on the cross-renderer set: every
/// axis the cue put right had 0.46 or more, every axis it put wrong 0.35 or less.
const BOUNDARY_MIN_STRENGTH: f32 = 0.4;

/// Least concentration (mean resultant length, see [`hole_phase`]) of the back-lit holes' cue
/// along an axis for it to place that axis: the bright pixels must gather in a band of at most
/// about 60 % of the cell around their centre (a uniform band of width `f·c` has resultant
/// `sin(πf)/(πf)`, 0.50 at `f = 0.6`); beyond that they are no lattice of holes.
const HOLE_MIN_CONCENTRATION: f32 = 0.5;

/// Put the target's cell boundaries on the yarn boundaries: estimate the crop's sub-cell phase
/// and shift the crop cyclically by it (the crop is one repeat of a periodic image, so it may
/// start anywhere), then resample the target again. Preparation places its crop on the yarn
/// boundaries it finds, but a grid read from the brightness profiles can land on the yarn centres
/// instead (gaps brighter than the yarns, yarn families of very different brightness), and a crop
/// half a cell off makes every pattern candidate wrong.
///
/// The phase comes from the image's cues where they are trustworthy ([`cue_phase`]); bright
/// spots are not taken for holes where the capture estimated from the photo (`fit::capture`)
/// says, clearly, that they are not ([`front_lit_for_sure`]). The crop rectangle of the
/// preparation moves with the crop, so that the output frames the input as before. Returns the
/// shift in target pixels (fit resolution).
pub(crate) fn align_to_cells(t: &mut FitTarget, model: &Image, c: u32) -> (i32, i32) {
    let capture = t.prep.as_ref().and_then(super::capture::estimate_capture);
    let use_holes = !capture.as_ref().is_some_and(front_lit_for_sure);
    let front_lit = capture.is_some_and(|e| e.capture == super::capture::Capture::Front);
    let (dx, dy) = cue_phase(&t.image, model, c, use_holes, front_lit);
    shift_target(t, (dx, dy), c);
    (dx, dy)
}

/// The sub-cell phase `(dx, dy)` of a one-repeat `image` of `c`-pixel cells (the shift that puts
/// its cell boundaries on the yarn boundaries), axis by axis, from the first cue that can be
/// trusted:
/// 1. the edges ([`boundary_phase`]) where their cue is strong (at least
///    [`BOUNDARY_MIN_STRENGTH`]), so that the phase cannot depend on the fit's starting pattern
///    nor on the fine detail of the model's renders (ply and fibre stripes that a photo or another
///    renderer's image may lack: matched against them, the crops of the cross-renderer set moved
///    4–7 of 16 pixels off a boundary prep had found);
/// 2. the back-lit holes ([`hole_phase`], concentration at least [`HOLE_MIN_CONCENTRATION`]),
///    when the bright spots are holes at the cell corners rather than yarn tops: placed there,
///    they are compact spots (their brightness [`SPOT_REACH`] cells away along either axis at
///    most [`MAX_HOLE_REACH`] of theirs: [`corner_reach`], the rule by which `fit::capture` tells
///    holes from yarn tops on the whole photo, which cannot be used here since it reads the
///    photo on preparation's lattice, the very phase in question), and on an axis whose edge cue
///    is strong they land within a quarter cell of it. A cloth with thin yarns and open holes gives
///    a weak edge cue on at least one axis (the holes' edges, a quarter cell or more from the
///    corners, outweigh the silhouettes), and the model fold of step 3 then put the crops of the
///    own multi-repeat renders a quarter cell off, every pattern candidate with them;
///    `use_holes = false` turns this step off;
/// 3. the model's fold ([`cell_phase_given`] against `model`, a render of any cloth on the grid),
///    searched only along the axes steps 1 and 2 leave open, the others held where those put
///    them: searched over both axes at once, its best on the FabricNET plain W044 sat half a cell
///    off along the x the edges had settled and took y 6 of 16 px off with it;
/// 4. on a front-lit picture (`front_lit`: the capture estimated from the photo, `fit::capture`),
///    each axis step 3 placed is moved by half a cell when its boundaries came out brighter than
///    its yarn centres ([`boundary_luma_contrast`] above [`BOUNDARY_LUMA_FLIP`]). Lit from the
///    camera's side, a yarn is brightest along its top and darkest where it turns away and meets
///    its neighbour or a gap (the cosine fall-off across a tube, the shadowed gap), so the dark
///    lines of the folded luminance are the boundaries. The fold of step 3 matches edges, which
///    cannot tell a boundary from a centre: a soft photo's edges lie half way between the two,
///    and a render's silhouettes match a photo's highlight edges half a cell away. On a crop left
///    on its yarn centres, the fit drives the radius of that family to its lower bound, so that
///    the gap between thin yarns lands where the photo is dark (FabricNET W012: `r_a` 1.00, crop
///    21.1 dB; put back on its boundaries: `r_a` 2.20, 22.9 dB; docs/benchmarks.md, session 16);
/// 5. whatever steps 1–4 decided, the crop moves to the shift at which the cells' colours
///    differ most ([`family_phase`], the spread of the cells' chromaticities,
///    [`cell_chroma_spread`]) where that spread is at least [`FAMILY_MIN_SPREAD`] and
///    [`FAMILY_CLEAR_RATIO`] times the spread here: framed on its yarn boundaries, each cell of
///    a two-colour weave shows one family on top; framed off them, each cell mixes neighbours.
///    Steps 2 and 4 read bright spots, and cannot tell a hole (the background through the gap,
///    at a cell corner) from a crown (a yarn's top, at a cell centre) or a specular spot on it:
///    a two-colour twill over a white background, whose white holes make its boundaries bright
///    under a front light, was moved off them by step 4 (fresh Mitsuba scene 10: exact, 22.6 dB
///    → wrong, 14.4 dB), and the highlights on the crowns of a glossy plain weave under an area
///    light were taken for holes by step 2 (scene 06, x half a cell off, 16.9 dB, both families
///    one muddy colour). The edges of step 1 are strong yet a quarter of a cell off where the
///    light falls on the yarns from all sides but unevenly (an environment light: each yarn
///    bright on one flank and shaded down the other, so the log-luminance gradient gathers on
///    the shaded flank, not at the boundary; a seed-1818 Mitsuba plain weave of orange and grey
///    yarns came out with both families brown, 18.7 dB). Holes and spots add alike to every cell
///    at every phase; the yarn colours do not, and a chromaticity does not change with
///    brightness, so a cloth of one colour gives no evidence and keeps the phase of steps 1–4.
///
/// With the environment variable [`TRACE_PHASE_VAR`] set, the cues and the decision are printed
/// on standard error.
pub(crate) fn cue_phase(image: &Image, model: &Image, c: u32, use_holes: bool, front_lit: bool) -> (i32, i32) {
    let ((bx, by), (sx, sy)) = boundary_phase(image, c);
    let strong = (sx >= BOUNDARY_MIN_STRENGTH, sy >= BOUNDARY_MIN_STRENGTH);
    let trace = std::env::var_os(TRACE_PHASE_VAR).is_some();
    let ci = c.max(1) as i32;
    let apart = |a: i32, b: i32| {
        let d = (a - b).rem_euclid(ci);
        d.min(ci - d)
    };
    let half = |v: i32| (v + ci / 2 + ci / 2).rem_euclid(ci) - ci / 2;
    let mut spots = None;
    let mut settled = (Some(bx), Some(by));
    let mut contrast = None;
    let mut phase = (bx, by);
    if !(strong.0 && strong.1) {
        // Compact spots at the corners, agreeing with the edges on every axis the edges settle.
        spots = hole_phase(image, c);
        let holes = spots.filter(|_| use_holes).filter(|(h, _)| {
            let agree = [(strong.0, h.0, bx), (strong.1, h.1, by)];
            agree.iter().filter(|a| a.0).all(|&(_, h, b)| 4 * apart(h, b) <= ci)
                && corner_reach(image, c, *h, SPOT_REACH) <= MAX_HOLE_REACH
        });
        // Steps 1 and 2, axis by axis.
        let settle = |k: usize| -> Option<i32> {
            if (k == 0 && strong.0) || (k == 1 && strong.1) {
                return Some(if k == 0 { bx } else { by });
            }
            let ((hx, hy), (rx, ry)) = holes?;
            let (h, r) = if k == 0 { (hx, rx) } else { (hy, ry) };
            (r >= HOLE_MIN_CONCENTRATION).then_some(h)
        };
        settled = (settle(0), settle(1));
        phase = if let (Some(x), Some(y)) = settled {
            (x, y)
        } else {
            // Step 3 places only the axes left open, the others held where they are settled.
            let open = cell_phase_given(image, model, c, settled).0;
            let mut phase = (settled.0.unwrap_or(open.0), settled.1.unwrap_or(open.1));
            // Step 4: on a front-lit picture, an open axis whose boundaries came out brighter
            // than its yarn centres is half a cell off.
            if front_lit {
                let k = boundary_luma_contrast(image, c, phase);
                contrast = Some(k);
                if settled.0.is_none() && k.0 > BOUNDARY_LUMA_FLIP {
                    phase.0 = half(phase.0);
                }
                if settled.1.is_none() && k.1 > BOUNDARY_LUMA_FLIP {
                    phase.1 = half(phase.1);
                }
            }
            phase
        };
    }
    let before = phase;
    // Step 5: where the cells' colours tell the yarn families apart, the shift at which they
    // differ most, when it is clearly more than here.
    let here = cell_chroma_spread(image, c, phase);
    let best = family_phase(image, c).unwrap_or((phase, here));
    if best.1 >= FAMILY_MIN_SPREAD && best.1 >= FAMILY_CLEAR_RATIO * here {
        phase = best.0;
    }
    if trace {
        let reach = spots.map(|(h, _)| corner_reach(image, c, h, SPOT_REACH));
        eprintln!(
            "cue_phase: c={c} edges ({bx}, {by}) strength ({sx:.3}, {sy:.3}) spots {spots:?} reach {reach:?} \
             use_holes {use_holes} settled {settled:?} front_lit {front_lit} contrast {contrast:?} \
             steps 1-4 -> {before:?}; chroma spread {here:.2e}, best {:.2e} at {:?} -> {phase:?}",
            best.1, best.0
        );
    }
    phase
}

/// Environment variable which, when set, makes [`cue_phase`] print its cues and its decision on
/// standard error (one line a fit: the survey of the phase rules over a set of images).
pub(crate) const TRACE_PHASE_VAR: &str = "WOVEN_TRACE_PHASE";

/// Least spread of the cells' chromaticities ([`cell_chroma_spread`]) at the phase
/// [`cue_phase`]'s step 5 moves an axis to: the variance of two equal groups of cells whose
/// chromaticities lie `2·√0.001 ≈ 0.063` apart (a plainly visible difference of hue, as between
/// the violet and green of a two-colour plain; grey yarns on a white background lie 0 apart).
/// Below it the cells do not differ by yarn colour and step 5 keeps the phase: on the 20
/// prepared real photos with an open axis the spread stays at or below 0.0008 at every phase
/// tried but on two with coloured families (FabricNET W022, W025: 0.03–0.04, largest at their
/// own phase), cloths of one colour whose cells differ only in brightness (the two mirror-image
/// kinds of corner of a plain weave under a slanting light, which a spread of sRGB values took
/// for families, moving W013, W078 and W081 back off the boundaries step 4 had found); the
/// two-colour renders of the fresh Mitsuba set with an open axis read 0.0013–0.038.
const FAMILY_MIN_SPREAD: f32 = 1e-3;

/// How many times the chromaticity spread here ([`cell_chroma_spread`]) it must reach half a
/// cell over for [`cue_phase`]'s step 5 to move an axis there. Framed half a cell off along one
/// axis, every cell averages two neighbouring cells' tops, which leaves about `(1 + ρ)/2` of the
/// spread (`ρ` the correlation of neighbouring cells' families): 1/2 for a 2/2 twill (ρ = 0),
/// 3/8 for a satin 5, 1/4 for a 2/1 twill, none for a plain weave. 1.5, between no evidence (1)
/// and the uncorrelated case (2), leaves room for blur and for holes that pale every cell alike.
const FAMILY_CLEAR_RATIO: f32 = 1.5;

/// How much the cells of `image` (`c`-pixel cells started at the shift `(dx, dy)`: pixel
/// `(x, y)` lies in cell `((x − dx)/c, (y − dy)/c)`) differ in colour: the variance over the
/// cells of the chromaticity `m / (m_r + m_g + m_b)` of each cell's mean linear colour `m` (the
/// sum of the three components' variances; 0 when every cell has the same chromaticity). Framed
/// on its yarn boundaries, each cell of a weave shows one yarn on top, and cells of two differently
/// coloured families differ; framed half a cell off, each cell mixes two or four crossings
/// (linearly: light adds) and their chromaticities move together. A hole (the background through
/// the gap at a cell corner) or a specular spot on a crown adds alike to every cell at either
/// phase (a quarter hole at each corner, or one whole in the middle; the spot in every cell of
/// its family), so neither pulls this cue the way it pulls the edges, the holes' lattice or the
/// luminance fold. A chromaticity does not change with brightness, so a cloth of one colour
/// gives about 0 at every phase however its cells' shading differs: no evidence.
pub(crate) fn cell_chroma_spread(image: &Image, c: u32, (dx, dy): (i32, i32)) -> f32 {
    let (w, h) = (image.width as i32, image.height as i32);
    let ci = c.max(1) as i32;
    let (nx, ny) = ((w / ci).max(1), (h / ci).max(1));
    let mut sums = vec![[0.0f64; 3]; (nx * ny) as usize];
    for y in 0..h {
        for x in 0..w {
            let p = image.get(x as u32, y as u32);
            let cell =
                (((y - dy).rem_euclid(h) / ci).min(ny - 1) * nx + ((x - dx).rem_euclid(w) / ci).min(nx - 1)) as usize;
            for ch in 0..3 {
                sums[cell][ch] += p[ch].max(0.0) as f64;
            }
        }
    }
    let chroma: Vec<[f64; 3]> = sums
        .iter()
        .filter(|m| m.iter().sum::<f64>() > 0.0)
        .map(|m| {
            let t = m.iter().sum::<f64>();
            m.map(|v| v / t)
        })
        .collect();
    if chroma.len() < 2 {
        return 0.0;
    }
    let n = chroma.len() as f64;
    let mean = [0, 1, 2].map(|ch| chroma.iter().map(|q| q[ch]).sum::<f64>() / n);
    let var = chroma.iter().map(|q| (0..3).map(|ch| (q[ch] - mean[ch]).powi(2)).sum::<f64>()).sum::<f64>() / n;
    var as f32
}

/// The shift `(dx, dy)` (each in `[−c/2, c/2)`) at which the cells of `image` (`c`-pixel cells)
/// differ most in colour ([`cell_chroma_spread`]), and the spread there; `None` for an empty
/// image. Every shift of the cell is tried (one pass over the image each), so the answer does
/// not depend on where the other cues put the crop: a phase a quarter of a cell off, which no
/// half-cell move repairs, is found as readily as one half a cell off. Shifts are ranked by the
/// spread summed over their 3 × 3 neighbourhood (cyclic): where the gaps between thin yarns are
/// dark, moving a cell boundary through a gap hardly changes the cells' colours, and the spread
/// is a plateau whose middle, not its first pixel, is the boundary.
pub(crate) fn family_phase(image: &Image, c: u32) -> Option<((i32, i32), f32)> {
    if image.width == 0 || image.height == 0 {
        return None;
    }
    let ci = c.max(1) as i32;
    let at = |i: i32| i - ci / 2;
    let spread: Vec<f32> = (0..ci * ci).map(|k| cell_chroma_spread(image, c, (at(k % ci), at(k / ci)))).collect();
    let s = |i: i32, j: i32| spread[(j.rem_euclid(ci) * ci + i.rem_euclid(ci)) as usize];
    let mut best: Option<((i32, i32), f32)> = None;
    for j in 0..ci {
        for i in 0..ci {
            let around: f32 = (-1..=1).flat_map(|v| (-1..=1).map(move |u| (u, v))).map(|(u, v)| s(i + u, j + v)).sum();
            if best.is_none_or(|b| around > b.1) {
                best = Some(((i, j), around));
            }
        }
    }
    best.map(|((i, j), _)| ((at(i), at(j)), s(i, j)))
}

/// Least [`boundary_luma_contrast`] (boundaries brighter than the yarn centres, as a fraction of
/// the mean luminance) for which [`cue_phase`] moves an open axis of a front-lit picture by half
/// a cell. Below it the fold's contrast is no evidence either way (a twill whose dark lines are
/// slanted across the crop, a cloth of flat yarns): on 24 prepared real photos, the open
/// axes above it read 0.075–0.15, those left alone −0.46–0.04; the one Mitsuba render with an
/// open front-lit axis, d08, reads −0.003.
const BOUNDARY_LUMA_FLIP: f32 = 0.05;

/// How much brighter the cell boundaries of `image` (`c`-pixel cells), started at the shift
/// `(dx, dy)`, are than the cell centres, along each axis: the cosine coefficient of the first
/// Fourier harmonic of the luminance (sRGB, as [`boundary_phase`] reads it) folded into one cell,
/// `a = (2/c) Σ_u L(u) cos(2π(u + ½)/c)` with `u` the pixel's offset from the boundary, over the
/// mean luminance. Positive: the boundaries are the bright lines; negative: the dark ones.
pub(crate) fn boundary_luma_contrast(image: &Image, c: u32, (dx, dy): (i32, i32)) -> (f32, f32) {
    let (w, h) = (image.width as i32, image.height as i32);
    let ci = c.max(1) as i32;
    let (mut fx, mut fy) = (vec![0.0f64; ci as usize], vec![0.0f64; ci as usize]);
    let mut total = 0.0f64;
    for y in 0..h {
        for x in 0..w {
            let p = image.get(x as u32, y as u32);
            let l = crate::image_io::linear_to_srgb((p[0] + p[1] + p[2]) / 3.0) as f64;
            // Pixel (x, y) of the image lies at (x − dx, y − dy) of the shifted one.
            fx[(x - dx).rem_euclid(ci) as usize] += l;
            fy[(y - dy).rem_euclid(ci) as usize] += l;
            total += l;
        }
    }
    let mean = total / (w as f64 * h as f64).max(1.0);
    let coef = |f: &[f64], across: i32| {
        let n = f.len() as f64;
        let a: f64 = f
            .iter()
            .enumerate()
            .map(|(u, v)| v / across as f64 * (std::f64::consts::TAU * (u as f64 + 0.5) / n).cos())
            .sum::<f64>()
            * 2.0
            / n;
        if mean > 0.0 {
            (a / mean) as f32
        } else {
            0.0
        }
    };
    // Each fold bin sums `across` pixels per cell period: h·(w/c)/… normalised to a mean.
    (coef(&fx, h * (w / ci).max(1)), coef(&fy, w * (h / ci).max(1)))
}

/// Whether the capture estimated from the whole photo says, beyond doubt, that its bright spots
/// are no holes lit from behind: not back-lit (`fit::capture`'s decision), although the two
/// lattices it compares (preparation's yarn crossings and cell centres) differ clearly, by at
/// least `fit::capture`'s back-lit ratio either way. Where they do not, preparation's lattice
/// sits between the holes and the yarn centres (a crop a quarter cell off, the case
/// [`cue_phase`] mends) and mixes both, and the decision says nothing about the spots. A dark
/// front-lit photo whose yarn tops shine in small spots (the FabricNET photo W052: crossings
/// 0.002 against centres 0.028, brightness reach 0.53) is the case this keeps from being framed
/// on its yarn tops.
fn front_lit_for_sure(e: &super::capture::CaptureEstimate) -> bool {
    let (hi, lo) = (e.hole_luma.max(e.centre_luma), e.hole_luma.min(e.centre_luma));
    e.capture == super::capture::Capture::Front && hi >= super::capture::BACKLIT_RATIO * lo.max(1e-6)
}

/// Shift the target cyclically by `(dx, dy)` pixels at `c` pixels per cell (see
/// [`shift_periodic`]): the crop by the same amount at its own resolution, the target resampled
/// from it again, and the preparation's crop rectangle moved along.
pub(crate) fn shift_target(t: &mut FitTarget, (dx, dy): (i32, i32), c: u32) {
    if (dx, dy) == (0, 0) {
        return;
    }
    let (n_e, n_a) = t.grid;
    // The same shift at the crop's own resolution (it is resampled to the fit's afterwards).
    let sx = (dx as f32 * t.crop.width as f32 / (n_a as u32 * c) as f32).round() as i32;
    let sy = (dy as f32 * t.crop.height as f32 / (n_e as u32 * c) as f32).round() as i32;
    t.crop = shift_periodic(&t.crop, sx, sy);
    t.image = resample(&t.crop, n_a as u32 * c, n_e as u32 * c);
    if let Some(p) = t.prep.as_mut() {
        // A crop moved before the image's edge starts one repeat later instead (it is periodic).
        let moved = |at: u32, by: i32, len: u32| {
            let v = at as i64 + by as i64;
            (if v < 0 { v + len as i64 } else { v }) as u32
        };
        p.crop.x = moved(p.crop.x, sx, p.crop.w);
        p.crop.y = moved(p.crop.y, sy, p.crop.h);
    }
}

/// The target read with every yarn as `k` yarns (`paired`: yarns that work in groups, which
/// preparation took for one): the grid `k` times finer, `image` the crop at the fit's pixels per
/// cell on it, and the preparation's pitches, phases and weave repeat on that grid too, so that the
/// output frames and registers the finer grid as the crop it spans.
pub(crate) fn regroup_target(t: &mut FitTarget, k: usize, image: Image) {
    t.grid = (t.grid.0 * k, t.grid.1 * k);
    t.image = image;
    t.blur_px *= k as f32;
    if let Some(p) = t.prep.as_mut() {
        let kf = k as f32;
        (p.pitch_x, p.pitch_y) = (p.pitch_x / kf, p.pitch_y / kf);
        (p.phase_x, p.phase_y) = (p.phase_x.rem_euclid(p.pitch_x), p.phase_y.rem_euclid(p.pitch_y));
        (p.n_e, p.n_a) = (p.n_e * k, p.n_a * k);
        p.weave_repeat = p.weave_repeat.map(|[e, a]| [e * k, a * k]);
    }
}

/// The yarn grid: a fixed pattern's (with a warning where prep found another), else the one
/// found by prep or given, else the one detected in `crop`; refused outside `1..=MAX_SIDE`, or
/// when detected with a side under 2 (no weave fits).
fn settle_grid(
    crop: &Image,
    found: Option<(usize, usize)>,
    opts: &InputOptions,
    warnings: &mut Vec<String>,
) -> Result<(usize, usize)> {
    let mut grid = found;
    if let Some(p) = &opts.pattern {
        if let Some(g) = grid {
            if g != (p.n_e(), p.n_a()) && opts.prep {
                warnings.push(format!(
                    "--pattern is {}×{} but prep found a {}×{} grid; using the pattern's grid",
                    p.n_e(),
                    p.n_a(),
                    g.0,
                    g.1
                ));
            }
        }
        grid = Some((p.n_e(), p.n_a()));
    }
    let (n_e, n_a) = match grid {
        Some(g) => g,
        None => detect_grid(crop)
            .context("cannot detect the yarn grid of the input; pass --grid NExNA or --pattern, or run with prep")?,
    };
    if grid.is_none() && (n_e < 2 || n_a < 2) {
        bail!(
            "the yarn grid detected in the input is {n_e}×{n_a}, which cannot hold a weave (every yarn would float); \
             pass --grid NExNA or --pattern, or run with prep"
        );
    }
    if n_e == 0 || n_a == 0 || n_e > MAX_SIDE || n_a > MAX_SIDE {
        bail!("grid {n_e}×{n_a} is outside 1..={MAX_SIDE}");
    }
    Ok((n_e, n_a))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pattern::WeavePattern;

    /// `v` pixels as an offset from the nearest boundary of `c`-pixel cells, in `[−c/2, c/2)`.
    fn off_boundary(v: i32, c: u32) -> i32 {
        (v + c as i32 / 2).rem_euclid(c as i32) - c as i32 / 2
    }

    /// Whether a crop framed `(sx, sy)` off its cell boundaries and then shifted by `(dx, dy)`
    /// is back on them, to a pixel.
    fn back_on_boundaries((sx, sy): (i32, i32), (dx, dy): (i32, i32), c: u32) -> bool {
        off_boundary(sx + dx, c).abs() <= 1 && off_boundary(sy + dy, c).abs() <= 1
    }

    /// Asserts that `cue_phase` puts `sharp` (a one-repeat picture on its boundaries) back on
    /// them to a pixel, from four framings and under both captures, `model` as the fold's model.
    fn assert_reframed(sharp: &Image, model: &Image, c: u32, use_holes: bool) {
        for (sx, sy) in [(0, 0), (5, -3), (8, 8), (-7, 2)] {
            let img = crate::fit::target::shift_periodic(sharp, sx, sy);
            for front_lit in [false, true] {
                let (dx, dy) = cue_phase(&img, model, c, use_holes, front_lit);
                assert!(
                    back_on_boundaries((sx, sy), (dx, dy), c),
                    "framed ({sx}, {sy}) off, front-lit {front_lit}: shifted by ({dx}, {dy})"
                );
            }
        }
    }

    #[test]
    fn small_or_non_finite_inputs_are_refused() {
        let e = check_input(&Image::filled(8, 20, [0.5; 3])).unwrap_err().to_string();
        assert!(e.contains("8×20") && e.contains("at least 16×16"), "{e}");
        let mut img = Image::filled(16, 16, [0.5; 3]);
        assert!(check_input(&img).is_ok());
        img.data[3][0] = f32::INFINITY;
        assert!(check_input(&img).is_err());
    }

    #[test]
    fn black_negative_or_absurdly_bright_inputs_are_refused() {
        for v in [-0.5, 0.0] {
            let e = check_input(&Image::filled(16, 16, [v; 3])).unwrap_err().to_string();
            assert!(e.contains("no positive value"), "{v}: {e}");
        }
        // One positive pixel in a negative image is enough (a dark photo with a highlight).
        let mut img = Image::filled(16, 16, [-1.0; 3]);
        img.data[7][2] = 0.01;
        assert!(check_input(&img).is_ok());
        // A linear image scaled by 1e30 is refused with a hint; the largest accepted value passes.
        let e = check_input(&Image::filled(16, 16, [0.5e30; 3])).unwrap_err().to_string();
        assert!(e.contains("5.000e29") && e.contains("linear image") && e.contains("rescale"), "{e}");
        assert!(check_input(&Image::filled(16, 16, [MAX_INPUT_VALUE; 3])).is_ok());
    }

    #[test]
    fn a_fixed_pattern_sets_the_grid_and_a_given_grid_is_checked() {
        let crop = Image::filled(32, 32, [0.5; 3]);
        let opts =
            InputOptions { prep: false, grid: Some((9, 9)), pattern: Some(WeavePattern::preset("satin5").unwrap()) };
        let mut w = Vec::new();
        assert_eq!(settle_grid(&crop, opts.grid, &opts, &mut w).unwrap(), (5, 5));
        assert!(w.is_empty(), "no warning without prep: {w:?}");
        let prep = InputOptions { prep: true, ..opts };
        settle_grid(&crop, Some((4, 4)), &prep, &mut w).unwrap();
        assert!(w[0].contains("5×5") && w[0].contains("4×4"), "{w:?}");
        let big = InputOptions { prep: false, grid: Some((2, MAX_SIDE + 1)), pattern: None };
        assert!(settle_grid(&crop, big.grid, &big, &mut w).unwrap_err().to_string().contains("outside"));
        // A uniform image has no yarn grid to detect.
        let none = InputOptions { prep: false, grid: None, pattern: None };
        assert!(settle_grid(&crop, None, &none, &mut w).unwrap_err().to_string().contains("grid"));
    }

    #[test]
    fn the_target_is_resampled_to_the_cells() {
        let img = Image::filled(40, 20, [0.25; 3]);
        let opts = InputOptions { prep: false, grid: Some((2, 4)), pattern: None };
        let t = prepare_target(&img, None, &opts, 6).unwrap();
        assert_eq!((t.grid, t.image.width, t.image.height), ((2, 4), 24, 12));
        assert!(t.prep.is_none() && t.crop.width == 40);
        assert!(t.image.data.iter().all(|p| (p[0] - 0.25).abs() < 1e-6));
    }

    #[test]
    fn a_crop_half_a_cell_off_the_yarn_grid_is_put_back_on_it() {
        use crate::fit::demo::demo_cloth;
        use crate::fit::target::{fit_scene, shift_periodic};
        use crate::render::{render, RenderOptions};
        let truth = demo_cloth();
        let (n_e, n_a) = (truth.pattern.n_e(), truth.pattern.n_a());
        let ro = RenderOptions { threads: Some(1), ..Default::default() };
        let rig = crate::scene::LightRig::default_rig();
        // The crop at 13 px per cell starting 6 px (about half a cell) right and 7 px down of a
        // yarn boundary, as a grid read on the yarn centres gives it; the fit runs at 10 px.
        let sharp = render(&truth, &fit_scene(n_e, n_a, 13, 4, 2, &rig), &ro);
        let crop = shift_periodic(&sharp, 6, 7);
        let c = 10;
        let image = resample(&crop, n_a as u32 * c, n_e as u32 * c);
        let mut t = FitTarget { crop, prep: None, grid: (n_e, n_a), image, warnings: Vec::new(), blur_px: 0.0 };
        let mut model = truth.clone();
        model.pattern = crate::fit::default_twill(n_e, n_a);
        let m = render(&model, &fit_scene(n_e, n_a, c, 4, 3, &rig), &ro);
        let (dx, dy) = align_to_cells(&mut t, &m, c);
        // −5 and +5 are the same sub-cell phase (a whole cell apart: a shift of the pattern).
        let wrap = |v: i32| (v + 5).rem_euclid(10) - 5;
        assert!(wrap(dx + 5).abs() <= 1 && wrap(dy + 5).abs() <= 1, "({dx}, {dy})");
        // The target is now (within a pixel) the unshifted render at the fit's resolution, up to
        // whole cells.
        let want = resample(&sharp, n_a as u32 * c, n_e as u32 * c);
        let best = |img: &Image| {
            let cells = (0..n_e as i32).flat_map(|i| (0..n_a as i32).map(move |j| (j, i)));
            cells.map(|(j, i)| shift_periodic(img, j * c as i32, i * c as i32).psnr_srgb(&want)).fold(0.0f32, f32::max)
        };
        let off = resample(&shift_periodic(&sharp, 6, 7), n_a as u32 * c, n_e as u32 * c);
        assert!(best(&t.image) > best(&off) + 4.0, "{} vs {}", best(&t.image), best(&off));
        assert_eq!((t.crop.width, t.crop.height), (13 * n_a as u32, 13 * n_e as u32));
    }
    /// Smooth two-colour tubes without plies or fibres, as another renderer draws them (the
    /// cross-renderer set): a plain weave at `c` px per cell, grey gaps, the weft red and the warp
    /// blue, shaded like cylinders.
    fn painted_tubes(c: u32) -> Image {
        let (n, r) = (2u32, 0.42 * c as f32);
        let mut data = Vec::new();
        for y in 0..n * c {
            for x in 0..n * c {
                let (i, j) = (y / c, x / c);
                let dx = (x as f32 + 0.5) - (j as f32 + 0.5) * c as f32;
                let dy = (y as f32 + 0.5) - (i as f32 + 0.5) * c as f32;
                let shade = |d: f32| (1.0 - (d / r).powi(2)).max(0.0).sqrt();
                let (warp, weft) = (dx.abs() < r, dy.abs() < r);
                let warp_on_top = (i + j) % 2 == 0;
                data.push(if warp && (warp_on_top || !weft) {
                    [0.1, 0.3, 0.8].map(|v| v * shade(dx))
                } else if weft {
                    [0.8, 0.2, 0.1].map(|v| v * shade(dy))
                } else {
                    [0.3; 3]
                });
            }
        }
        let img = Image::new(n * c, n * c, data);
        Image::from_rgb32f(&crate::prep::image_ops::blur_rgb(&img.to_rgb32f(), 1.5))
    }

    #[test]
    fn tubes_without_plies_framed_half_a_cell_off_go_back_on_their_boundaries_whatever_the_model() {
        use crate::fit::target::fit_scene;
        use crate::render::render;
        let c = 16;
        let sharp = painted_tubes(c);
        let rig = crate::scene::LightRig::default_rig();
        let ro = crate::render::RenderOptions { threads: Some(1), ..Default::default() };
        // The model fold of a render with ply stripes (either start: the plain weave and its
        // inverse) must not pull the phase off the boundaries the image shows.
        for pattern in ["10/01", "01/10"] {
            let model_cloth = crate::fit::preestimate::default_cloth(WeavePattern::parse(pattern).unwrap());
            let model = render(&model_cloth, &fit_scene(2, 2, c, 8, 3, &rig), &ro);
            for (sx, sy) in [(8, 8), (7, -3), (0, 5)] {
                let crop = shift_periodic(&sharp, sx, sy);
                let image = crop.clone();
                let mut t = FitTarget { crop, prep: None, grid: (2, 2), image, warnings: Vec::new(), blur_px: 0.0 };
                let cue = crate::fit::target::boundary_phase(&t.image, c);
                let (dx, dy) = align_to_cells(&mut t, &model, c);
                // Back on the boundaries: the total shift is a whole number of cells (±1 px).
                assert!(
                    back_on_boundaries((sx, sy), (dx, dy), c),
                    "start {pattern}, framed ({sx}, {sy}) off: shifted by ({dx}, {dy}); image cue {cue:?}"
                );
            }
        }
    }

    /// A back-lit twill (the default rig, whose back light shines through the holes) of thin wefts
    /// and wider warps, so that the holes are taller than wide, as in the own multi-repeat renders
    /// whose crops went a quarter cell off; `c` px per cell.
    fn open_backlit_twill(c: u32) -> Image {
        use crate::fit::demo::demo_cloth;
        use crate::fit::target::fit_scene;
        let mut cloth = demo_cloth();
        cloth.pattern = WeavePattern::parse("110/011/101").unwrap();
        (cloth.r_e, cloth.r_a, cloth.n_p) = (2.7, 3.8, 3);
        let ro = crate::render::RenderOptions { threads: Some(1), ..Default::default() };
        crate::render::render(&cloth, &fit_scene(3, 3, c, 4, 2, &crate::scene::LightRig::default_rig()), &ro)
    }

    #[test]
    fn an_open_back_lit_weave_is_put_on_its_boundaries_by_its_holes() {
        use crate::fit::target::{fit_scene, shift_periodic};
        let c = 16;
        let sharp = open_backlit_twill(c);
        let ro = crate::render::RenderOptions { threads: Some(1), ..Default::default() };
        let start = crate::fit::preestimate::default_cloth(crate::fit::default_twill(3, 3));
        let model =
            crate::render::render(&start, &fit_scene(3, 3, c, 8, 3, &crate::scene::LightRig::default_rig()), &ro);
        let mut fold_missed = 0;
        for (sx, sy) in [(0, 5), (4, -3), (-6, 6), (8, 8)] {
            let img = shift_periodic(&sharp, sx, sy);
            // The edges settle x but not y (the holes' edges outweigh the thin wefts' silhouettes).
            let (_, (ex, ey)) = boundary_phase(&img, c);
            assert!(ex >= BOUNDARY_MIN_STRENGTH && ey < BOUNDARY_MIN_STRENGTH, "edge strengths {ex} {ey}");
            // The model's fold, which decided y before, misses the boundary.
            let (fold, _) = cell_phase_given(&img, &model, c, (Some(boundary_phase(&img, c).0 .0), None));
            if off_boundary(sy + fold.1, c).abs() >= 2 {
                fold_missed += 1;
            }
            // The holes put it back: compact spots, agreeing with the edges on x.
            let (dx, dy) = cue_phase(&img, &model, c, true, false);
            assert!(back_on_boundaries((sx, sy), (dx, dy), c), "framed ({sx}, {sy}) off, shifted by ({dx}, {dy})");
            // Without the holes, the fold (x held at the edges' phase) decides y as before.
            assert_eq!(cue_phase(&img, &model, c, false, false).1, fold.1);
        }
        assert!(fold_missed >= 2, "the model fold missed only {fold_missed} of 4");
    }

    /// Soft yarn tops lit from the front, as a blurred photo's mean repeat shows them (`c` px per
    /// cell, 2 × 2 cells): each cell a rounded bump, brightest at its centre and darkest on the
    /// cell boundaries, its sRGB value `0.1 + 0.8·s(u)·s(v)` (the profile the edge cue reads) with `s(u) = (1 + cos πu)/2` and `u, v ∈ [−1, 1]`
    /// across the cell. Its edges gather half way between the boundaries and the centres (the slope
    /// of `s` peaks at `u = ±½`), so their fold has period half a cell, no fundamental, and no
    /// axis is settled by them: the model's fold decides.
    fn soft_front_lit_bumps(c: u32) -> Image {
        let n = 2u32;
        let s = |v: u32| {
            let u = ((v % c) as f32 + 0.5) / c as f32 * 2.0 - 1.0;
            0.5 * (1.0 + (std::f32::consts::PI * u).cos())
        };
        let lin = |l: f32| crate::image_io::srgb_to_linear(l);
        let data = (0..n * c).flat_map(|y| (0..n * c).map(move |x| [lin(0.1 + 0.8 * s(x) * s(y)); 3])).collect();
        Image::new(n * c, n * c, data)
    }

    #[test]
    fn front_lit_boundaries_are_the_dark_lines() {
        let c = 16;
        let img = soft_front_lit_bumps(c);
        let (ax, ay) = boundary_luma_contrast(&img, c, (0, 0));
        assert!(ax < -0.3 && ay < -0.3, "framed on the boundaries: {ax} {ay}");
        let (bx, by) = boundary_luma_contrast(&img, c, (8, 8));
        assert!(bx > 0.3 && by > 0.3, "half a cell off: {bx} {by}");
        // The contrast of a shifted image at the shift that undoes it is the original's.
        let moved = shift_periodic_for_test(&img, 5, -3);
        let (mx, my) = boundary_luma_contrast(&moved, c, (-5, 3));
        assert!((mx - ax).abs() < 1e-4 && (my - ay).abs() < 1e-4, "{mx} {my} vs {ax} {ay}");
    }

    fn shift_periodic_for_test(img: &Image, dx: i32, dy: i32) -> Image {
        crate::fit::target::shift_periodic(img, dx, dy)
    }

    /// Where no image cue settles an axis, the model's fold decides, and it can land the crop on
    /// the yarn centres: the edges it matches (a render's yarn silhouettes) may be a photo's
    /// highlight edges half a cell away, and a soft photo's edges, half way between its
    /// boundaries and centres, fold alike at both phases. Here the model is the picture itself
    /// framed half a cell off, so that the fold lands there for sure. On a front-lit picture the
    /// dark lines are the boundaries, and step 4 puts the crop back on them; not front-lit, the
    /// fold's phase stands (the old behaviour).
    #[test]
    fn a_front_lit_crop_on_its_yarn_centres_goes_back_to_the_dark_boundaries() {
        use crate::fit::target::shift_periodic;
        let c = 16;
        let sharp = soft_front_lit_bumps(c);
        let half_off = shift_periodic(&sharp, 8, 8);
        for (sx, sy) in [(0, 0), (5, -3), (8, 8), (-7, 2), (3, 11)] {
            let img = shift_periodic(&sharp, sx, sy);
            let (_, (ex, ey)) = boundary_phase(&img, c);
            assert!(ex < BOUNDARY_MIN_STRENGTH && ey < BOUNDARY_MIN_STRENGTH, "edge strengths {ex} {ey}");
            let (fx, fy) = cue_phase(&img, &half_off, c, false, false);
            assert!(
                off_boundary(sx + fx, c).abs() >= 7 && off_boundary(sy + fy, c).abs() >= 7,
                "framed ({sx}, {sy}): the fold gave ({fx}, {fy}), not half a cell off"
            );
            let (dx, dy) = cue_phase(&img, &half_off, c, false, true);
            assert!(
                back_on_boundaries((sx, sy), (dx, dy), c),
                "framed ({sx}, {sy}) off: shifted by ({dx}, {dy}), the fold alone ({fx}, {fy})"
            );
        }
        // A crop the fold put on the boundaries stays there.
        let (dx, dy) = cue_phase(&shift_periodic(&sharp, 5, -3), &sharp, c, false, true);
        assert!(off_boundary(5 + dx, c).abs() <= 1 && off_boundary(-3 + dy, c).abs() <= 1, "({dx}, {dy})");
    }

    /// A weave painted as smooth tubes, `c` px per cell: `pattern` rows (1 = warp on top), yarns
    /// `r` cells wide on either side of their axis, linear colours `warp` and `weft` shaded across
    /// the yarn by `shade(d)` (`d` the signed offset from the yarn's axis over `r`, towards +x for
    /// a warp and +y for a weft), the background
    /// `bg` where neither yarn covers (the holes at the cell corners), a specular spot of peak
    /// `spot.0` and σ `spot.1` px added at each crown centre, blurred periodically by `blur` px
    /// (3 × 3 repeats blurred, the middle one kept).
    #[allow(clippy::too_many_arguments)]
    fn painted_weave(
        pattern: &[&[u8]],
        c: u32,
        r: f32,
        (warp, weft, bg): ([f32; 3], [f32; 3], [f32; 3]),
        shade: &dyn Fn(f32) -> f32,
        spot: (f32, f32),
        blur: f32,
    ) -> Image {
        let (n_e, n_a) = (pattern.len() as u32, pattern[0].len() as u32);
        let (w, h) = (3 * n_a * c, 3 * n_e * c);
        let rc = r * c as f32;
        let peak = |a: f32, b: f32| spot.0 * (-(a * a + b * b) / (2.0 * spot.1 * spot.1)).exp();
        let mut data = Vec::with_capacity((w * h) as usize);
        for y in 0..h {
            for x in 0..w {
                let (i, j) = ((y / c) % n_e, (x / c) % n_a);
                let dx = (x % c) as f32 + 0.5 - 0.5 * c as f32;
                let dy = (y % c) as f32 + 0.5 - 0.5 * c as f32;
                let (on_warp, on_weft) = (dx.abs() < rc, dy.abs() < rc);
                let warp_on_top = pattern[i as usize][j as usize] == 1;
                data.push(if on_warp && (warp_on_top || !on_weft) {
                    let s = if warp_on_top { peak(dx, dy) } else { 0.0 };
                    warp.map(|v| v * shade(dx / rc) + s)
                } else if on_weft {
                    let s = if warp_on_top { 0.0 } else { peak(dx, dy) };
                    weft.map(|v| v * shade(dy / rc) + s)
                } else {
                    bg
                });
            }
        }
        let big = Image::from_rgb32f(&crate::prep::image_ops::blur_rgb(&Image::new(w, h, data).to_rgb32f(), blur));
        big.crop(n_a * c, n_e * c, n_a * c, n_e * c)
    }

    /// A 2/2 twill of thin pink and dark blue yarns over a bright grey background, under a front
    /// light (the tubes brightest along their tops), as the fresh Mitsuba scene 10 shows it (its
    /// pink and dark red differ less: chromaticity spread 0.0022 against 0.0014 half a cell off):
    /// the background through the gaps makes large bright holes at the cell corners.
    fn twill_over_bright_holes(c: u32) -> Image {
        let twill: [&[u8]; 4] = [&[1, 1, 0, 0], &[1, 0, 0, 1], &[0, 0, 1, 1], &[0, 1, 1, 0]];
        let colours = ([0.25, 0.02, 0.1], [0.01, 0.02, 0.08], [0.35; 3]);
        painted_weave(&twill, c, 0.33, colours, &|d| 0.3 + 0.7 * (1.0 - d * d).max(0.0).sqrt(), (0.0, 1.0), 2.0)
    }

    #[test]
    fn bright_holes_at_the_corners_do_not_move_a_two_colour_twill_off_its_boundaries_under_a_front_light() {
        use crate::fit::target::shift_periodic;
        let c = 16;
        let sharp = twill_over_bright_holes(c);
        // The picture's own premises: the edges settle x only; on the boundaries the bright holes
        // make the boundaries brighter than the yarn centres along y (step 4 would move y half a
        // cell), and the cells there hold one family each (twice the colour spread half a cell
        // over).
        let (_, (ex, ey)) = boundary_phase(&sharp, c);
        assert!(ex >= BOUNDARY_MIN_STRENGTH && ey < BOUNDARY_MIN_STRENGTH, "edge strengths {ex} {ey}");
        let (_, ky) = boundary_luma_contrast(&sharp, c, (0, 0));
        assert!(ky > BOUNDARY_LUMA_FLIP, "boundary contrast {ky}");
        let (on, half_y) = (cell_chroma_spread(&sharp, c, (0, 0)), cell_chroma_spread(&sharp, c, (0, 8)));
        assert!(on >= FAMILY_MIN_SPREAD && on >= FAMILY_CLEAR_RATIO * half_y, "spreads {on} {half_y}");
        for (sx, sy) in [(0, 0), (5, -3), (-7, 2), (3, 8)] {
            let img = shift_periodic(&sharp, sx, sy);
            // The fold (against the picture itself on its boundaries) puts y right; the holes are
            // vetoed as a front-lit capture's (scene 10: "front-lit for sure").
            let (dx, dy) = cue_phase(&img, &sharp, c, false, true);
            assert!(back_on_boundaries((sx, sy), (dx, dy), c), "framed ({sx}, {sy}) off: shifted by ({dx}, {dy})");
        }
    }

    /// A plain weave of soft violet and green tubes, darkest on the cell boundaries, each crown
    /// with a small specular spot at its top (the fresh Mitsuba scene 06: rough plastic under an
    /// area light, no back light).
    fn glossy_plain(c: u32, spot: f32) -> Image {
        let plain: [&[u8]; 2] = [&[1, 0], &[0, 1]];
        let colours = ([0.07, 0.03, 0.35], [0.01, 0.06, 0.04], [0.0; 3]);
        let cos2 = |d: f32| 0.02 + 0.98 * (std::f32::consts::FRAC_PI_2 * d.min(1.0)).cos().powi(2);
        painted_weave(&plain, c, 0.5, colours, &cos2, (spot, 1.5), 1.0)
    }

    #[test]
    fn specular_spots_on_two_colour_crowns_are_not_taken_for_holes() {
        let c = 16;
        let sharp = glossy_plain(c, 0.5);
        // No axis settled by the edges; the spots pass step 2's test for holes, half a cell off.
        let (_, (ex, ey)) = boundary_phase(&sharp, c);
        assert!(ex < BOUNDARY_MIN_STRENGTH && ey < BOUNDARY_MIN_STRENGTH, "edge strengths {ex} {ey}");
        let ((hx, hy), (rx, ry)) = hole_phase(&sharp, c).unwrap();
        assert!(off_boundary(hx, c).abs() >= 7 && off_boundary(hy, c).abs() >= 7, "spots at ({hx}, {hy})");
        assert!(rx >= HOLE_MIN_CONCENTRATION && ry >= HOLE_MIN_CONCENTRATION, "{rx} {ry}");
        assert!(corner_reach(&sharp, c, (hx, hy), SPOT_REACH) <= MAX_HOLE_REACH);
        assert_reframed(&sharp, &sharp, c, true);
    }

    #[test]
    fn round_two_colour_crowns_half_a_cell_off_go_back_to_their_boundaries() {
        use crate::fit::target::shift_periodic;
        let c = 16;
        let sharp = glossy_plain(c, 0.0);
        let half_off = shift_periodic(&sharp, 8, 8);
        // The fold forced half a cell off: put back by step 4 under a front light, and by the
        // cells' colours (step 5) whatever the light.
        assert_reframed(&sharp, &half_off, c, false);
    }

    /// A plain weave of orange and grey tubes over a black background, lit from every side but
    /// unevenly (an environment light, the seed-1818 Mitsuba scene 06): each yarn is brightest
    /// on its −x / −y flank, where it rises sharply out of the gap, and shades down to the
    /// darkness of the gap on the other.
    fn unevenly_lit_plain(c: u32) -> Image {
        let plain: [&[u8]; 2] = [&[1, 0], &[0, 1]];
        let colours = ([0.6, 0.24, 0.13], [0.3, 0.3, 0.3], [0.02; 3]);
        painted_weave(&plain, c, 0.33, colours, &uneven_flank, (0.0, 1.0), 1.0)
    }

    /// Shading across a yarn under an uneven all-round light: 1 on the lit flank (`d = −1`),
    /// down to 5 % on the other (`d = 1`).
    fn uneven_flank(d: f32) -> f32 {
        0.05 + 0.95 * (0.5 - 0.5 * d.clamp(-1.0, 1.0)).powf(1.5)
    }

    #[test]
    fn strong_edges_a_quarter_cell_off_give_way_to_the_cells_colours() {
        let c = 16;
        let sharp = unevenly_lit_plain(c);
        // The picture's premise: the edges are strong on both axes (step 1 settles both) but
        // gather on the shaded flanks, away from the boundaries.
        let ((bx, by), (ex, ey)) = boundary_phase(&sharp, c);
        assert!(ex >= BOUNDARY_MIN_STRENGTH && ey >= BOUNDARY_MIN_STRENGTH, "edge strengths {ex} {ey}");
        assert!(off_boundary(bx, c).abs().max(off_boundary(by, c).abs()) >= 3, "edges at ({bx}, {by})");
        let ((fx, fy), _) = family_phase(&sharp, c).unwrap();
        assert!(off_boundary(fx, c).abs() <= 1 && off_boundary(fy, c).abs() <= 1, "colours at ({fx}, {fy})");
        assert_reframed(&sharp, &sharp, c, false);
        // One colour, the same light: no evidence, the edges keep their phase.
        let grey = painted_weave(
            &[&[1, 0], &[0, 1]],
            c,
            0.33,
            ([0.3; 3], [0.3; 3], [0.02; 3]),
            &uneven_flank,
            (0.0, 1.0),
            1.0,
        );
        let ((gx, gy), _) = boundary_phase(&grey, c);
        assert_eq!(cue_phase(&grey, &grey, c, false, true), (gx, gy));
    }

    #[test]
    fn the_cells_differ_in_colour_only_on_the_boundaries() {
        let c = 16;
        let img = glossy_plain(c, 0.5);
        let on = cell_chroma_spread(&img, c, (0, 0));
        assert!(on > 10.0 * FAMILY_MIN_SPREAD, "{on}");
        // Half a cell off along either axis, every cell holds half of each family.
        for d in [(8, 0), (0, 8), (8, 8)] {
            let s = cell_chroma_spread(&img, c, d);
            assert!(s < 1e-3 * on, "{d:?}: {s}");
        }
        // One colour: no spread at any phase, however the cells' brightness differs (grey bumps,
        // and the same bumps with every other cell darker); none in a flat image.
        let grey = soft_front_lit_bumps(c);
        let mut uneven = grey.clone();
        for (k, p) in uneven.data.iter_mut().enumerate() {
            let (x, y) = (k as u32 % grey.width, k as u32 / grey.width);
            if (x / c + y / c) % 2 == 1 {
                *p = p.map(|v| 0.5 * v);
            }
        }
        for img in [&grey, &uneven] {
            for d in [(0, 0), (8, 0), (8, 8), (3, -5)] {
                assert!(cell_chroma_spread(img, c, d) < 1e-9, "{d:?}");
            }
        }
        assert_eq!(cell_chroma_spread(&Image::filled(32, 32, [0.4; 3]), c, (3, 5)), 0.0);
    }

    #[test]
    fn only_a_clear_front_lit_capture_vetoes_the_holes() {
        use crate::fit::capture::{Capture, CaptureEstimate};
        let e = |capture, hole_luma, centre_luma| CaptureEstimate {
            capture,
            hole_luma,
            centre_luma,
            crossings: 100,
            bright_share: 0.1,
            reach: 0.5,
        };
        // Dark crossings far below the yarn centres: a front-lit photo.
        assert!(front_lit_for_sure(&e(Capture::Front, 0.002, 0.028)));
        // Lattices within the back-lit ratio of each other: preparation's lattice mixes holes
        // and yarns (a crop a quarter cell off), the decision is no evidence.
        assert!(!front_lit_for_sure(&e(Capture::Front, 0.027, 0.057)));
        assert!(!front_lit_for_sure(&e(Capture::Front, 0.042, 0.052)));
        // Back-lit photos keep their holes.
        assert!(!front_lit_for_sure(&e(Capture::Both, 1.37, 0.24)));
        assert!(!front_lit_for_sure(&e(Capture::Back, 0.86, 0.03)));
    }
}
