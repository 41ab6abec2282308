//! The fit's view of the target: the minimum-pattern crop at `c` pixels per cell, the mapping
//! from pattern cells to pixels, grid detection and colour statistics.

use crate::image_io::Image;
use crate::pattern::WeavePattern;
use crate::scene::{CameraSpec, LightRig, Projection, Scene};

/// Scene whose orthographic camera frames exactly one repeat of an `n_e × n_a` pattern at `c`
/// pixels per cell: cell boundaries fall on pixel boundaries, column `j` of cells is warp `j`,
/// row `r` of cells (from the top) is weft `n_e − 1 − r` (see [`cell_rect`]).
pub fn fit_scene(n_e: usize, n_a: usize, c: u32, spp: u32, seed: u64, lights: &LightRig) -> Scene {
    Scene {
        width: n_a as u32 * c,
        height: n_e as u32 * c,
        spp,
        seed,
        camera: CameraSpec {
            projection: Projection::Orthographic,
            tiles: 1.0,
            rotation_deg: 0.0,
            tilt_deg: 0.0,
            fov_deg: 30.0,
            offset: [0.5, 0.5],
        },
        lights: lights.clone(),
        exposure: 1.0,
        backdrop: None,
        // Point-sampled fibres in the fit's own view: every fit test and evaluation was measured
        // that way. The stratified fibre phase (`Scene::footprint_filter`) is unbiased, but with it
        // on the Levenberg–Marquardt polish of `refine`'s test left `R^B_e` 0.09 off in 15
        // iterations (the loss at the truth is still exactly 0): switching it on for the fit waits
        // for its own measurement on the evaluations.
        footprint_filter: false,
    }
}

/// Pixel rectangle `(x0, y0, x1, y1)` (exclusive ends) of pattern cell `(i, j)` (weft `i`, warp
/// `j`) in a [`fit_scene`] image with `c` pixels per cell.
pub fn cell_rect(n_e: usize, i: usize, j: usize, c: u32) -> (u32, u32, u32, u32) {
    let r = (n_e - 1 - i) as u32;
    (j as u32 * c, r * c, (j as u32 + 1) * c, (r + 1) * c)
}

// The fit's box resampling is the shared one (`tests/grid.rs` and the input stage name it here).
pub use crate::math::resample::resample;

/// Tile an image `nx × ny` times.
pub fn tile(img: &Image, nx: u32, ny: u32) -> Image {
    let (w, h) = (img.width * nx, img.height * ny);
    let data = (0..h).flat_map(|y| (0..w).map(move |x| (x, y))).map(|(x, y)| img.get(x % img.width, y % img.height));
    Image::new(w, h, data.collect())
}

/// Cyclic shift of a periodic image: pixel `(x, y)` of the result is pixel `(x + dx, y + dy)` of
/// `img`, both taken modulo the image size (one repeat of a periodic image can start anywhere).
pub fn shift_periodic(img: &Image, dx: i32, dy: i32) -> Image {
    let (w, h) = (img.width as i32, img.height as i32);
    let data = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .map(|(x, y)| img.get((x + dx).rem_euclid(w) as u32, (y + dy).rem_euclid(h) as u32))
        .collect();
    Image::new(img.width, img.height, data)
}

/// Edge energy folded into one cell: the squared gradient of the sRGB luminance (central
/// differences, wrapping around the repeat), averaged over every cell of an image of `c`-pixel
/// cells at each offset `(u, v)` inside the cell; `c × c` values, row-major by `v`.
///
/// Which yarn lies on top changes from cell to cell, but every cell of a weave has its edges in
/// the same places: the yarns' silhouettes run along the cell boundaries and the gaps (bright
/// where the back light shows through, dark where a background does) sit at the cell corners,
/// while the crowns of the yarns at the cell centres are smooth. The squared gradient does not
/// care whether a gap is brighter or darker than the yarns, nor which colour either family has.
pub fn folded_edges(img: &Image, c: u32) -> Vec<f32> {
    let (w, h) = (img.width as i32, img.height as i32);
    let lum: Vec<f32> = img.data.iter().map(|p| crate::image_io::linear_to_srgb((p[0] + p[1] + p[2]) / 3.0)).collect();
    let at = |x: i32, y: i32| lum[(y.rem_euclid(h) * w + x.rem_euclid(w)) as usize];
    let c = c.max(1) as i32;
    let mut fold = vec![0.0f32; (c * c) as usize];
    for y in 0..h {
        for x in 0..w {
            let gx = 0.5 * (at(x + 1, y) - at(x - 1, y));
            let gy = 0.5 * (at(x, y + 1) - at(x, y - 1));
            fold[((y % c) * c + x % c) as usize] += gx * gx + gy * gy;
        }
    }
    let cells = ((w / c).max(1) * (h / c).max(1)) as f32;
    fold.iter_mut().for_each(|v| *v /= cells);
    fold
}

/// Sub-cell phase of a one-repeat `target` against a `model` render of the same grid at `c`
/// pixels per cell: the cyclic shift `(dx, dy)`, each in `(−c/2, c/2]`, for which
/// [`shift_periodic`]`(target, dx, dy)` has its cell boundaries where the model has them. It
/// maximises the correlation of the two [`folded_edges`] over all `c × c` cyclic shifts (a 2-D
/// cross-correlation of the edge energy folded into one cell), which needs no pattern: a crop that
/// starts half a cell off the yarn grid puts its edges in the middle of the model's cells.
/// Returns the shift and the correlation coefficient it reaches (0 when either fold is flat).
pub fn cell_phase(target: &Image, model: &Image, c: u32) -> ((i32, i32), f32) {
    cell_phase_given(target, model, c, (None, None))
}

