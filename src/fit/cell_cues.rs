//! The over/under decision of each cell read from the picture's structure, not from the
//! renderer's loss: every copy of the repeat in the rectified photo votes on which yarn lies on
//! top in each cell of the repeat, and the votes are combined into one pattern with a
//! per-cell confidence.
//!
//! Why: on hairy cloth whose two families have the same colour (FabricNET twills W116, W117,
//! W125, W126), the fit's target — the mean of the aligned repeats, blurred — keeps little of the
//! shading that tells warp from weft, and a nearly flat render fits it about as well with any
//! pattern: the loss gives the cell decision little signal. The rectified photo itself still
//! shows the floats clearly (a float's long axis, its fibres, its bright centre and dark ends),
//! and it holds many copies of the repeat, so structure measured per copy and then averaged is
//! both sharp and robust to fibre noise (averaging the *measurements*, not the pixels, also
//! survives a grid that drifts by a pixel or two between copies, which blurs a pixel mean).
//!
//! Two cues, both on the log-luminance `L = ln(Y + ε)` (blind to the yarn colour and the light
//! level, as in `prep::cells`) lightly smoothed (σ = 1 px, against JPEG blocks and sensor noise):
//!
//! 1. **Orientation inside the cell** (unary). Over the cell's inner part (a fifth of the pitch
//!    left out at each side, so boundaries and crossings do not count), the mean squared
//!    gradients in *cell units*: `E_x = ⟨(p_x ∂L/∂x)²⟩`, `E_y = ⟨(p_y ∂L/∂y)²⟩`, with `p_x, p_y`
//!    the pitches, and `o = (E_y − E_x)/(E_y + E_x)`. A weft on top runs along x: its fibres,
//!    its ply twist and the shading from its crown to its flanks all vary across it (along y), so
//!    `o > 0`; a warp gives `o < 0`. Measuring in cell units removes the bias of unbalanced
//!    cloth: with `p_x = 1.5 p_y` the same yarn shading spread over a 1.5× wider warp has 1.5×
//!    weaker pixel gradients, and pixel units would call most cells weft.
//! 2. **Continuity across cell boundaries** (pairwise). Between two cells of one row, the
//!    boundary strip (a tenth of the pitch each side, the middle half of the row) against the two
//!    cells' centres: `b = ⟨L⟩_strip − ⟨L⟩_centres`. A weft that floats over both cells passes the
//!    boundary at its bright, unbroken crown (`b ≳ 0`); any other pair puts a crossing there — a
//!    yarn diving under, or the gap between two warps — which is darker (`b < 0`). Likewise
//!    between two cells of one column for a warp floating over both. The sign of `b` needs no
//!    threshold: it asks whether the boundary is darker than the yarn centres beside it.
//!
//! Each cue is averaged over all copies of the cell (or boundary) in the rectified photo and
//! turned into a *t*-statistic (mean over its standard error, the error floored so that a few
//! identical copies do not give infinite evidence); the pattern minimises
//! `E(P) = −Σ_cells s_ij·t^o_ij − Σ_row pairs [P_ij ∧ P_ij+1]·t^b − Σ_column pairs [¬P_ij ∧ ¬P_i+1j]·t^b`
//! with `s = +1` for weft on top (`P = 1`) and `−1` otherwise, over the patterns in which every
//! yarn interlaces. Unary and pairwise terms are weighted alike: each is one independent reading
//! measured in its own standard errors. Small repeats (≤ 16 cells) are searched exhaustively, which
//! gives each cell's confidence as a max-marginal (the best energy with the cell flipped minus the
//! best); larger ones are searched from the named weaves in every shift and the unary labelling,
//! each improved by single-cell flips.

use crate::pattern::WeavePattern;
use crate::prep::image_ops::{blur_gray, Gray};
use crate::prep::Prepared;
use serde::Serialize;

/// Fewest copies of every cell of the repeat that must lie inside the rectified photo for the
/// cues to be read (with one copy there is no standard error, and one copy's fibres decide).
pub const MIN_COPIES: usize = 2;

/// Floor of a cue's standard error, in units of the cue's own spread over the whole repeat: a
/// cell whose copies agree exactly (a clean render) gets large but finite evidence.
const SE_FLOOR: f64 = 0.05;

/// Largest repeat (cells) searched exhaustively (`2^16` labellings).
const MAX_EXHAUSTIVE: usize = 16;

/// The cues read for one repeat of `n_e × n_a` cells; cell `(i, j)` is weft `i`, warp `j`, as in
/// [`WeavePattern`] (weft 0 is the bottom row of the image).
#[derive(Clone, Debug)]
pub struct CellCues {
    /// Pattern rows (wefts).
    pub n_e: usize,
    /// Pattern columns (warps).
    pub n_a: usize,
    /// Orientation evidence per cell, row-major by weft: > 0 weft on top (t-statistic of `o`).
    pub orient: Vec<f64>,
    /// Continuity of weft `i` from warp `j` to warp `j + 1` (mod `n_a`), row-major: > 0 the weft
    /// passes over the boundary unbroken (t-statistic of `b`).
    pub weft_link: Vec<f64>,
    /// Continuity of warp `j` from weft `i` to weft `i + 1` (mod `n_e`), row-major by weft.
    pub warp_link: Vec<f64>,
    /// Fewest copies any cell had.
    pub copies: usize,
}

/// The pattern the cues read, with each cell's confidence.
#[derive(Clone, Debug)]
pub struct CueReading {
    /// The pattern of least cue energy among the woven ones searched (unreduced, `n_e × n_a`).
    pub pattern: WeavePattern,
    /// Per cell (row-major by weft): how much the energy rises when this cell alone is forced to
    /// the other value (exhaustive search: the best pattern with it flipped), ≥ 0.
    pub margin: Vec<f64>,
    /// The energy of `pattern`.
    pub energy: f64,
}

/// Running mean and variance (Welford).
#[derive(Clone, Copy, Default)]
struct Acc {
    n: usize,
    mean: f64,
    m2: f64,
}

impl Acc {
    fn add(&mut self, v: f64) {
        self.n += 1;
        let d = v - self.mean;
        self.mean += d / self.n as f64;
        self.m2 += d * (v - self.mean);
    }
    /// Mean over its standard error, the error floored at `floor`.
    fn t(&self, floor: f64) -> f64 {
        if self.n == 0 {
            return 0.0;
        }
        let var = if self.n > 1 { self.m2 / (self.n - 1) as f64 } else { 0.0 };
        let se = (var / self.n as f64).sqrt().max(floor);
        self.mean / se
    }
}

/// Mean of `f` over the pixel rectangle `x0..x1 × y0..y1` (clamped to the image), `None` if empty.
fn rect_mean(g: &Gray, (x0, x1): (f64, f64), (y0, y1): (f64, f64), f: impl Fn(usize, usize) -> f64) -> Option<f64> {
    let xa = x0.ceil().max(1.0) as usize;
    let xb = (x1.floor() as usize).min(g.w.saturating_sub(2));
    let ya = y0.ceil().max(1.0) as usize;
    let yb = (y1.floor() as usize).min(g.h.saturating_sub(2));
    if xa > xb || ya > yb {
        return None;
    }
    let mut s = 0.0;
    for y in ya..=yb {
        for x in xa..=xb {
            s += f(x, y);
        }
    }
    Some(s / ((xb - xa + 1) * (yb - ya + 1)) as f64)
}