/// [`cell_phase`] with the shift along an axis held where `fixed` gives it (`(Some(dx), None)`:
/// only `dy` is searched): the fold then places only the axes nothing else settles. An axis placed
/// by a trustworthy cue must not be moved by the fold's best over both axes, which on a cloth the
/// model does not yet resemble can sit half a cell off along the settled axis and drag the other
/// with it (the FabricNET plain W044: edges settle x at 0, the free fold (8, −6) of 16).
pub fn cell_phase_given(target: &Image, model: &Image, c: u32, fixed: (Option<i32>, Option<i32>)) -> ((i32, i32), f32) {
    let (ft, fm) = (folded_edges(target, c), folded_edges(model, c));
    let centred = |f: &[f32]| {
        let m = f.iter().sum::<f32>() / f.len().max(1) as f32;
        let d: Vec<f32> = f.iter().map(|v| v - m).collect();
        let n = d.iter().map(|v| v * v).sum::<f32>().sqrt();
        (d, n)
    };
    let ((dt, nt), (dm, nm)) = (centred(&ft), centred(&fm));
    if nt <= 0.0 || nm <= 0.0 {
        return ((0, 0), 0.0);
    }
    let c = c.max(1) as i32;
    let signed = |s: i32| if s > c / 2 { s - c } else { s };
    let mut best: ((i32, i32), f32) = ((0, 0), f32::NEG_INFINITY);
    let range = |f: Option<i32>| match f {
        Some(s) => {
            let s = s.rem_euclid(c);
            s..s + 1
        }
        None => 0..c,
    };
    for sy in range(fixed.1) {
        for sx in range(fixed.0) {
            let mut acc = 0.0f32;
            for v in 0..c {
                for u in 0..c {
                    acc += dt[(((v + sy) % c) * c + (u + sx) % c) as usize] * dm[(v * c + u) as usize];
                }
            }
            let s = (signed(sx), signed(sy));
            // Ties (a fold with a symmetry) go to the smaller shift.
            let better = acc > best.1 + 1e-9 * nt * nm
                || ((acc - best.1).abs() <= 1e-9 * nt * nm
                    && s.0.abs() + s.1.abs() < best.0 .0.abs() + best.0 .1.abs());
            if better {
                best = (s, acc);
            }
        }
    }
    (best.0, best.1 / (nt * nm))
}

/// Sub-cell phase of a one-repeat image of `c`-pixel cells from the image alone: the cyclic shift
/// `(dx, dy)`, each in `(−c/2, c/2]`, for which [`shift_periodic`]`(img, dx, dy)` starts on a yarn
/// boundary, and the strength of the cue along each axis (see below).
///
/// Along x, the squared horizontal difference of the sRGB luminance is folded into one cell
/// (summed over every row and every cell: a profile of `c` values); along y, the vertical one.
/// Every vertical edge of a weave lies on a warp boundary (the warps' silhouettes, the wefts'
/// ends where they pass under a warp), whatever the pattern, the colours, and whether the gaps are
/// brighter or darker than the yarns, while the crowns at the cell centres are smooth: the
/// profile's fundamental (first Fourier harmonic over the cell) peaks on the boundary. Its phase
/// is sub-pixel and needs no model, so it cannot depend on a starting pattern or on the model's
/// own fine detail (the ply and fibre stripes of a render, which a photo or another renderer may
/// not have). An axis's strength is the ratio of the fundamental's amplitude to the profile's mean
/// (0 when the axis is flat): about 1 where the edges gather on the boundaries; low where they
/// gather elsewhere too, as the two silhouettes of a thin yarn well inside its cell do, and the
/// phase is then not to be trusted.
pub fn boundary_phase(img: &Image, c: u32) -> ((i32, i32), (f32, f32)) {
    let (w, h) = (img.width as i32, img.height as i32);
    let lum: Vec<f32> = img.data.iter().map(|p| crate::image_io::linear_to_srgb((p[0] + p[1] + p[2]) / 3.0)).collect();
    let at = |x: i32, y: i32| lum[(y.rem_euclid(h) * w + x.rem_euclid(w)) as usize];
    let ci = c.max(1) as i32;
    let (mut px, mut py) = (vec![0.0f64; ci as usize], vec![0.0f64; ci as usize]);
    for y in 0..h {
        for x in 0..w {
            let gx = 0.5 * (at(x + 1, y) - at(x - 1, y));
            let gy = 0.5 * (at(x, y + 1) - at(x, y - 1));
            px[(x % ci) as usize] += (gx * gx) as f64;
            py[(y % ci) as usize] += (gy * gy) as f64;
        }
    }
    // The fundamental's peak `u*` (pixel-centre coordinates: pixel `u` is centred at `u`). A
    // boundary between pixels `k − 1` and `k` shows as a peak at `k − 0.5`, and the shift that
    // starts the image there is `k`, i.e. `u* + 0.5`.
    let axis = |p: &[f64]| {
        let n = p.len() as f64;
        let (mut re, mut im) = (0.0f64, 0.0f64);
        for (u, v) in p.iter().enumerate() {
            let a = std::f64::consts::TAU * u as f64 / n;
            re += v * a.cos();
            im += v * a.sin();
        }
        let mean = p.iter().sum::<f64>() / n;
        let amp = 2.0 * (re * re + im * im).sqrt() / n;
        let peak = im.atan2(re) / std::f64::consts::TAU * n;
        let s = (peak + 0.5).round() as i32;
        let s = s.rem_euclid(ci);
        let s = if s > ci / 2 { s - ci } else { s };
        (s, if mean > 0.0 { (amp / mean) as f32 } else { 0.0 })
    };
    let ((sx, ax), (sy, ay)) = (axis(&px), axis(&py));
    ((sx, sy), (ax, ay))
}