/// Reads the cues of the `n_e × n_a` repeat from the grey linear luminance `g`, with cell
/// boundaries at `origin + k·pitch` (pixels, x and y) and the repeat's cell `(0, 0)` — weft
/// `n_e − 1`, the top row — starting at `origin`. `None` when the pitch is under 6 px, a side of
/// the repeat is 0, or some cell has fewer than [`MIN_COPIES`] copies fully inside `g`.
pub fn read_cues(g: &Gray, pitch: [f64; 2], origin: [f64; 2], n_e: usize, n_a: usize) -> Option<CellCues> {
    if n_e == 0 || n_a == 0 || !(pitch[0] >= 6.0 && pitch[1] >= 6.0) || !origin.iter().all(|v| v.is_finite()) {
        return None;
    }
    let (px, py) = (pitch[0], pitch[1]);
    let mean = g.data.iter().map(|&v| v as f64).sum::<f64>() / g.data.len().max(1) as f64;
    if !mean.is_finite() || mean <= 0.0 {
        return None;
    }
    // ε as in `prep::cells`: dark gaps and noise must not dominate the log.
    let eps = (0.02 * mean) as f32;
    let lg = Gray { w: g.w, h: g.h, data: g.data.iter().map(|&v| (v.max(0.0) + eps).ln()).collect() };
    let l = blur_gray(&lg, 1.0);
    let at = |x: usize, y: usize| l.data[y * l.w + x] as f64;
    // Cell columns / rows whose whole cell (and the next one, for the links) lies inside.
    let kx0 = ((0.0 - origin[0]) / px).ceil() as i64;
    let kx1 = ((l.w as f64 - 1.0 - origin[0]) / px).floor() as i64 - 1; // last k with k+1 inside
    let ky0 = ((0.0 - origin[1]) / py).ceil() as i64;
    let ky1 = ((l.h as f64 - 1.0 - origin[1]) / py).floor() as i64 - 1;
    if kx1 < kx0 || ky1 < ky0 {
        return None;
    }
    let n = n_e * n_a;
    let (mut orient, mut weft, mut warp) = (vec![Acc::default(); n], vec![Acc::default(); n], vec![Acc::default(); n]);
    let cell_of = |kx: i64, ky: i64| -> usize {
        let j = kx.rem_euclid(n_a as i64) as usize;
        let i = n_e - 1 - ky.rem_euclid(n_e as i64) as usize;
        i * n_a + j
    };
    for ky in ky0..=ky1 {
        for kx in kx0..=kx1 {
            let (x0, y0) = (origin[0] + kx as f64 * px, origin[1] + ky as f64 * py);
            let c = cell_of(kx, ky);
            // 1. Orientation over the inner part, gradients in cell units (central differences).
            let inner = ((x0 + px / 5.0, x0 + px - px / 5.0), (y0 + py / 5.0, y0 + py - py / 5.0));
            let ex = rect_mean(&l, inner.0, inner.1, |x, y| ((at(x + 1, y) - at(x - 1, y)) * 0.5 * px).powi(2));
            let ey = rect_mean(&l, inner.0, inner.1, |x, y| ((at(x, y + 1) - at(x, y - 1)) * 0.5 * py).powi(2));
            if let (Some(ex), Some(ey)) = (ex, ey) {
                if ex + ey > 0.0 {
                    orient[c].add((ey - ex) / (ey + ex));
                }
            }
            // 2. Continuity to the right neighbour (same weft) and to the neighbour below (same
            //    warp; below in the image is the previous weft, so the link is stored on it).
            let mid_y = (y0 + py / 4.0, y0 + 3.0 * py / 4.0);
            let bx = x0 + px;
            let strip = rect_mean(&l, (bx - px / 10.0, bx + px / 10.0), mid_y, at);
            let left = rect_mean(&l, (bx - px / 2.0 - px / 10.0, bx - px / 2.0 + px / 10.0), mid_y, at);
            let right = rect_mean(&l, (bx + px / 2.0 - px / 10.0, bx + px / 2.0 + px / 10.0), mid_y, at);
            if let (Some(s), Some(a), Some(b)) = (strip, left, right) {
                weft[c].add(s - 0.5 * (a + b));
            }
            let mid_x = (x0 + px / 4.0, x0 + 3.0 * px / 4.0);
            let by = y0 + py;
            let strip = rect_mean(&l, mid_x, (by - py / 10.0, by + py / 10.0), at);
            let up = rect_mean(&l, mid_x, (by - py / 2.0 - py / 10.0, by - py / 2.0 + py / 10.0), at);
            let down = rect_mean(&l, mid_x, (by + py / 2.0 - py / 10.0, by + py / 2.0 + py / 10.0), at);
            if let (Some(s), Some(a), Some(b)) = (strip, up, down) {
                // The cell below (image) is weft i − 1: store on that weft so that the link of
                // weft i runs from weft i to i + 1.
                let below = cell_of(kx, ky + 1);
                warp[below].add(s - 0.5 * (a + b));
            }
        }
    }
    let copies = orient.iter().chain(&weft).chain(&warp).map(|a| a.n).min().unwrap_or(0);
    if copies < MIN_COPIES {
        return None;
    }
    // Standard-error floors in each cue's own units: a fraction of its spread over the repeat.
    let spread = |a: &[Acc]| -> f64 {
        let m = a.iter().map(|v| v.mean).sum::<f64>() / a.len() as f64;
        let sd = (a.iter().map(|v| (v.mean - m).powi(2)).sum::<f64>() / a.len() as f64).sqrt();
        let abs = a.iter().map(|v| v.mean.abs()).sum::<f64>() / a.len() as f64;
        (SE_FLOOR * sd.max(abs)).max(1e-9)
    };
    // The orientation cue's zero is not trusted, only its order within the repeat: the balance
    // of fibre texture (fine, isotropic in pixels) against yarn shading (coarse, across the yarn)
    // differs between cloths, and on unbalanced cloth the two pull `o` opposite ways (measured:
    // every cell of the hairy twill W117, 50×34 px cells, came out warp in cell units, every
    // cell of a plain W052 weft in pixel units). It is centred at the split that separates the
    // cells' means into two groups best (Otsu's between-class variance); every woven repeat
    // holds both families on top somewhere, so two groups exist.
    let beta = otsu_split(&orient.iter().map(|a| a.mean).collect::<Vec<_>>());
    for a in orient.iter_mut() {
        a.mean -= beta;
    }
    let (fo, fb) = (spread(&orient), spread(&[weft.clone(), warp.clone()].concat()));
    Some(CellCues {
        n_e,
        n_a,
        orient: orient.iter().map(|a| a.t(fo)).collect(),
        weft_link: weft.iter().map(|a| a.t(fb)).collect(),
        warp_link: warp.iter().map(|a| a.t(fb)).collect(),
        copies,
    })
}

/// The threshold that splits `v` into two groups of largest between-class variance
/// `w₀·w₁·(μ₀ − μ₁)²` (Otsu's criterion), halfway between the two values it falls between; the
/// mean when `v` has fewer than two distinct values.
fn otsu_split(v: &[f64]) -> f64 {
    let mut s: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    s.sort_by(|a, b| a.total_cmp(b));
    let n = s.len();
    let total: f64 = s.iter().sum();
    let mut best: Option<(f64, f64)> = None;
    let mut low = 0.0;
    for k in 1..n {
        low += s[k - 1];
        if s[k] <= s[k - 1] {
            continue;
        }
        let (w0, w1) = (k as f64, (n - k) as f64);
        let score = w0 * w1 * (low / w0 - (total - low) / w1).powi(2);
        if best.is_none_or(|b| score > b.0) {
            best = Some((score, 0.5 * (s[k - 1] + s[k])));
        }
    }
    best.map_or(total / n.max(1) as f64, |b| b.1)
}

/// [`read_cues`] for a fit's prepared photo: the rectified image, the preparation's pitches, and
/// the cell grid anchored at the crop's corner (`prep.crop`, which the fit moves along with the
/// target, so the repeat's cells are the fit's cells) — put back on preparation's yarn boundaries
/// where the fit moved it less than [`SNAP_CELLS`] of a cell off them ([`cue_origin`]).
pub fn read_prepared(prep: &Prepared, n_e: usize, n_a: usize) -> Option<CellCues> {
    let g = Gray::from_rgb(&prep.rectified);
    read_cues(&g, [prep.pitch_x as f64, prep.pitch_y as f64], cue_origin(prep), n_e, n_a)
}

/// Largest distance, in cells, between the crop's corner and preparation's nearest yarn boundary
/// at which [`cue_origin`] reads the cues on the boundary instead of the corner.
pub const SNAP_CELLS: f64 = 0.25;