/// Sub-cell phase of a one-repeat image of `c`-pixel cells from its back-lit holes: the cyclic
/// shift `(dx, dy)`, each in `(−c/2, c/2]`, for which [`shift_periodic`]`(img, dx, dy)` starts on
/// a yarn boundary, and the concentration of the cue along each axis (see below). Only for a
/// picture whose holes glow with a light behind the cloth: lit from the front, the bright spots
/// are the yarns' tops instead, which [`corner_reach`] tells apart.
///
/// Wherever four yarns meet, whichever lies on top, a hole opens at the cell corner, centred on
/// the crossing of a weft boundary and a warp boundary, whatever the yarns' widths: a thin weft
/// leaves a tall hole, a wide warp a narrow one, but both are symmetric about the corner. The
/// pixels brighter than the middle of the luminance range (linear; between its 2nd and 98th
/// percentiles, as `fit::capture` counts bright pixels) are weighted by how far they rise above
/// it, `w = max(0, L − mid)`, and folded into one cell along each axis; the circular mean of that
/// profile (the phase of its first Fourier harmonic, as in [`boundary_phase`]) is the holes'
/// centre, i.e. the boundary. The concentration is the mean resultant length `|Σ w·e^{iθ}| / Σ w`
/// (1 when every hole pixel sits on one line, about 0 when the bright pixels spread over the
/// whole cell). The edge cue ([`boundary_phase`]) fails on exactly these pictures: the holes'
/// edges, a quarter of a cell or more from the corner on each side, outweigh the yarns'
/// silhouettes, and its fundamental loses its peak. `None` when the image has no bright pixel.
pub fn hole_phase(img: &Image, c: u32) -> Option<((i32, i32), (f32, f32))> {
    let lum: Vec<f32> = img.data.iter().map(|p| 0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2]).collect();
    let mut sorted = lum.clone();
    sorted.sort_by(f32::total_cmp);
    if sorted.is_empty() {
        return None;
    }
    let pct = |q: f32| sorted[((sorted.len() - 1) as f32 * q).round() as usize];
    let mid = 0.5 * (pct(0.02) + pct(0.98));
    let ci = c.max(1) as usize;
    let (mut px, mut py) = (vec![0.0f64; ci], vec![0.0f64; ci]);
    let w = img.width as usize;
    for (k, &l) in lum.iter().enumerate() {
        let v = (l - mid).max(0.0) as f64;
        px[(k % w) % ci] += v;
        py[(k / w) % ci] += v;
    }
    let axis = |p: &[f64]| -> Option<(i32, f32)> {
        let n = p.len() as f64;
        let total: f64 = p.iter().sum();
        if total <= 0.0 {
            return None;
        }
        let (mut re, mut im) = (0.0f64, 0.0f64);
        for (u, v) in p.iter().enumerate() {
            let a = std::f64::consts::TAU * u as f64 / n;
            re += v * a.cos();
            im += v * a.sin();
        }
        // Pixel `u` is centred at `u`: a hole centred between pixels `k − 1` and `k` has its mean
        // at `k − 0.5`, and the shift that starts the image there is `k`.
        let centre = im.atan2(re) / std::f64::consts::TAU * n;
        let s = ((centre + 0.5).round() as i32).rem_euclid(ci as i32);
        let s = if s > ci as i32 / 2 { s - ci as i32 } else { s };
        Some((s, ((re * re + im * im).sqrt() / total) as f32))
    };
    let ((sx, rx), (sy, ry)) = (axis(&px)?, axis(&py)?);
    Some(((sx, sy), (rx, ry)))
}

/// How far the brightness of the cell corners reaches, as a share of theirs, in a one-repeat
/// image of `c`-pixel cells whose cell boundaries start at `(dx, dy)` (the shift [`hole_phase`]
/// returns): at every corner, the linear luminance `reach` cells away along x and along y (each
/// the mean of both sides; the brighter direction) against the corner's own (the 2×2 pixels
/// around it); the median over the corners. `fit::capture` tells holes from yarn tops the same
/// way on the whole photo: a hole is a small spot closed on every side by yarns, while a bright
/// yarn top stays bright along its yarn. `NaN` when every corner is black.
pub fn corner_reach(img: &Image, c: u32, (dx, dy): (i32, i32), reach: f32) -> f32 {
    let ci = c.max(1) as i32;
    let (w, h) = (img.width as i32, img.height as i32);
    let lum = |x: i32, y: i32| {
        let p = img.get(x.rem_euclid(w) as u32, y.rem_euclid(h) as u32);
        0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2]
    };
    let d = (reach * ci as f32).round() as i32;
    let mut shares = Vec::new();
    // The corner lies between pixels `x0 − 1` and `x0` (and `y0 − 1`, `y0`).
    for y0 in (0..(h / ci).max(1)).map(|k| dy + k * ci) {
        for x0 in (0..(w / ci).max(1)).map(|k| dx + k * ci) {
            let spot = (lum(x0 - 1, y0 - 1) + lum(x0, y0 - 1) + lum(x0 - 1, y0) + lum(x0, y0)) / 4.0;
            let along_x = [y0 - 1, y0].iter().map(|&y| lum(x0 - 1 - d, y) + lum(x0 + d, y)).sum::<f32>() / 4.0;
            let along_y = [x0 - 1, x0].iter().map(|&x| lum(x, y0 - 1 - d) + lum(x, y0 + d)).sum::<f32>() / 4.0;
            if spot > 0.0 {
                shares.push(along_x.max(along_y) / spot);
            }
        }
    }
    if shares.is_empty() {
        return f32::NAN;
    }
    shares.sort_by(f32::total_cmp);
    shares[shares.len() / 2]
}

/// Least geometric mean of the two comb fractions of a yarn count (see [`yarn_count`]).
const COMB_MIN: f32 = 0.45;

/// A count must score at least this fraction of each of its divisors' scores: the edges of a
/// yarn, and the stripes of its plies, put power on the harmonics of twice the count too, but
/// less than on the count's own.
const COMB_DIVISOR: f32 = 0.7;

/// Fewest pixels per yarn a count may imply.
const MIN_PX_PER_YARN: usize = 4;

/// Fraction of a periodic profile's AC power (DFT, bins `1..=len/2`) on the harmonics of `n`.
fn comb_fraction(power: &[f32], n: usize) -> f32 {
    let total: f32 = power.iter().skip(1).sum();
    if total <= 0.0 {
        return 0.0;
    }
    power.iter().skip(n).step_by(n).sum::<f32>() / total
}

/// Power spectrum (bins `0..=len/2`) of a periodic profile.
fn power_spectrum(profile: &[f32]) -> Vec<f32> {
    use rustfft::num_complex::Complex;
    let n = profile.len();
    let mean = profile.iter().sum::<f32>() / n.max(1) as f32;
    let mut buf: Vec<Complex<f32>> = profile.iter().map(|v| Complex::new(v - mean, 0.0)).collect();
    rustfft::FftPlanner::new().plan_fft_forward(n).process(&mut buf);
    buf[..=n / 2].iter().map(|c| c.norm_sqr()).collect()
}

/// Number of yarns across one repeat from two periodic profiles along the axis: the mean
/// luminance (bright yarn centres, dark boundaries) and the mean absolute luminance derivative
/// across the axis (yarn edges). A count `n` is plausible when the harmonics of `n` carry a large
/// part of both spectra (geometric mean ≥ [`COMB_MIN`]) and not much less than any of its
/// divisors does ([`COMB_DIVISOR`]); the largest plausible count wins. The
/// luminance alone has strong low harmonics from the weave's colour layout (a divisor of the true
/// count); the edges alone have two edges per yarn (twice the count); both together single out
/// the yarn pitch.
fn yarn_count(luminance: &[f32], edges: &[f32]) -> Option<usize> {
    let (pl, pe) = (power_spectrum(luminance), power_spectrum(edges));
    let max_n = (luminance.len() / MIN_PX_PER_YARN).min(crate::pattern::MAX_SIDE);
    let score = |n: usize| (comb_fraction(&pl, n) * comb_fraction(&pe, n)).sqrt();
    let plausible = |n: usize| {
        let s = score(n);
        s >= COMB_MIN && (2..n).filter(|d| n.is_multiple_of(*d)).all(|d| s >= COMB_DIVISOR * score(d))
    };
    (2..=max_n).rev().find(|&n| plausible(n))
}

/// Yarn grid `(n_e, n_a)` of an image holding exactly one repeat, from the luminance and edge
/// profiles along each axis (see `yarn_count`); `None` when an axis has no plausible count.
pub fn comb_grid(img: &Image) -> Option<(usize, usize)> {
    let (w, h) = (img.width as usize, img.height as usize);
    let lum: Vec<f32> = img.data.iter().map(|p| (p[0] + p[1] + p[2]).clamp(0.0, 3.0) / 3.0).collect();
    let at = |x: usize, y: usize| lum[(y % h) * w + x % w];
    let (mut row_l, mut row_e) = (vec![0.0f32; h], vec![0.0f32; h]);
    let (mut col_l, mut col_e) = (vec![0.0f32; w], vec![0.0f32; w]);
    for y in 0..h {
        for x in 0..w {
            let v = at(x, y);
            row_l[y] += v;
            col_l[x] += v;
            row_e[y] += (at(x, y + 1) - v).abs();
            col_e[x] += (at(x + 1, y) - v).abs();
        }
    }
    Some((yarn_count(&row_l, &row_e)?, yarn_count(&col_l, &col_e)?))
}