/// The corner of the cue grid: along each axis, preparation's yarn boundary
/// (`phase + k·pitch`) nearest to the crop's corner when it lies within [`SNAP_CELLS`] of a cell,
/// else the corner itself.
///
/// Why: the fit puts the crop on the model's cell grid (`input::align_to_cells`). Where the grid
/// read from the brightness profiles landed on the yarn centres that is a move of about half a
/// cell, and the corner it gives is the one to read the cues on. But it also moves crops whose
/// corner was on the boundaries already by a fifth of a cell or so (the default cloth's
/// silhouettes matched against another renderer's yarns), and the cues, which compare cell
/// interiors with the strips on the boundaries between them, then straddle the yarns: the
/// seed-3232 random 3 × 6 (m3232_04) was read exactly, every cell's margin ≥ 30.8, at
/// preparation's corner (67, 91), and with seven cells wrong at the fit's (67, 93), 0.17 cell
/// below the boundary at 90.53. Each crop cell still reads the picture cell it overlaps most (the
/// snap is under half a cell).
pub fn cue_origin(prep: &Prepared) -> [f64; 2] {
    [
        snap_to_boundary(prep.crop.x as f64, prep.phase_x as f64, prep.pitch_x as f64),
        snap_to_boundary(prep.crop.y as f64, prep.phase_y as f64, prep.pitch_y as f64),
    ]
}

/// The boundary `phase + k·pitch` nearest to `corner` when it lies within [`SNAP_CELLS`] of a
/// pitch, else `corner` (also for a pitch or phase that is not a finite positive number).
fn snap_to_boundary(corner: f64, phase: f64, pitch: f64) -> f64 {
    if !(pitch > 0.0 && pitch.is_finite() && phase.is_finite()) {
        return corner;
    }
    let b = phase + ((corner - phase) / pitch).round() * pitch;
    if (b - corner).abs() < SNAP_CELLS * pitch {
        b
    } else {
        corner
    }
}

impl CellCues {
    /// Cue energy of the labelling `lab` (row-major by weft, `true` = weft on top); lower is
    /// better (see the module docs).
    pub fn energy(&self, lab: &[bool]) -> f64 {
        let (n_e, n_a) = (self.n_e, self.n_a);
        let mut e = 0.0;
        for i in 0..n_e {
            for j in 0..n_a {
                let k = i * n_a + j;
                e -= if lab[k] { self.orient[k] } else { -self.orient[k] };
                if lab[k] && lab[i * n_a + (j + 1) % n_a] {
                    e -= self.weft_link[k];
                }
                if !lab[k] && !lab[((i + 1) % n_e) * n_a + j] {
                    e -= self.warp_link[k];
                }
            }
        }
        e
    }

    /// The pattern of least energy in which every yarn interlaces, and each cell's margin; `None`
    /// when no woven labelling is found (a repeat with a side of 1).
    pub fn read(&self) -> Option<CueReading> {
        let n = self.n_e * self.n_a;
        if n <= MAX_EXHAUSTIVE {
            self.read_exhaustive()
        } else {
            self.read_local()
        }
    }

    fn woven(&self, lab: &[bool]) -> bool {
        let (n_e, n_a) = (self.n_e, self.n_a);
        let rows = (0..n_e).all(|i| (0..n_a).any(|j| lab[i * n_a + j]) && (0..n_a).any(|j| !lab[i * n_a + j]));
        let cols = (0..n_a).all(|j| (0..n_e).any(|i| lab[i * n_a + j]) && (0..n_e).any(|i| !lab[i * n_a + j]));
        rows && cols
    }

    fn pattern_of(&self, lab: &[bool]) -> Option<WeavePattern> {
        let rows: Vec<Vec<bool>> = lab.chunks(self.n_a).map(|r| r.to_vec()).collect();
        WeavePattern::from_rows_unreduced(&rows).ok()
    }

    fn read_exhaustive(&self) -> Option<CueReading> {
        let n = self.n_e * self.n_a;
        // Best energy with each cell at 0 / at 1 (max-marginals), over the woven labellings.
        let mut best_at = vec![[f64::INFINITY; 2]; n];
        let mut best: Option<(f64, Vec<bool>)> = None;
        let mut lab = vec![false; n];
        for code in 0u32..(1u32 << n) {
            for (k, v) in lab.iter_mut().enumerate() {
                *v = code >> k & 1 == 1;
            }
            if !self.woven(&lab) {
                continue;
            }
            let e = self.energy(&lab);
            for (k, &v) in lab.iter().enumerate() {
                let b = &mut best_at[k][v as usize];
                *b = b.min(e);
            }
            if best.as_ref().is_none_or(|b| e < b.0) {
                best = Some((e, lab.clone()));
            }
        }
        let (energy, lab) = best?;
        let margin = lab.iter().enumerate().map(|(k, &v)| best_at[k][!v as usize] - energy).collect();
        Some(CueReading { pattern: self.pattern_of(&lab)?, margin, energy })
    }

    fn read_local(&self) -> Option<CueReading> {
        let (n_e, n_a) = (self.n_e, self.n_a);
        let mut starts: Vec<Vec<bool>> = vec![self.orient.iter().map(|&o| o > 0.0).collect()];
        for p in super::candidates::template_candidates(n_e, n_a) {
            starts.push((0..n_e).flat_map(|i| (0..n_a).map(move |j| (i, j))).map(|(i, j)| p.get(i, j)).collect());
        }
        let mut best: Option<(f64, Vec<bool>)> = None;
        for mut lab in starts {
            // Single-cell flips while any lowers the energy of a woven labelling.
            let mut e = if self.woven(&lab) { self.energy(&lab) } else { f64::INFINITY };
            loop {
                let mut step: Option<(f64, usize)> = None;
                for k in 0..lab.len() {
                    lab[k] = !lab[k];
                    if self.woven(&lab) {
                        let f = self.energy(&lab);
                        if f < e && step.is_none_or(|s| f < s.0) {
                            step = Some((f, k));
                        }
                    }
                    lab[k] = !lab[k];
                }
                match step {
                    Some((f, k)) => (e, lab[k]) = (f, !lab[k]),
                    None => break,
                }
            }
            if e.is_finite() && best.as_ref().is_none_or(|b| e < b.0) {
                best = Some((e, lab));
            }
        }
        let (energy, lab) = best?;
        let margin = (0..lab.len())
            .map(|k| {
                let mut t = lab.clone();
                t[k] = !t[k];
                if self.woven(&t) {
                    self.energy(&t) - energy
                } else {
                    f64::INFINITY
                }
            })
            .collect();
        Some(CueReading { pattern: self.pattern_of(&lab)?, margin, energy })
    }
}

/// Relative loss the picture's cells may overrule where both the fit's pattern and the reading
/// are named weaves, or both are not: the cue reading replaces the fit's pattern when, with the
/// same appearance descent, its loss is at most this fraction above the fit's. Zero: there the
/// loss decides. Measured (docs/benchmarks.md, session 10): with 2 % the plain W012 was turned
/// into its inverse (the cues cannot tell a plain weave's two phases better than the loss) and
/// its crop PSNR fell from 20.8 to 19.9 dB, while no twill or satin needed it (the named-weave
/// rule below decided each of them).
pub const LOSS_TOLERANCE: f32 = 0.0;

/// Least cue-energy advantage (sum of t-statistics, see the module docs) of the cue reading over
/// the fit's pattern for the reading to be tried against it: about three standard errors of one
/// reading, so that a tie in the cues does not overrule the loss.
pub const MIN_ENERGY_GAIN: f64 = 3.0;

/// Least cue-energy advantage *per cell of the repeat* of a named reading over the winner when the
/// winner is the reading's inverted twin (the face rule of `contest`): each cell then weighs in
/// with about two standard errors for the reading's face. Measured (docs/benchmarks.md, session
/// 22, `examples/cell_cues_diag`): of the 72 Mitsuba renders of the five sets and the shared set,
/// the 35 whose cues could be read and whose pattern is not its own inverse (up to a shift) all
/// put the truth's cue energy below its twin's, by 0.57 to 57 per cell; all but one by 4.6 or
/// more (the one-colour 2/1 twills m2121_04 and m2121_08: 5.8 and 16.7). The one below, the
/// warp-faced satin m1717_05 (0.57), is left to the loss. Session 35 found the first wrong face
/// the cues favour: the grey 1/2 twill m3636_08 under a near area light, whose wefts, lit along
/// their length, read as the long floats (3.4 per cell for the 2/1, whose loss is 2.4× the
/// truth's). The least gain sits between that and the truths' 4.6.
pub const FACE_GAIN_PER_CELL: f64 = 4.0;

/// Least margin (the cue energy one flipped cell costs, [`CueReading::margin`]) that every cell
/// of an irregular reading must have for `contest` to let it meet a named winner as it is,
/// instead of standing in the named weave the cues rank first: three times [`MIN_ENERGY_GAIN`].
///
/// Measured (docs/benchmarks.md, session 31, `examples/cell_cues_diag`) on the 101 Mitsuba
/// renders of the seed-2020 to -2525, -3131 and -3232 sets and the shared set whose cues could be
/// read: of the 22 irregular readings that were the truth, 21 had least margins of 12.9 to 116.5
/// (one 1.3); of the 7 wrong ones (a cell or two off the truth), 6 had 0.1 to 2.5 (one, the random
/// 4 × 4 m2323_05, 15.3); the irregular readings of the real photos FabricNET W104, W116, W126,
/// W067, W098 and W128 had 0.0 to 3.7. Such a reading is not taken on trust: it only meets the
/// winner by the loss. The seed-3232 random 3 × 6 (m3232_04, 30.8) was read exactly while a
/// herringbone won the fit, and the named weave the cues ranked first stood in for the reading.
pub const CONFIDENT_MARGIN: f64 = 3.0 * MIN_ENERGY_GAIN;

/// Whether every cell of `reading` has a margin of at least [`CONFIDENT_MARGIN`].
fn confident(reading: &CueReading) -> bool {
    reading.margin.iter().all(|&m| m >= CONFIDENT_MARGIN)
}

/// `true` when `read` is `fit` with every cell flipped, up to a shift, and `fit` is not its own
/// inverse up to a shift (a plain, a 2/2 twill, a rib or a basket has one face).
fn is_inverted_twin(fit: &WeavePattern, read: &WeavePattern) -> bool {
    let inv = fit.inverted();
    read.equivalent(&inv) && !fit.equivalent(&inv)
}

/// The cues' verdict on the face of the cloth: `true` when `fit` and `read` are both named weaves
/// (a weave class other than `Other`, as in [`contest`]), `read` is the inverted twin of `fit` (the same weave seen from the
/// back), and the cues favour `read` over `fit` by at least [`FACE_GAIN_PER_CELL`] per cell of the
/// `cues` grid; `false` otherwise (no face question, or the picture does not tell).
///
/// Why the picture decides here and not the loss: on one colour the two faces of a twill or satin
/// differ only in which family floats long, which both the orientation inside each cell and the
/// continuity across each boundary read directly, while the model's loss compares renders whose
/// yarn paths and shading are the model's own: a renderer other than the model's can make the
/// wrong face the model's better fit (the Mitsuba 2/1 twills m2121_04 and m2121_08: the loss of
/// the truth's face 2.6× and 2.0× its twin's after the same appearance descent, docs/benchmarks.md
/// session 22), so no loss margin separates "the loss cannot tell" from "the loss knows".
pub(crate) fn face_verdict(cues: &CellCues, fit: &WeavePattern, read: &WeavePattern) -> bool {
    use crate::pattern::WeaveClass;
    let (n_e, n_a) = (cues.n_e, cues.n_a);
    if (fit.n_e(), fit.n_a()) != (n_e, n_a) || (read.n_e(), read.n_a()) != (n_e, n_a) {
        return false;
    }
    let named = |p: &WeavePattern| p.weave_class() != WeaveClass::Other;
    let gain = cues.energy(&labelling(fit, n_e, n_a)) - cues.energy(&labelling(read, n_e, n_a));
    // NaN (no finite energies) is no verdict.
    named(fit) && named(read) && is_inverted_twin(fit, read) && gain >= FACE_GAIN_PER_CELL * (n_e * n_a) as f64
}

/// Row-major labelling of `p` (`true` = weft on top), on `n_e × n_a` cells.
pub fn labelling(p: &WeavePattern, n_e: usize, n_a: usize) -> Vec<bool> {
    (0..n_e).flat_map(|i| (0..n_a).map(move |j| (i, j))).map(|(i, j)| p.get(i, j)).collect()
}

/// The named weave of the grid (`parsimony::named_weaves`: the presets, the ribs and baskets,
/// every twill and regular satin, each shift and back) of least cue energy, with that energy; `None` when none fits
/// the grid.
///
/// Why: where the exhaustive reading lands a cell or two off any named weave (a hairy photo's
/// cues are noisy cell by cell), the cues still tell the weaves apart as wholes. On the
/// two-colour twill FabricNET W104 the reading `1011/1101/0110/0111` is irregular, yet the cues
/// rank the twills (3/1: −41.5, 2/2: −35.5) far above the basket the fit chose (−28.9); with the
/// irregular reading alone that evidence never met the fit's pattern.
fn best_named_reading(cues: &CellCues) -> Option<(WeavePattern, f64)> {
    let (n_e, n_a) = (cues.n_e, cues.n_a);
    super::parsimony::named_weaves(n_e, n_a)
        .into_iter()
        .map(|p| {
            let e = cues.energy(&labelling(&p, n_e, n_a));
            (p, e)
        })
        .filter(|(_, e)| e.is_finite())
        .min_by(|a, b| a.1.total_cmp(&b.1))
}

/// How the contest of `contest` (the fitted pattern against the reading) ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum Verdict {
    /// No contest: the reading is the fit's pattern, its grid differs, or the cues do not prefer
    /// it by [`MIN_ENERGY_GAIN`].
    NoContest,
    /// The fit's pattern is a named weave and the reading is not, and no named weave is favoured
    /// by the cues over the fit's by [`MIN_ENERGY_GAIN`]: the fit's is kept.
    KeptNamed,
    /// The reading is a named weave and the fit's pattern is not: the reading replaces it.
    TookNamed,
    /// The loss decided (within [`LOSS_TOLERANCE`]): the reading replaced the fit's pattern.
    TookByLoss,
    /// The face rule (`face_verdict`): both are named weaves, the fit's pattern is the reading's
    /// inverted twin and the cues favour the reading by [`FACE_GAIN_PER_CELL`] per cell: the
    /// reading's face replaced the fit's, whatever the loss.
    TookFace,
    /// The loss decided: the fit's pattern stays.
    KeptByLoss,
}

/// What `contest` weighed and decided: the record a fit keeps (`FitResult::cue_contest`, written
/// as `cues.json`) so that a wrong pattern can be traced to the cues or to the loss without
/// re-running the fit.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ContestRecord {
    /// The fit's pattern before the contest (rows by weft, `woven params` notation).
    pub fit_pattern: String,
    /// The reading that met it: the cue reading, or the named weave the cues favour most when the
    /// reading is irregular and the fit's pattern is named (the cue reading where no contest ran).
    pub read_pattern: String,
    /// Cue energy of the fit's pattern minus the exhaustive reading's (how much the cues prefer
    /// their own reading, before a named weave stands in for an irregular one); `None` where the
    /// grids differ or no energy is finite.
    pub energy_gain: Option<f64>,
    /// Whether the face rule (`face_verdict`) held.
    pub face: bool,
    /// Loss of the fit's pattern after the contest's short appearance descent.
    pub loss_fit: Option<f32>,
    /// Loss of the better variant of the reading after the same descent.
    pub loss_read: Option<f32>,
    /// How it ended.
    pub verdict: Verdict,
}

impl ContestRecord {
    /// The record of `fit` against `read`, without losses (a contest that ended before any was
    /// computed; the others add theirs).
    fn new(fit: &WeavePattern, read: &WeavePattern, gain: Option<f64>, verdict: Verdict) -> Self {
        ContestRecord {
            fit_pattern: fit.to_string(),
            read_pattern: read.to_string(),
            energy_gain: gain.filter(|g| g.is_finite()),
            face: false,
            loss_fit: None,
            loss_read: None,
            verdict,
        }
    }
}