/// Detect the yarn grid `(n_e, n_a)` of an image that holds exactly one repeat: the comb of the
/// luminance and edge spectra ([`comb_grid`]), else the yarn pitch that `prep` finds on a 3×3
/// tiling of it (no rectification, no Kernel PCA).
pub fn detect_grid(img: &Image) -> Option<(usize, usize)> {
    comb_grid(img).or_else(|| prep_grid(img))
}

/// Grid from `prep`'s yarn pitch on a 3×3 tiling of a one-repeat image.
fn prep_grid(img: &Image) -> Option<(usize, usize)> {
    let tiled = tile(img, 3, 3);
    let opts = crate::prep::PrepOptions {
        rectify: false,
        perspective: false,
        regularize: false,
        min_pitch: 3.0,
        ..Default::default()
    };
    let p = crate::prep::prepare(&tiled.to_rgb32f(), &opts).ok()?;
    let n_a = (img.width as f32 / p.pitch_x).round() as usize;
    let n_e = (img.height as f32 / p.pitch_y).round() as usize;
    let ok = |n: usize| (1..=crate::pattern::MAX_SIDE).contains(&n);
    (ok(n_e) && ok(n_a)).then_some((n_e, n_a))
}

/// Mean colour of the cells where weft (`weft_on_top = true`) or warp lies on top, over the
/// inner part of each cell (`margin` of the cell size ignored at each edge). `None` if no cell.
pub fn yarn_mean(img: &Image, p: &WeavePattern, c: u32, weft_on_top: bool, margin: f32) -> Option<[f32; 3]> {
    yarn_mean_where(img, p, c, weft_on_top, margin, &vec![true; img.data.len()])
}

/// Mean colour of the cells where weft (`weft_on_top = true`) or warp lies on top, as
/// [`yarn_mean`], over only the pixels where `keep` (row-major, one per pixel of `img`) is true:
/// the pixels a yarn covers, not the gaps between the yarns (see `colours::yarn_pixels`).
/// `None` if no pixel is kept.
pub fn yarn_mean_where(
    img: &Image,
    p: &WeavePattern,
    c: u32,
    weft_on_top: bool,
    margin: f32,
    keep: &[bool],
) -> Option<[f32; 3]> {
    let m = ((c as f32 * margin).round() as u32).min(c.saturating_sub(1) / 2);
    let mut acc = [0.0f64; 3];
    let mut n = 0usize;
    for i in 0..p.n_e() {
        for j in 0..p.n_a() {
            if p.get(i, j) != weft_on_top {
                continue;
            }
            let (x0, y0, x1, y1) = cell_rect(p.n_e(), i, j, c);
            for y in y0 + m..y1 - m {
                for x in x0 + m..x1 - m {
                    if !keep.get((y * img.width + x) as usize).copied().unwrap_or(false) {
                        continue;
                    }
                    let v = img.get(x, y);
                    (0..3).for_each(|k| acc[k] += v[k] as f64);
                    n += 1;
                }
            }
        }
    }
    (n > 0).then(|| acc.map(|a| (a / n as f64) as f32))
}

/// Indices of the brightest `frac` of the pixels (by luminance) among those below 0.95: the
/// specular highlights of the yarns, not the gaps (which see the back light and clip to white).
pub fn top_pixels(img: &Image, frac: f32) -> Vec<usize> {
    let lum = |p: &[f32; 3]| 0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2];
    let mut px: Vec<(usize, f32)> =
        img.data.iter().enumerate().map(|(i, p)| (i, lum(p))).filter(|(_, l)| *l < 0.95).collect();
    px.sort_by(|a, b| b.1.total_cmp(&a.1));
    let n = ((px.len() as f32 * frac).ceil() as usize).min(px.len());
    px[..n].iter().map(|(i, _)| *i).collect()
}

/// Mean colour of the pixels `idx`, values clamped to [0, 1] (zero if `idx` is empty).
pub fn mean_at(img: &Image, idx: &[usize]) -> [f32; 3] {
    let mut acc = [0.0f32; 3];
    for &i in idx {
        let p = img.data[i];
        (0..3).for_each(|k| acc[k] += p[k].clamp(0.0, 1.0) / idx.len() as f32);
    }
    acc
}

/// MSE in linear RGB.
pub fn mse(a: &Image, b: &Image) -> f32 {
    let r = a.rmse(b);
    r * r
}

/// Inner mean colour of every cell (`margin` of the cell size ignored at each edge), row-major by
/// weft `i`, warp `j`.
pub fn cell_means(img: &Image, n_e: usize, n_a: usize, c: u32, margin: f32) -> Vec<[f32; 3]> {
    let m = ((c as f32 * margin).round() as u32).min(c.saturating_sub(1) / 2);
    let mut out = Vec::with_capacity(n_e * n_a);
    for i in 0..n_e {
        for j in 0..n_a {
            let (x0, y0, x1, y1) = cell_rect(n_e, i, j, c);
            let mut acc = [0.0f64; 3];
            let mut n = 0usize;
            for y in y0 + m..y1 - m {
                for x in x0 + m..x1 - m {
                    let v = img.get(x, y);
                    (0..3).for_each(|k| acc[k] += v[k].clamp(0.0, 1.0) as f64);
                    n += 1;
                }
            }
            out.push(acc.map(|a| (a / n.max(1) as f64) as f32));
        }
    }
    out
}