/// The contest of the fit's winner `cloth` against the cue reading, when the cues prefer their
/// pattern by at least [`MIN_ENERGY_GAIN`]:
///
/// * **Regular weaves first.** Real cloth is woven to a named weave (plain, twill, satin, basket)
///   far more often than to an irregular pattern, and a reading that is a named weave is strong
///   evidence by itself: a reading from noise lands on one only by coincidence (of the 2¹⁶
///   labellings of a 4×4 grid, 8 are 2/2 twills). So where exactly one of the two patterns is a
///   named weave, that one is kept, whatever the loss. Why the loss is not trusted there: on the
///   hairy same-coloured twill FabricNET W117 the fit reached a pattern one cell from the
///   *inverse* of the twill whose floats the sharp photo shows (fibres along the top yarn in each
///   cell, looked at), with a loss 19 % below the twill's: the fit compares a nearly flat render
///   with the blurred mean repeat, in which a float's bright centre on a cell boundary and its dark
///   ends look much like the other family's.
/// * **An irregular reading against a named winner** hands over to the named weave the cues
///   favour most (`best_named_reading`), when they favour it over the winner's pattern by
///   [`MIN_ENERGY_GAIN`]; that weave then meets the winner by the loss (next point), both named.
/// * **The face of the cloth from the picture** ([`face_verdict`]): where both are named and the
///   winner is the (named) reading's inverted twin — the same weave seen from the back — and the
///   cues favour the reading's face by [`FACE_GAIN_PER_CELL`] per cell, the reading is kept
///   whatever the loss (the better of its two variants below).
/// * **Otherwise the loss decides**: the reading's pattern with the winner's appearance and
///   shape, and with the families' colours and radii swapped, each get the same appearance
///   descent (`lm_iters` Levenberg–Marquardt iterations, `refine::polish` without radius rounds)
///   as the winner; the better replaces the winner when its loss is within [`LOSS_TOLERANCE`]
///   (zero: not higher) of the winner's. (Where the named-weave rule takes the reading, the better
///   of the two variants is what replaces the winner.)
///
/// Returns the cloth kept (polished where a contest ran) and the record of the contest.
pub(crate) fn contest(
    ev: &super::evaluator::Evaluator,
    cues: &CellCues,
    reading: &CueReading,
    cloth: &crate::params::ClothParams,
    known: &[crate::params::ClothParams],
    lm_iters: usize,
    stop: &std::sync::atomic::AtomicBool,
) -> (crate::params::ClothParams, ContestRecord) {
    use crate::pattern::WeaveClass;
    let (n_e, n_a) = (cloth.pattern.n_e(), cloth.pattern.n_a());
    let no_contest = |gain| ContestRecord::new(&cloth.pattern, &reading.pattern, gain, Verdict::NoContest);
    if (n_e, n_a) != (cues.n_e, cues.n_a) || reading.pattern == cloth.pattern {
        return (cloth.clone(), no_contest(None));
    }
    let gain = cues.energy(&labelling(&cloth.pattern, n_e, n_a)) - reading.energy;
    // NaN (no finite energies) starts no contest either.
    if gain.is_nan() || gain < MIN_ENERGY_GAIN {
        return (cloth.clone(), no_contest(Some(gain)));
    }
    let named = |p: &WeavePattern| p.weave_class() != WeaveClass::Other;
    let (fit_named, read_named) = (named(&cloth.pattern), named(&reading.pattern));
    // An irregular reading does not overrule a named winner, but the cues still rank the named
    // weaves: the one they favour most, when they favour it over the winner by
    // [`MIN_ENERGY_GAIN`], meets the winner by the loss instead (both named). A reading sure of
    // every cell ([`confident`]) is no noisy near-miss of a named weave: it meets the winner by
    // the loss itself.
    let read_pattern = if fit_named && !read_named && !confident(reading) {
        let fit_energy = cues.energy(&labelling(&cloth.pattern, n_e, n_a));
        match best_named_reading(cues) {
            Some((p, e)) if p != cloth.pattern && fit_energy - e >= MIN_ENERGY_GAIN => p,
            _ => {
                let kept = ContestRecord::new(&cloth.pattern, &reading.pattern, Some(gain), Verdict::KeptNamed);
                return (cloth.clone(), kept);
            }
        }
    } else {
        reading.pattern.clone()
    };
    let read_named = named(&read_pattern);
    // The reading with the winner's appearance, and with the families' colours and radii swapped
    // (`candidates::inverted_twin`): a reading near the *inverse* of the fit's pattern lays the
    // other family on the cells the winner's colours were fitted to, and a short appearance
    // descent does not swap two colours. Beside them, every state the fit reached with the
    // reading's pattern itself (`known`: the warm-up's candidates, the joint runs' bests), with
    // its own shape and ply count: the winner's were fitted to another pattern. The best of them
    // goes on. Why: on the yarn-dyed plain FabricNET W025 the fit ended on an irregular 6 × 2
    // pattern (its stripes read as cells) and the cues' plain, taken with that pattern's 4 plies
    // and radii, scored 0.0455 where the warm-up's own plain had reached 0.043; from there the
    // yarn colours ended at 0.018 and the crop at 17.9 dB, against 0.011 and 21.1 dB from the
    // plain's own state.
    let (cue, l_cue) = [cloth.clone(), super::candidates::inverted_twin(cloth)]
        .into_iter()
        .chain(known.iter().filter(|k| k.pattern == read_pattern).cloned())
        .map(|mut c| {
            c.pattern = read_pattern.clone();
            let l = super::refine::polish(ev, &mut c, 0, lm_iters, stop);
            (c, l)
        })
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .expect("two variants");
    let record = |face, loss_fit: Option<f32>, verdict| ContestRecord {
        face,
        loss_fit: loss_fit.filter(|l| l.is_finite()),
        loss_read: Some(l_cue).filter(|l| l.is_finite()),
        ..ContestRecord::new(&cloth.pattern, &read_pattern, Some(gain), verdict)
    };
    if read_named && !fit_named {
        return (cue, record(false, None, Verdict::TookNamed));
    }
    let mut own = cloth.clone();
    let l_own = super::refine::polish(ev, &mut own, 0, lm_iters, stop);
    // The face rule: a named winner and a named reading that are each other's inverted twins,
    // the cues clearly for the reading's face.
    let face = face_verdict(cues, &cloth.pattern, &read_pattern);
    if face && l_cue.is_finite() {
        return (cue, record(face, Some(l_own), Verdict::TookFace));
    }
    if l_cue.is_finite() && l_cue <= l_own * (1.0 + LOSS_TOLERANCE) {
        (cue, record(face, Some(l_own), Verdict::TookByLoss))
    } else {
        (own, record(face, Some(l_own), Verdict::KeptByLoss))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::prep::testutil::{add_noise, plain, render_flat, render_texture_rotated, twill22};

    /// Truth of an image whose cell rows are listed top to bottom (`rows[r][j]`, 1 = weft on
    /// top), in the pattern's convention (weft 0 is the bottom row).
    fn from_image_rows(rows: &[Vec<u8>]) -> WeavePattern {
        let p: Vec<Vec<bool>> = rows.iter().rev().map(|r| r.iter().map(|&v| v == 1).collect()).collect();
        WeavePattern::from_rows_unreduced(&p).unwrap()
    }

    /// m3232_04: preparation's boundaries at 10.54 + k·14.29 px and 5.47 + k·14.18 px; the fit's
    /// corner (67, 93) is read on the boundaries (67.70, 90.53), 0.05 and 0.17 cell away; a
    /// corner moved half a cell (onto the yarn centres' lattice, as `align_to_cells` does where
    /// the grid landed there) stays where the fit put it.
    #[test]
    fn the_cue_grid_snaps_to_preparations_boundaries_only_when_near() {
        let (px, py) = (14.290419, 14.176409);
        let x = snap_to_boundary(67.0, 10.541961, px);
        let y = snap_to_boundary(93.0, 5.471865, py);
        assert!((x - (10.541961 + 4.0 * px)).abs() < 1e-9, "{x}");
        assert!((y - (5.471865 + 6.0 * py)).abs() < 1e-9, "{y}");
        assert_eq!(snap_to_boundary(67.7 + 0.5 * px, 10.541961, px), 67.7 + 0.5 * px);
        assert_eq!(snap_to_boundary(67.7 + 0.3 * px, 10.541961, px), 67.7 + 0.3 * px);
        assert_eq!(snap_to_boundary(12.0, f64::NAN, px), 12.0);
        assert_eq!(snap_to_boundary(12.0, 3.0, 0.0), 12.0);
    }

    /// A reading is confident only when every cell's margin reaches `CONFIDENT_MARGIN` (a cell
    /// whose flip leaves no woven pattern counts as sure; NaN does not).
    #[test]
    fn a_reading_is_confident_only_when_sure_of_every_cell() {
        let p = WeavePattern::parse("001010/100100/111011").unwrap();
        let r = |margin: Vec<f64>| CueReading { pattern: p.clone(), margin, energy: -365.9 };
        assert!(confident(&r(vec![30.8, 59.4, f64::INFINITY])));
        assert!(!confident(&r(vec![30.8, 2.5, f64::INFINITY])), "one cell a near-miss");
        assert!(!confident(&r(vec![30.8, f64::NAN])));
    }

    #[test]
    fn otsu_splits_between_the_two_groups_whatever_their_sizes() {
        assert!((otsu_split(&[0.0, 0.1, 0.2, 5.0, 5.1]) - 2.6).abs() < 1e-12);
        // One cell of five in its own group (a satin's binding points).
        assert!((otsu_split(&[-3.0, 1.0, 1.1, 0.9, 1.2]) - (-1.05)).abs() < 1e-12);
        assert_eq!(otsu_split(&[2.0, 2.0]), 2.0);
    }

    #[test]
    fn the_reading_of_hand_made_cues_and_its_margins() {
        // 2×2: the orientation says checker; the only woven labellings are the two checkers,
        // energies −4 and +4, so every cell's margin is 8.
        let c = CellCues {
            n_e: 2,
            n_a: 2,
            orient: vec![1.0, -1.0, -1.0, 1.0],
            weft_link: vec![0.0; 4],
            warp_link: vec![0.0; 4],
            copies: 5,
        };
        let r = c.read().unwrap();
        assert_eq!(r.pattern, WeavePattern::parse("10/01").unwrap());
        assert_eq!(r.energy, -4.0);
        assert_eq!(r.margin, vec![8.0; 4]);
        // 4×4 with no orientation at all: the links alone of a 2/2 twill (weft i floats over
        // warps i, i+1; warp j over wefts j+1, j+2) give that twill, and nothing else as well.
        let twill = WeavePattern::parse("1100/0110/0011/1001").unwrap();
        let mut c = CellCues {
            n_e: 4,
            n_a: 4,
            orient: vec![0.0; 16],
            weft_link: vec![-1.0; 16],
            warp_link: vec![-1.0; 16],
            copies: 5,
        };
        for i in 0..4 {
            c.weft_link[i * 4 + i] = 5.0; // weft i over warps i and i + 1
            c.warp_link[((i + 1) % 4) * 4 + i] = 5.0; // warp i on top of wefts i + 1 and i + 2
        }
        let r = c.read().unwrap();
        assert_eq!(r.pattern, twill, "{}", r.pattern);
        assert!(r.margin.iter().all(|&m| m > 0.0), "{:?}", r.margin);
        assert_eq!(r.energy, c.energy(&labelling(&twill, 4, 4)));
    }

    /// A 2/2 twill as hairy yarns photographed front-lit, in the manner of `soft_twill13`: one
    /// colour, no gaps between parallel yarns (the flanks fall to `flank` of the crown), every
    /// float darker toward its ends, fibre streaks along the top yarn. Weft `ci` floats over
    /// cells `cj ≡ ci, ci + 1 (mod 4)`. Texture coordinates in pitches.
    fn soft_twill22(tx: f64, ty: f64, flank: f64) -> [f32; 3] {
        use std::f64::consts::PI;
        let (ci, cj) = (ty.floor() as i64, tx.floor() as i64);
        let (fx, fy) = (tx - tx.floor(), ty - ty.floor());
        let weft_on_top = (cj - ci).rem_euclid(4) < 2;
        let crown = |across: f64| flank + (1.0 - flank) * (PI * across).cos().max(0.0);
        // Streaks: a fine stripe pattern running along the yarn on top.
        let streak = |across: f64| 1.0 + 0.08 * (2.0 * PI * 6.0 * across).sin();
        let b = if weft_on_top {
            let along = (tx - ci as f64).rem_euclid(4.0); // 0..2 along the float
            crown(fy - 0.5) * streak(fy) * (0.6 + 0.4 * (PI * along / 2.0).sin().max(0.0))
        } else {
            let along = (ty - (cj - 2) as f64).rem_euclid(4.0); // 0..2 along the warp float
            crown(fx - 0.5) * streak(fx) * (0.6 + 0.4 * (PI * along / 2.0).sin().max(0.0))
        };
        let b = b as f32;
        [0.5 * b, 0.8 * b, 0.7 * b]
    }

    #[test]
    fn a_hairy_unbalanced_twill_is_read_from_its_copies() {
        // A soft, same-coloured 2/2 twill (no gaps between yarns, float ends darker, streaks along
        // the top yarn), warp pitch 1.5× the weft pitch as on FabricNET W117, with noise.
        let pitch = [36.0, 24.0];
        let (w, h) = (300, 240);
        let img = render_texture_rotated(pitch, w, h, 0.0, |tx, ty| soft_twill22(tx, ty, 0.55));
        // Fine isotropic texture (fibres, sensor): in cell units its gradients weigh 1.5² more
        // along x than along y, which calls every cell warp unless the cue is centred.
        let img = add_noise(&img, 0.06, 7);
        let g = Gray::from_rgb(&img);
        // Cell boundaries of `render_texture_rotated` at angle 0: x = w/2 + k·pitch.
        let origin = [(w as f64 / 2.0).rem_euclid(pitch[0]), (h as f64 / 2.0).rem_euclid(pitch[1])];
        let cues = read_cues(&g, pitch, origin, 4, 4).expect("cues");
        assert!(cues.copies >= 2, "{}", cues.copies);
        // Image row r (from the boundary at `origin`), cell j: weft on top where (j − r) mod 4 < 2
        // in the texture's cell indices (1000 pitches is a multiple of 4).
        let k0 = |o: f64, extent: u32, p: f64| ((o - extent as f64 / 2.0) / p).round() as i64;
        let (jx, iy) = (k0(origin[0], w, pitch[0]), k0(origin[1], h, pitch[1]));
        let rows: Vec<Vec<u8>> =
            (0..4).map(|r| (0..4).map(|j| u8::from((j + jx - r - iy).rem_euclid(4) < 2)).collect()).collect();
        let truth = from_image_rows(&rows);
        let r = cues.read().expect("a reading");
        assert!(r.pattern.equivalent(&truth), "read {} for {}", r.pattern, truth);
        assert!(r.margin.iter().all(|&m| m > 0.0), "{:?}", r.margin);
    }

    /// One-colour yarns of the image-row pattern `rows` (1 = weft on top, `rows[r][j]` image row
    /// `r` from the top), touching (no dark gaps: the flanks fall to 0.55 of the crown) and each
    /// float darker toward its ends, where it dives under: the two faces of a twill differ only in
    /// which family's floats are long. With `blobs`, every cell is instead the same round bump (no
    /// yarn direction anywhere): a picture that cannot tell a face. Texture coordinates in pitches.
    fn one_colour_weave(rows: &[Vec<u8>], tx: f64, ty: f64, blobs: bool) -> [f32; 3] {
        use std::f64::consts::PI;
        let (n_r, n_c) = (rows.len() as i64, rows[0].len() as i64);
        let (ci, cj) = (ty.floor() as i64, tx.floor() as i64);
        let (fx, fy) = (tx - tx.floor(), ty - ty.floor());
        let weft = |i: i64, j: i64| rows[i.rem_euclid(n_r) as usize][j.rem_euclid(n_c) as usize] == 1;
        let crown = |across: f64| 0.55 + 0.45 * (PI * across).cos().max(0.0);
        let b = if blobs {
            crown(((fx - 0.5).powi(2) + (fy - 0.5).powi(2)).sqrt())
        } else if weft(ci, cj) {
            // The weft's float: the run of weft cells along the row through this one.
            let (mut a, mut z) = (cj, cj);
            while weft(ci, a - 1) && cj - a < n_c {
                a -= 1;
            }
            while weft(ci, z + 1) && z - cj < n_c {
                z += 1;
            }
            let along = (tx - a as f64) / (z - a + 1) as f64;
            crown(fy - 0.5) * (0.55 + 0.45 * (PI * along).sin())
        } else {
            let (mut a, mut z) = (ci, ci);
            while !weft(a - 1, cj) && ci - a < n_r {
                a -= 1;
            }
            while !weft(z + 1, cj) && z - ci < n_r {
                z += 1;
            }
            let along = (ty - a as f64) / (z - a + 1) as f64;
            crown(fx - 0.5) * (0.55 + 0.45 * (PI * along).sin())
        };
        let b = b as f32;
        [0.6 * b, 0.62 * b, 0.58 * b]
    }

    /// The cues of `one_colour_weave(rows)` at 20 px per cell with noise, and the truth up to a
    /// shift (where the grid starts in the texture is left to the checks' shifts).
    fn one_colour_cues(rows: &[Vec<u8>], blobs: bool) -> (CellCues, WeavePattern) {
        let (pitch, w, h) = ([20.0, 20.0], 240, 240);
        let img = render_texture_rotated(pitch, w, h, 0.0, |tx, ty| one_colour_weave(rows, tx, ty, blobs));
        let img = add_noise(&img, 0.01, 11);
        // Cell boundaries of `render_texture_rotated` at angle 0: x = w/2 + k·pitch.
        let origin = [(w as f64 / 2.0).rem_euclid(pitch[0]), (h as f64 / 2.0).rem_euclid(pitch[1])];
        let cues = read_cues(&Gray::from_rgb(&img), pitch, origin, rows.len(), rows[0].len()).expect("cues");
        (cues, from_image_rows(rows))
    }

    /// Every cyclic shift of `p`.
    fn shifts(p: &WeavePattern) -> Vec<WeavePattern> {
        let rows = p.rows();
        let (n_e, n_a) = (p.n_e(), p.n_a());
        (0..n_e)
            .flat_map(|di| (0..n_a).map(move |dj| (di, dj)))
            .map(|(di, dj)| {
                let r: Vec<Vec<bool>> =
                    (0..n_e).map(|i| (0..n_a).map(|j| rows[(i + di) % n_e][(j + dj) % n_a]).collect()).collect();
                WeavePattern::from_rows_unreduced(&r).expect("a weave")
            })
            .collect()
    }

    #[test]
    fn a_one_colour_twill_and_its_twin_are_each_read_face_up() {
        // A weft-faced 2/1 twill and its inverse (warp-faced 1/2), one colour, no gaps.
        let weft_faced = vec![vec![1, 1, 0], vec![0, 1, 1], vec![1, 0, 1]];
        let warp_faced: Vec<Vec<u8>> = weft_faced.iter().map(|r| r.iter().map(|&v| 1 - v).collect()).collect();
        for rows in [weft_faced, warp_faced] {
            let (cues, truth) = one_colour_cues(&rows, false);
            let r = cues.read().expect("a reading");
            assert!(r.pattern.equivalent(&truth), "read {} for {}", r.pattern, truth);
            // The face rule turns the inverted twin, at any shift, back to the reading, and never
            // the reading to its twin.
            for twin in shifts(&truth.inverted()) {
                assert!(face_verdict(&cues, &twin, &r.pattern), "twin {twin} of {truth}");
                assert!(!face_verdict(&cues, &r.pattern, &twin), "{} to {twin}", r.pattern);
            }
            // Not a face question: the reading against itself shifted, or against a mirrored twill.
            for other in shifts(&truth) {
                assert!(!face_verdict(&cues, &other, &r.pattern));
            }
        }
    }

    #[test]
    fn a_picture_without_yarn_direction_gives_no_face_verdict() {
        let rows = vec![vec![1, 1, 0], vec![0, 1, 1], vec![1, 0, 1]];
        let (cues, truth) = one_colour_cues(&rows, true);
        for (p, twin) in shifts(&truth).iter().flat_map(|p| shifts(&truth.inverted()).into_iter().map(move |t| (p, t)))
        {
            assert!(!face_verdict(&cues, &twin, p), "{twin} to {p}");
            assert!(!face_verdict(&cues, p, &twin), "{p} to {twin}");
        }
    }

    #[test]
    fn plain_and_twill_renders_are_read_exactly() {
        for (rows, pitch) in [(plain(), 20.0), (twill22(), 16.0)] {
            let img = add_noise(&render_flat(&rows, pitch, 200, 176), 0.01, 3);
            let cues =
                read_cues(&Gray::from_rgb(&img), [pitch, pitch], [0.0, 0.0], rows.len(), rows[0].len()).expect("cues");
            let r = cues.read().expect("a reading");
            assert!(r.pattern.equivalent(&from_image_rows(&rows)), "read {}", r.pattern);
        }
    }

    #[test]
    fn no_cues_without_structure_or_copies() {
        let flat = Gray { w: 100, h: 100, data: vec![0.5; 10_000] };
        assert!(read_cues(&flat, [10.0, 10.0], [0.0, 0.0], 2, 2).is_none(), "a uniform image has no cues");
        let img = Gray::from_rgb(&render_flat(&twill22(), 16.0, 100, 100));
        assert!(read_cues(&img, [4.0, 16.0], [0.0, 0.0], 4, 4).is_none(), "pitch under 6 px");
        assert!(read_cues(&img, [16.0, 16.0], [0.0, 0.0], 4, 4).is_none(), "one copy of a 4×4 repeat in 100 px");
        assert!(read_cues(&img, [16.0, 16.0], [f64::NAN, 0.0], 4, 4).is_none());
        assert!(read_cues(&img, [16.0, 16.0], [0.0, 0.0], 0, 4).is_none());
    }

    #[test]
    fn the_face_rule_takes_the_cues_face_of_a_twill_whatever_the_loss() {
        use crate::fit::candidates::inverted_twin;
        use crate::fit::evaluator::Evaluator;
        use crate::fit::preestimate::default_cloth;
        use crate::fit::target::fit_scene;
        use crate::scene::LightRig;
        use std::sync::atomic::AtomicBool;
        // A one-colour weft-faced 2/1 twill rendered by the model itself: here the loss knows the
        // face, so a face taken against it shows that the rule, not the loss, decided.
        let mut truth = default_cloth(WeavePattern::parse("110/011/101").unwrap());
        truth.appearance.r_b_e = [0.6, 0.5, 0.4];
        truth.appearance.r_b_a = [0.6, 0.5, 0.4];
        let (n_e, n_a) = (3, 3);
        let ev = Evaluator::of_own_render(&truth, fit_scene(n_e, n_a, 8, 2, 1, &LightRig::default_rig()));
        let stop = AtomicBool::new(false);
        let twin = inverted_twin(&truth).pattern;
        // Cues that favour the twin by `t` per cell (orientation only).
        let cues_for = |t: f64| CellCues {
            n_e,
            n_a,
            orient: labelling(&twin, n_e, n_a).iter().map(|&v| if v { t } else { -t }).collect(),
            weft_link: vec![0.0; n_e * n_a],
            warp_link: vec![0.0; n_e * n_a],
            copies: 4,
        };
        let reading = |c: &CellCues| CueReading {
            pattern: twin.clone(),
            margin: vec![1.0; 9],
            energy: c.energy(&labelling(&twin, n_e, n_a)),
        };
        // 2 t-units per cell for the twin (an energy gain of 4 per cell): the twin's face is kept.
        let c = cues_for(2.0);
        assert!(face_verdict(&c, &truth.pattern, &twin));
        let (kept, ContestRecord { verdict: v, .. }) = contest(&ev, &c, &reading(&c), &truth, &[], 4, &stop);
        assert_eq!((v, &kept.pattern), (Verdict::TookFace, &twin));
        // A quarter of that (1 per cell, under FACE_GAIN_PER_CELL): a contest, which the loss
        // decides for the truth.
        let c = cues_for(0.5);
        assert!(!face_verdict(&c, &truth.pattern, &twin));
        let (kept, ContestRecord { verdict: v, .. }) = contest(&ev, &c, &reading(&c), &truth, &[], 4, &stop);
        assert_eq!((v, &kept.pattern), (Verdict::KeptByLoss, &truth.pattern));
    }

    #[test]
    fn the_contest_prefers_named_weaves_and_else_lets_the_loss_decide() {
        use crate::fit::candidates::toggled_cell;
        use crate::fit::evaluator::Evaluator;
        use crate::fit::preestimate::default_cloth;
        use crate::fit::target::fit_scene;
        use crate::pattern::WeaveClass;
        use crate::scene::LightRig;
        use std::sync::atomic::AtomicBool;
        // A 2/2 twill render with two families of different colours: the loss is informative.
        let mut truth = default_cloth(WeavePattern::parse("1100/0110/0011/1001").unwrap());
        truth.appearance.r_b_e = [0.7, 0.3, 0.2];
        truth.appearance.r_b_a = [0.2, 0.4, 0.7];
        let (n_e, n_a) = (4, 4);
        let ev = Evaluator::of_own_render(&truth, fit_scene(n_e, n_a, 8, 2, 1, &LightRig::default_rig()));
        let stop = AtomicBool::new(false);
        let wrong = toggled_cell(&truth, 0, 1).expect("a weave");
        assert_eq!(wrong.pattern.weave_class(), WeaveClass::Other);
        // Cues that favour `favoured` by 2 per cell.
        let cues_for = |favoured: &WeavePattern| CellCues {
            n_e,
            n_a,
            orient: labelling(favoured, n_e, n_a).iter().map(|&v| if v { 2.0 } else { -2.0 }).collect(),
            weft_link: vec![0.0; n_e * n_a],
            warp_link: vec![0.0; n_e * n_a],
            copies: 4,
        };
        let reading = |c: &CellCues, p: &WeavePattern| CueReading {
            pattern: p.clone(),
            margin: vec![4.0; n_e * n_a],
            energy: c.energy(&labelling(p, n_e, n_a)),
        };
        // A named reading replaces an irregular winner.
        let c = cues_for(&truth.pattern);
        let (kept, ContestRecord { verdict: v, .. }) =
            contest(&ev, &c, &reading(&c, &truth.pattern), &wrong, &[], 4, &stop);
        assert_eq!((v, &kept.pattern), (Verdict::TookNamed, &truth.pattern));
        // The same, with the winner's shape fitted to its own pattern (thinner yarns, more plies)
        // and the truth's own state known: the reading goes on from the known state, whose loss
        // is lower than the winner's shape gives it.
        let mut off = wrong.clone();
        (off.n_p, off.r_e, off.r_a) = (6, truth.r_e * 0.7, truth.r_a * 0.7);
        let (from_winner, _) = contest(&ev, &c, &reading(&c, &truth.pattern), &off, &[], 4, &stop);
        let known = [truth.clone(), wrong.clone()];
        let (kept, rec) = contest(&ev, &c, &reading(&c, &truth.pattern), &off, &known, 4, &stop);
        assert_eq!(
            (rec.verdict, &kept.pattern, kept.n_p, kept.r_e),
            (Verdict::TookNamed, &truth.pattern, truth.n_p, truth.r_e)
        );
        assert!(ev.trace_mse(&kept) < ev.trace_mse(&from_winner), "{rec:?}");
        // An irregular reading never replaces a named winner.
        let c = cues_for(&wrong.pattern);
        let (kept, ContestRecord { verdict: v, .. }) =
            contest(&ev, &c, &reading(&c, &wrong.pattern), &truth, &[], 4, &stop);
        assert_eq!((v, &kept.pattern), (Verdict::KeptNamed, &truth.pattern));
        // An irregular reading against a *wrong* named winner: the named weave the cues favour
        // most (the truth, one cell from the reading) meets the winner by the loss and wins it.
        let mut basket = truth.clone();
        basket.pattern = WeavePattern::parse("1100/1100/0011/0011").unwrap();
        assert_eq!(basket.pattern.weave_class(), WeaveClass::Basket);
        let c = cues_for(&wrong.pattern);
        assert_eq!(best_named_reading(&c).map(|b| b.0), Some(truth.pattern.clone()));
        let (kept, record) = contest(&ev, &c, &reading(&c, &wrong.pattern), &basket, &[], 4, &stop);
        assert_eq!((record.verdict, &kept.pattern), (Verdict::TookByLoss, &truth.pattern));
        // The record names what met (the named weave, not the irregular reading) and the losses
        // that decided: the truth's is not above the basket's.
        assert_eq!(record.fit_pattern, basket.pattern.to_string());
        assert_eq!(record.read_pattern, truth.pattern.to_string());
        let (l_fit, l_read) = (record.loss_fit.unwrap(), record.loss_read.unwrap());
        assert!(l_read <= l_fit, "{l_read} > {l_fit}");
        assert!(record.energy_gain.unwrap() >= MIN_ENERGY_GAIN);
        assert!(serde_json::to_string(&record).unwrap().contains("\"verdict\":\"TookByLoss\""));
        // Two irregular patterns: the loss decides, and on a clean render a wrong cell costs far
        // more than the tolerance, so the right winner stays against a wrong reading...
        let right = toggled_cell(&truth, 2, 2).expect("a weave");
        let ev2 = Evaluator::of_own_render(&right, fit_scene(n_e, n_a, 8, 2, 1, &LightRig::default_rig()));
        let both = toggled_cell(&right, 0, 1).expect("a weave");
        assert_eq!((right.pattern.weave_class(), both.pattern.weave_class()), (WeaveClass::Other, WeaveClass::Other));
        let c = cues_for(&both.pattern);
        let (kept, ContestRecord { verdict: v, .. }) =
            contest(&ev2, &c, &reading(&c, &both.pattern), &right, &[], 4, &stop);
        assert_eq!((v, &kept.pattern), (Verdict::KeptByLoss, &right.pattern));
        // ... and the right reading replaces a wrong winner.
        let c = cues_for(&right.pattern);
        let (kept, ContestRecord { verdict: v, .. }) =
            contest(&ev2, &c, &reading(&c, &right.pattern), &both, &[], 4, &stop);
        assert_eq!((v, &kept.pattern), (Verdict::TookByLoss, &right.pattern));
        // A winner one cell from the *inverse* of the truth, with the families' colours swapped
        // to match (what the twills W038 and W117 ended at): the reading replaces it with each
        // family's colour back in its place. (Here the short descent alone also swaps them back
        // from the unswapped variant; the swapped one is the guard where it does not.)
        let near_inverse = toggled_cell(&crate::fit::candidates::inverted_twin(&truth), 1, 1).expect("a weave");
        assert_eq!(near_inverse.pattern.weave_class(), WeaveClass::Other);
        let c = cues_for(&truth.pattern);
        let (kept, ContestRecord { verdict: v, .. }) =
            contest(&ev, &c, &reading(&c, &truth.pattern), &near_inverse, &[], 4, &stop);
        assert_eq!((v, &kept.pattern), (Verdict::TookNamed, &truth.pattern));
        let d = |a: [f32; 3], b: [f32; 3]| a.iter().zip(b).map(|(x, y)| (x - y).abs()).sum::<f32>();
        let a = &kept.appearance;
        assert!(d(a.r_b_e, truth.appearance.r_b_e) < d(a.r_b_e, truth.appearance.r_b_a), "weft {:?}", a.r_b_e);
        // Cues that barely prefer their reading start no contest.
        let mut weak = cues_for(&truth.pattern);
        weak.orient.iter_mut().for_each(|o| *o *= 0.05);
        let (kept, ContestRecord { verdict: v, .. }) =
            contest(&ev, &weak, &reading(&weak, &truth.pattern), &wrong, &[], 4, &stop);
        assert_eq!((v, &kept.pattern), (Verdict::NoContest, &wrong.pattern));
    }
}