/// Two-means clustering of the cells' inner mean colours, started from the two most different
/// cells: where the two yarn families differ in colour, the clusters are the cells where weft
/// resp. warp lies on top (paper §5.1's colour cue). Which cluster is which is not decided here:
/// the caller tries the labelling and its inverse. A row or column left in one cluster has its
/// least certain cell flipped. `None` when every cell lands in one cluster.
pub fn colour_clusters(img: &Image, n_e: usize, n_a: usize, c: u32) -> Option<WeavePattern> {
    let x = cell_means(img, n_e, n_a, c, 0.2);
    let d2 = |a: &[f32; 3], b: &[f32; 3]| (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f32>();
    let mut far = (0, 0, -1.0f32);
    for a in 0..x.len() {
        for b in a + 1..x.len() {
            let d = d2(&x[a], &x[b]);
            if d > far.2 {
                far = (a, b, d);
            }
        }
    }
    if far.2 <= 0.0 {
        return None;
    }
    let mut mu = [x[far.0], x[far.1]];
    let mut lab = vec![false; x.len()];
    for _ in 0..32 {
        let new: Vec<bool> = x.iter().map(|p| d2(p, &mu[1]) < d2(p, &mu[0])).collect();
        let changed = new != lab;
        lab = new;
        let n1 = lab.iter().filter(|&&l| l).count();
        if n1 == 0 || n1 == lab.len() {
            return None;
        }
        for (side, m) in mu.iter_mut().enumerate() {
            let sel: Vec<&[f32; 3]> = x.iter().zip(&lab).filter(|(_, &l)| l == (side == 1)).map(|(p, _)| p).collect();
            *m = std::array::from_fn(|k| sel.iter().map(|p| p[k]).sum::<f32>() / sel.len() as f32);
        }
        if !changed {
            break;
        }
    }
    let margin: Vec<f32> = x.iter().map(|p| (d2(p, &mu[0]) - d2(p, &mu[1])).abs()).collect();
    woven_labelling(lab, n_e, n_a, &margin)
}

/// The pattern of a cell labelling (row-major by weft `i`, weft on top where true). A row or
/// column all one value would have a yarn floating over the whole repeat (no weave): the least
/// certain cell (smallest `margin`) among those whose flip leaves fewer such lines is flipped,
/// until none is left or no flip helps.
fn woven_labelling(mut lab: Vec<bool>, n_e: usize, n_a: usize, margin: &[f32]) -> Option<WeavePattern> {
    let uniform_lines = |lab: &[bool]| {
        let rows = (0..n_e).filter(|&i| (0..n_a).all(|j| lab[i * n_a + j] == lab[i * n_a])).count();
        let cols = (0..n_a).filter(|&j| (0..n_e).all(|i| lab[i * n_a + j] == lab[j])).count();
        rows + cols
    };
    while uniform_lines(&lab) > 0 {
        let now = uniform_lines(&lab);
        let flip = (0..lab.len())
            .filter(|&k| {
                let mut t = lab.to_vec();
                t[k] = !t[k];
                uniform_lines(&t) < now
            })
            .min_by(|&a, &b| margin[a].total_cmp(&margin[b]));
        match flip {
            Some(k) => lab[k] = !lab[k],
            None => break,
        }
    }
    let rows: Vec<Vec<bool>> = (0..n_e).map(|i| lab[i * n_a..(i + 1) * n_a].to_vec()).collect();
    WeavePattern::from_rows_unreduced(&rows).ok()
}

/// The pattern read from the yarns' directions: in each cell (inner part, a fifth of the cell
/// ignored at each edge), weft lies on top where the luminance (sRGB) varies more across rows than
/// across columns (a horizontal yarn's edges, shading and gaps run along x). Unlike the colour
/// clusters it says which family is on top, and it works when the two families' colours are close.
/// Floating yarns are repaired as in [`colour_clusters`]. `None` for cells under 5 px.
pub fn orientation_labelling(img: &Image, n_e: usize, n_a: usize, c: u32) -> Option<WeavePattern> {
    if c < 5 {
        return None;
    }
    let lum = |x: u32, y: u32| {
        let p = img.get(x.min(img.width - 1), y.min(img.height - 1));
        crate::image_io::linear_to_srgb((p[0] + p[1] + p[2]) / 3.0)
    };
    let m = c / 5;
    let mut lab = vec![false; n_e * n_a];
    let mut margin = vec![0.0f32; n_e * n_a];
    for i in 0..n_e {
        for j in 0..n_a {
            let (x0, y0, x1, y1) = cell_rect(n_e, i, j, c);
            let (mut sx, mut sy) = (0.0f32, 0.0f32);
            for y in y0 + m..y1 - m {
                for x in x0 + m..x1 - m {
                    let v = lum(x, y);
                    sx += (lum(x + 1, y) - v).powi(2);
                    sy += (lum(x, y + 1) - v).powi(2);
                }
            }
            lab[i * n_a + j] = sy > sx;
            margin[i * n_a + j] = (sy - sx).abs() / (sy + sx).max(1e-12);
        }
    }
    woven_labelling(lab, n_e, n_a, &margin)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::LightRig;

    /// A one-repeat image whose cells are painted with colour `a` where `p` is 1 and `b` where 0,
    /// with a dark border in every cell (the part `cell_means` ignores) and a little noise.
    fn painted(p: &WeavePattern, c: u32, a: [f32; 3], b: [f32; 3]) -> Image {
        let (w, h) = (p.n_a() as u32 * c, p.n_e() as u32 * c);
        let mut data = vec![[0.02f32; 3]; (w * h) as usize];
        for i in 0..p.n_e() {
            for j in 0..p.n_a() {
                let (x0, y0, x1, y1) = cell_rect(p.n_e(), i, j, c);
                for y in y0 + 2..y1 - 2 {
                    for x in x0 + 2..x1 - 2 {
                        let wobble = (((x * 7 + y * 13) % 5) as f32 - 2.0) * 0.01;
                        data[(y * w + x) as usize] = (if p.get(i, j) { a } else { b }).map(|v| v + wobble);
                    }
                }
            }
        }
        Image::new(w, h, data)
    }

    #[test]
    fn colour_clusters_recover_the_cells_of_each_colour() {
        let p = WeavePattern::parse("10010/00110/01011/11110/11000").expect("pattern");
        let img = painted(&p, 12, [0.7, 0.2, 0.1], [0.2, 0.3, 0.6]);
        let q = colour_clusters(&img, 5, 5, 12).expect("two clusters");
        assert!(q == p || q == p.inverted(), "{q} vs {p}");
    }

    #[test]
    fn a_cluster_labelling_with_a_floating_yarn_is_repaired_at_its_least_certain_cell() {
        let p = WeavePattern::parse("110/011/101").expect("pattern");
        let (a, b) = ([0.7, 0.2, 0.1], [0.2, 0.3, 0.6]);
        let mut img = painted(&p, 12, a, b);
        // The one `b` cell of weft 0 is painted just on `a`'s side of the midpoint: plain 2-means
        // puts it with the other cells of its row, which leaves weft 0 floating over the repeat.
        let j = (0..3).find(|&j| !p.get(0, j)).expect("a 0 cell in row 0");
        let (x0, y0, x1, y1) = cell_rect(3, 0, j, 12);
        let mid: [f32; 3] = std::array::from_fn(|k| 0.53 * a[k] + 0.47 * b[k]);
        for y in y0 + 2..y1 - 2 {
            for x in x0 + 2..x1 - 2 {
                img.data[(y * img.width + x) as usize] = mid;
            }
        }
        let q = colour_clusters(&img, 3, 3, 12).expect("two clusters");
        assert!(!q.has_unbound_yarn(), "{q}");
        assert!(q == p || q == p.inverted(), "{q} vs {p}");
    }

    #[test]
    fn colour_clusters_give_up_on_a_uniform_image() {
        let p = WeavePattern::parse("1100/0110/0011/1001").expect("pattern");
        let img = painted(&p, 10, [0.5; 3], [0.5; 3]);
        // Only the ±0.02 wobble separates cells: whatever comes back must not crash, and a flat
        // image (no wobble at all) gives no clusters.
        let _ = colour_clusters(&img, 4, 4, 10);
        let flat = Image::new(40, 40, vec![[0.5; 3]; 1600]);
        assert!(colour_clusters(&flat, 4, 4, 10).is_none());
    }

    #[test]
    fn top_pixels_skip_clipped_gaps() {
        let mut data = vec![[0.3f32; 3]; 100];
        data[..20].iter_mut().for_each(|p| *p = [1.0; 3]); // gaps
        data[20..25].iter_mut().for_each(|p| *p = [0.8; 3]); // highlights
        let img = Image::new(10, 10, data);
        let idx = top_pixels(&img, 0.0625);
        assert_eq!(idx.len(), 5);
        assert!(idx.iter().all(|&i| (20..25).contains(&i)));
        assert!(mean_at(&img, &idx).iter().all(|v| (v - 0.8).abs() < 1e-5));
    }

    /// A back-lit one-repeat image of `n × n` cells of `c` px: dark yarns, and at every cell corner
    /// a white hole, an ellipse of half-axes `(ax, ay)` px centred on the corner.
    fn holes_at_corners(n: u32, c: u32, ax: f32, ay: f32) -> Image {
        let side = n * c;
        let data = (0..side * side)
            .map(|k| {
                let (x, y) = ((k % side) as f32 + 0.5, (k / side) as f32 + 0.5);
                let (cx, cy) = ((x / c as f32).round() * c as f32, (y / c as f32).round() * c as f32);
                let inside = ((x - cx) / ax).powi(2) + ((y - cy) / ay).powi(2) <= 1.0;
                if inside {
                    [1.0; 3]
                } else {
                    [0.06, 0.04, 0.08]
                }
            })
            .collect();
        Image::new(side, side, data)
    }

    #[test]
    fn back_lit_holes_mark_the_boundaries_whatever_their_shape() {
        let c = 16;
        let off = |v: i32| (v + c as i32 / 2).rem_euclid(c as i32) - c as i32 / 2;
        // Tall holes (thin wefts, wide warps) and round ones.
        for (ax, ay) in [(2.5, 5.0), (3.5, 3.5)] {
            let img = holes_at_corners(3, c, ax, ay);
            for (sx, sy) in [(0, 0), (0, 5), (4, -3), (-6, 7), (8, 8)] {
                let ((dx, dy), (rx, ry)) = hole_phase(&shift_periodic(&img, sx, sy), c).expect("holes");
                assert!(off(sx + dx) == 0 && off(sy + dy) == 0, "({sx}, {sy}) shifted by ({dx}, {dy})");
                assert!(rx > 0.8 && ry > 0.5, "concentration {rx} {ry}");
            }
        }
        // Spread bright pixels (every other column lit) are no lattice of holes.
        let stripes = Image::new(32, 32, (0..32 * 32).map(|k| if k % 2 == 0 { [1.0; 3] } else { [0.1; 3] }).collect());
        let (_, (rx, _)) = hole_phase(&stripes, 16).expect("bright pixels");
        assert!(rx < 0.1, "{rx}");
        assert!(hole_phase(&Image::filled(32, 32, [0.4; 3]), 16).is_none());
    }

    #[test]
    fn holes_are_compact_spots_and_yarn_tops_reach_along_their_yarns() {
        let c = 16;
        let holes = holes_at_corners(3, c, 2.5, 5.0);
        let r = corner_reach(&holes, c, (0, 0), 0.35);
        assert!(r < 0.15, "holes {r}");
        // Front-lit yarn tops: a bright bar along each cell's top yarn (weft where i + j is even,
        // warp elsewhere), 3 px wide and the cell long, on dark gaps. The brightest spots are the cell centres; a
        // frame that puts them on the corners (half a cell off) finds them reaching along the
        // yarns.
        let side = 3 * c;
        let tops = Image::new(
            side,
            side,
            (0..side * side)
                .map(|k| {
                    let (x, y) = (k % side, k / side);
                    let (i, j) = (y / c, x / c);
                    let (u, v) = ((x % c) as i32 - 8, (y % c) as i32 - 8);
                    let on = if (i + j) % 2 == 0 { v.abs() <= 1 } else { u.abs() <= 1 };
                    if on {
                        [0.8; 3]
                    } else {
                        [0.02; 3]
                    }
                })
                .collect(),
        );
        let ((dx, dy), _) = hole_phase(&tops, c).expect("bright pixels");
        let off = |v: i32| (v + c as i32 / 2).rem_euclid(c as i32) - c as i32 / 2;
        assert!(off(dx - 8).abs() <= 1 && off(dy - 8).abs() <= 1, "spots at ({dx}, {dy})");
        let r = corner_reach(&tops, c, (dx, dy), 0.35);
        assert!(r > 0.45, "tops {r}");
        assert!(corner_reach(&Image::filled(32, 32, [0.0; 3]), 16, (0, 0), 0.35).is_nan());
    }

    #[test]
    fn the_sub_cell_phase_of_a_shifted_crop_is_found_without_its_pattern() {
        use crate::fit::demo::demo_cloth;
        use crate::render::{render, RenderOptions};
        let truth = demo_cloth();
        let (n_e, n_a, c) = (truth.pattern.n_e(), truth.pattern.n_a(), 10);
        let scene = fit_scene(n_e, n_a, c, 4, 2, &LightRig::default_rig());
        let ro = RenderOptions { threads: Some(1), ..Default::default() };
        let img = render(&truth, &scene, &ro);
        // The model has another pattern, other radii and a grey appearance: only the cell
        // structure is shared.
        let mut model = truth.clone();
        model.pattern = crate::fit::default_twill(n_e, n_a);
        (model.r_e, model.r_a, model.appearance) = (4.0, 4.0, crate::fit::grey_appearance());
        let m = render(&model, &scene, &ro);
        assert_eq!(cell_phase(&img, &m, c).0, (0, 0));
        for (dx, dy) in [(3, -4), (5, 5), (-2, 1)] {
            let shifted = shift_periodic(&img, dx, dy);
            let ((sx, sy), r) = cell_phase(&shifted, &m, c);
            // Undoing the shift modulo a cell (a whole-cell shift is a shift of the pattern).
            let wrap = |v: i32| (v + c as i32 / 2).rem_euclid(c as i32) - c as i32 / 2;
            assert!(wrap(sx + dx).abs() <= 1 && wrap(sy + dy).abs() <= 1, "({dx},{dy}) -> ({sx},{sy}) r {r}");
            assert!(r > 0.5, "{r}");
            // With one axis held (at the right shift, or a wrong one), the other is still found
            // and the held one is returned as held.
            for hold in [-dx, -dx + 3] {
                let ((hx, hy), _) = cell_phase_given(&shifted, &m, c, (Some(hold), None));
                assert_eq!(
                    (hx.rem_euclid(c as i32), wrap(hy + dy).abs() <= 1),
                    (hold.rem_euclid(c as i32), true),
                    "({dx},{dy}) x held at {hold}: y {hy}"
                );
            }
            let ((hx, hy), _) = cell_phase_given(&shifted, &m, c, (None, Some(-dy)));
            assert_eq!((wrap(hx + dx).abs() <= 1, hy.rem_euclid(c as i32)), (true, (-dy).rem_euclid(c as i32)));
        }
        // A flat image has no phase.
        assert_eq!(cell_phase(&Image::filled(50, 50, [0.5; 3]), &m, c), ((0, 0), 0.0));
        // The shift wraps around: shifting back restores the image.
        let s = shift_periodic(&shift_periodic(&img, 7, -3), -7, 3);
        assert_eq!(s.data, img.data);
    }
}
