//! Yarn centre curves generated from the weave pattern (paper Appendix A, docs/design.md §1.1).
//!
//! Weft `i` runs along x at `y = (i + ½)·PITCH`, warp `j` along y at `x = (j + ½)·PITCH`. Each
//! yarn's height is a periodic cubic B-spline over `CTRL_PER_CELL` control values per crossed
//! cell: `+h` where it lies on top, `−h` where it lies below, Gaussian-smoothed (kernel 16).

use super::bspline::{floor_fast, PeriodicBSpline};
use crate::pattern::WeavePattern;
use glam::Vec3;

/// Yarn pitch (centre-to-centre distance): the length unit of the whole model.
pub const PITCH: f32 = 10.0;
/// Control points per crossed cell (paper: 12).
pub const CTRL_PER_CELL: usize = 12;
/// Gaussian kernel size in control points (paper: 16).
pub const SMOOTH_KERNEL: usize = 16;
/// Gaussian sigma in control points. The paper's σ = 1 leaves a square wave whose flanks are steeper
/// than the yarns are thick; σ = 3 (¼ cell) gives the "sinusoidal" crimp the paper describes.
pub const SMOOTH_SIGMA: f32 = 3.0;
/// Default crossing height as a fraction of the touching height `(r_e + r_a)/2`: yarns flatten
/// against each other, so the centres are closer than for round yarns ([`YarnShape::crossing`]).
pub const CRIMP: f32 = 0.7;

/// Cross-section shape of the yarns (docs/design.md §1.1): the crossing depth and the flattening.
///
/// A flattened yarn is the round tube of radius `r` around its centre curve, seen in a space
/// whose z axis is stretched by `1/aspect`: in the world, the tube's cross-section is an ellipse
/// with the half-width `r` across the cloth and the half-height `aspect·r` through it. One aspect
/// for the whole cloth makes this one linear map `S = diag(1, 1, 1/aspect)` of the whole tile, so
/// tracing, the ply mapping and the exit points stay the exact circle computations of the round
/// model in that space (`TileGeometry`, `PlyModel` convert rays in and normals out).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct YarnShape {
    /// Crossing height as a fraction of the touching height (`CRIMP` = 0.7 by default).
    pub crossing: f32,
    /// Half-height / half-width of the cross-section (1 = round).
    pub aspect: f32,
    /// Where the ply twist starts along the yarns, `[weft, warp]`: the arc length (model units)
    /// added to every yarn's arc length from the repeat's edge before the plies' and fibres'
    /// twist angles are taken from it (0 by default).
    ///
    /// Why: the twist is periodic per repeat but its phase is tied to where the repeat starts.
    /// A photo's crop starts at whatever yarn crossing the preparation chose, so the crop's
    /// helical ply stripes stand at a phase the model framed at its own repeat edge cannot show,
    /// whichever way the pattern is shifted: on the whole-path eval's 5-end satin (seed 1, target
    /// 0) the true cloth framed the model's way scored 19 dB against its prepared crop and 29 dB
    /// moved by whole cells (docs/benchmarks.md, session 19).
    pub ply_origin: [f32; 2],
    /// Fibre relief: the share of the fibres' own curvature in the shading normal (1 by default:
    /// each point shades with the normal of the fibre under it, §1.4; 0: with the ply's, so a
    /// single-ply yarn shades as a smooth tube).
    ///
    /// Why: the fibre normal field turns the normal by up to ±90° across every fibre, so a yarn
    /// of the model cannot show the one sharp highlight along its crown that a smooth, glossy
    /// tube (a filament yarn, another renderer's plastic tube) shows under a small light: the fit
    /// explained it as a broad, tinted specular lobe instead (docs/benchmarks.md, session 29).
    /// Left out of files at its default, so that files without it read as before.
    #[serde(skip_serializing_if = "full_relief")]
    pub relief: f32,
}

/// True for the default relief of [`YarnShape::relief`] (1: every fibre's own normal).
fn full_relief(relief: &f32) -> bool {
    *relief == 1.0
}

impl Default for YarnShape {
    fn default() -> Self {
        YarnShape { crossing: CRIMP, aspect: 1.0, ply_origin: [0.0; 2], relief: 1.0 }
    }
}

impl YarnShape {
    /// Range of [`YarnShape::crossing`]: from yarns pressed deep into each other (0.3) to round
    /// yarns just touching (1.0).
    pub const CROSSING_RANGE: (f32, f32) = (0.3, 1.0);
    /// Range of [`YarnShape::aspect`]: from a ribbon three times wider than thick to round.
    pub const ASPECT_RANGE: (f32, f32) = (0.33, 1.0);
    /// Range of [`YarnShape::relief`]: from smooth plies to the fibres' full relief.
    pub const RELIEF_RANGE: (f32, f32) = (0.0, 1.0);

    /// True for the default shape (round yarns, crossing 0.7): parameter files leave it out.
    pub fn is_default(&self) -> bool {
        *self == YarnShape::default()
    }
}

/// Which yarn family.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Family {
    /// Weft: runs along x, rows of `P`.
    Weft,
    /// Warp: runs along y, columns of `P`.
    Warp,
}

impl Family {
    /// 0 for the weft, 1 for the warp: the order of every `[weft, warp]` pair of the model
    /// (`YarnShape::ply_origin`, the shading's per-family colours).
    pub fn index(self) -> usize {
        match self {
            Family::Weft => 0,
            Family::Warp => 1,
        }
    }
}

/// One yarn's centre curve `c(s)` and radius.
#[derive(Clone, Debug)]
pub struct YarnCurve {
    /// Family.
    pub family: Family,
    /// Row (weft) or column (warp) index in the pattern.
    pub index: usize,
    /// Fixed lateral coordinate (y for weft, x for warp).
    pub offset: f32,
    /// Tube radius.
    pub radius: f32,
    /// Cross-section aspect ([`YarnShape::aspect`]): the curve and the tube below live in the
    /// stretched space `z/aspect`; [`YarnCurve::to_round`] maps world points there.
    pub aspect: f32,
    /// Fibre relief ([`YarnShape::relief`]): the scale of the fibres' normal perturbation.
    pub relief: f32,
    /// Height profile over the length coordinate `s` (x for weft, y for warp).
    pub height: PeriodicBSpline,
    /// Length along `s` of the pattern's minimum repeat (≤ the curve's period when the tile holds
    /// several repeats): twist rates are whole turns per repeat.
    pub repeat: f32,
    /// Arc length added to [`YarnCurve::arc_length`] in the frame ([`YarnShape::ply_origin`] of
    /// the yarn's family): the phase of the ply and fibre twist.
    pub arc_origin: f32,
    arc: Vec<f32>,
    /// Arc-length table steps per unit `s` (`(arc.len() − 1) / period`).
    arc_du: f32,
}

/// Local frame of a yarn at `s`.
#[derive(Clone, Copy, Debug)]
pub struct YarnFrame {
    /// Centre point.
    pub c: Vec3,
    /// Unit tangent `e_z`.
    pub t: Vec3,
    /// Reference "up" normal `e_y` (perpendicular to `t`, towards +z).
    pub ey: Vec3,
    /// `e_x = e_y × e_z`.
    pub ex: Vec3,
    /// Arc length from `s = 0`, plus the yarn's twist origin ([`YarnCurve::arc_origin`]).
    pub arc: f32,
}

/// A point on (or near) a yarn's tube with the frame of its nearest centre-curve point: the
/// point `q` in the stretched space where the tube is round, and `frame(closest_s(q))`.
///
/// A path vertex asks its own tube many questions at one point: the tube normal, the ply hit, and
/// for each shadow ray into its own tube the ply test and the exit distance; a shadow ray that
/// passes a tube between its plies asks two. Each started with the Newton search for the closest
/// curve parameter (two B-spline evaluations) and the frame there (another, plus the arc-length
/// table): 17 % of a render's profile was `closest_s` and `frame`. The anchor computes them once;
/// every answer is the same to the bit, since the same functions see the same inputs.
#[derive(Clone, Copy, Debug)]
pub struct Anchor {
    /// The point in the stretched space ([`YarnCurve::to_round`]).
    pub q: Vec3,
    /// The frame at the closest curve parameter of `q`.
    pub frame: YarnFrame,
}

const ARC_STEPS_PER_CELL: usize = 32;

impl YarnCurve {
    fn new(family: Family, index: usize, radius: f32, heights: Vec<f32>) -> Self {
        let period = heights.len() as f32 / CTRL_PER_CELL as f32 * PITCH;
        let height = PeriodicBSpline::new(heights, period);
        let n = (period / PITCH) as usize * ARC_STEPS_PER_CELL;
        let ds = period / n as f32;
        let mut arc = vec![0.0; n + 1];
        for k in 0..n {
            let slope = |s: f32| (1.0 + height.eval(s).1.powi(2)).sqrt();
            // Simpson's rule per step: the true arc length (ambiguity 18, docs/design.md).
            let s0 = k as f32 * ds;
            arc[k + 1] = arc[k] + ds / 6.0 * (slope(s0) + 4.0 * slope(s0 + ds / 2.0) + slope(s0 + ds));
        }
        let offset = (index as f32 + 0.5) * PITCH;
        let arc_du = n as f32 / period;
        YarnCurve {
            family,
            index,
            offset,
            radius,
            aspect: 1.0,
            relief: 1.0,
            height,
            repeat: period,
            arc_origin: 0.0,
            arc,
            arc_du,
        }
    }

    /// World point → the stretched space where this yarn's tube is round (identity when round).
    #[inline]
    pub fn to_round(&self, p: Vec3) -> Vec3 {
        if self.aspect == 1.0 {
            p
        } else {
            Vec3::new(p.x, p.y, p.z / self.aspect)
        }
    }

    /// World direction → unit direction in the stretched space and the length factor `|S d|`
    /// (a stretched distance `t'` is the world distance `t'/|S d|`).
    #[inline]
    pub fn dir_to_round(&self, d: Vec3) -> (Vec3, f32) {
        if self.aspect == 1.0 {
            (d, 1.0)
        } else {
            let s = Vec3::new(d.x, d.y, d.z / self.aspect);
            let len = s.length();
            (s / len, len)
        }
    }

    /// Stretched-space normal → world unit normal (normals map by `Sᵀ = diag(1, 1, 1/aspect)`).
    #[inline]
    pub fn normal_to_world(&self, n: Vec3) -> Vec3 {
        if self.aspect == 1.0 {
            n
        } else {
            Vec3::new(n.x, n.y, n.z / self.aspect).normalize_or(n)
        }
    }

    /// Stretched-space tangent → world unit tangent (tangents map by `S⁻¹ = diag(1, 1, aspect)`).
    #[inline]
    pub fn tangent_to_world(&self, t: Vec3) -> Vec3 {
        if self.aspect == 1.0 {
            t
        } else {
            Vec3::new(t.x, t.y, t.z * self.aspect).normalize_or(t)
        }
    }

    /// Outward unit tube normal at world point `p` on (or near) the tube.
    pub fn tube_normal(&self, p: Vec3) -> Vec3 {
        self.tube_normal_at(&self.anchor(p))
    }

    /// The nearest centre-curve frame of world point `p` ([`Anchor`]): what every question about
    /// the tube at `p` starts from, computed once.
    pub fn anchor(&self, p: Vec3) -> Anchor {
        let q = self.to_round(p);
        Anchor { q, frame: self.frame(self.closest_s(q)) }
    }

    /// [`YarnCurve::tube_normal`] at an anchored point: from the centre `c(s)` to the point, in
    /// the stretched space, mapped back to the world.
    pub fn tube_normal_at(&self, a: &Anchor) -> Vec3 {
        self.normal_to_world((a.q - a.frame.c).normalize_or(Vec3::Z))
    }

    /// Period of the curve along `s`.
    pub fn period(&self) -> f32 {
        self.height.period()
    }

    /// Length coordinate of a point (x for weft, y for warp).
    pub fn s_of(&self, p: Vec3) -> f32 {
        match self.family {
            Family::Weft => p.x,
            Family::Warp => p.y,
        }
    }

    /// Lateral coordinate of a point (y for weft, x for warp).
    pub fn lateral_of(&self, p: Vec3) -> f32 {
        match self.family {
            Family::Weft => p.y,
            Family::Warp => p.x,
        }
    }

    /// Centre point at `s`.
    pub fn point(&self, s: f32) -> Vec3 {
        let z = self.height.value(s);
        match self.family {
            Family::Weft => Vec3::new(s, self.offset, z),
            Family::Warp => Vec3::new(self.offset, s, z),
        }
    }

    fn axis(&self) -> Vec3 {
        match self.family {
            Family::Weft => Vec3::X,
            Family::Warp => Vec3::Y,
        }
    }

    /// Arc length from 0 to `s` (periodic extension).
    pub fn arc_length(&self, s: f32) -> f32 {
        let p = self.period();
        let laps = floor_fast(s / p);
        let u = (s - laps * p) * self.arc_du;
        let k = (u.max(0.0) as usize).min(self.arc.len() - 2);
        let f = u - k as f32;
        laps * self.arc[self.arc.len() - 1] + self.arc[k] * (1.0 - f) + self.arc[k + 1] * f
    }

    /// Frame at `s`; its arc length starts at the twist origin ([`YarnCurve::arc_origin`]).
    pub fn frame(&self, s: f32) -> YarnFrame {
        let (_, dz, _) = self.height.eval(s);
        let c = self.point(s);
        let t = (self.axis() + Vec3::Z * dz).normalize();
        let ey = (Vec3::Z - t * t.z).normalize();
        let ex = ey.cross(t);
        YarnFrame { c, t, ey, ex, arc: self.arc_length(s) + self.arc_origin }
    }

    /// Closest curve parameter to `p` (Newton on `(p − c(s))·c'(s) = 0`, started at the projection).
    pub fn closest_s(&self, p: Vec3) -> f32 {
        let mut s = self.s_of(p);
        for _ in 0..2 {
            let (z, dz, ddz) = self.height.eval(s);
            let ps = self.s_of(p);
            // g(s) = (ps − s) + (pz − z)·dz ; g'(s) = −1 − dz² + (pz − z)·ddz
            let g = (ps - s) + (p.z - z) * dz;
            let dg = -1.0 - dz * dz + (p.z - z) * ddz;
            if dg.abs() < 1e-6 {
                break;
            }
            s -= (g / dg).clamp(-2.0, 2.0);
        }
        s
    }

    /// Distance from `p` to the centre curve, and the closest parameter.
    pub fn distance(&self, p: Vec3) -> (f32, f32) {
        let s = self.closest_s(p);
        ((p - self.point(s)).length(), s)
    }
}

/// Gaussian smoothing of a periodic sequence (circular convolution, kernel `SMOOTH_KERNEL`).
fn smooth_periodic(v: &[f32]) -> Vec<f32> {
    let half = (SMOOTH_KERNEL / 2) as i64;
    let w: Vec<f32> = (-half..=half).map(|k| (-(k * k) as f32 / (2.0 * SMOOTH_SIGMA * SMOOTH_SIGMA)).exp()).collect();
    let sum: f32 = w.iter().sum();
    let n = v.len() as i64;
    (0..n)
        .map(|i| (-half..=half).zip(&w).map(|(k, wk)| wk * v[(i + k).rem_euclid(n) as usize]).sum::<f32>() / sum)
        .collect()
}

/// All yarn curves of one pattern repeat.
#[derive(Clone, Debug)]
pub struct YarnSet {
    /// Weft yarns (one per pattern row) then warp yarns (one per column).
    pub yarns: Vec<YarnCurve>,
    /// Tile size along x (`n_a · PITCH`).
    pub tile_x: f32,
    /// Tile size along y (`n_e · PITCH`).
    pub tile_y: f32,
    /// Crossing height `h` (in the stretched space of [`YarnShape`]; `aspect·h` in the world).
    pub h: f32,
    /// Cross-section shape.
    pub shape: YarnShape,
}

impl YarnSet {
    /// Generate the centre curves of `pattern` with weft radius `r_e` and warp radius `r_a`.
    pub fn new(pattern: &WeavePattern, r_e: f32, r_a: f32) -> Self {
        Self::with_shape(pattern, r_e, r_a, YarnShape::default())
    }

    /// [`YarnSet::new`] with a crossing depth and a flattening ([`YarnShape`]). The crossing height
    /// `h = crossing·(r_e + r_a)/2` is set in the stretched space where the tubes are round, so in
    /// the world it is `crossing·aspect·(r_e + r_a)/2`: the same fraction of the flattened yarns'
    /// touching height.
    pub fn with_shape(pattern: &WeavePattern, r_e: f32, r_a: f32, shape: YarnShape) -> Self {
        let (ne, na) = (pattern.n_e(), pattern.n_a());
        let h = shape.crossing * 0.5 * (r_e + r_a);
        let mut yarns = Vec::with_capacity(ne + na);
        for i in 0..ne {
            let raw: Vec<f32> =
                (0..na * CTRL_PER_CELL).map(|k| if pattern.get(i, k / CTRL_PER_CELL) { h } else { -h }).collect();
            yarns.push(YarnCurve::new(Family::Weft, i, r_e, smooth_periodic(&raw)));
        }
        for j in 0..na {
            let raw: Vec<f32> =
                (0..ne * CTRL_PER_CELL).map(|k| if pattern.get(k / CTRL_PER_CELL, j) { -h } else { h }).collect();
            yarns.push(YarnCurve::new(Family::Warp, j, r_a, smooth_periodic(&raw)));
        }
        let red = pattern.reduced();
        for y in &mut yarns {
            y.aspect = shape.aspect;
            y.relief = shape.relief;
            y.arc_origin = shape.ply_origin[y.family.index()];
            y.repeat = match y.family {
                Family::Weft => red.n_a() as f32 * PITCH,
                Family::Warp => red.n_e() as f32 * PITCH,
            };
        }
        YarnSet { yarns, tile_x: na as f32 * PITCH, tile_y: ne as f32 * PITCH, h, shape }
    }

    /// Highest point of any tube in the stretched space where the tubes are round (for bounding
    /// the cloth slab); `aspect` times it in the world.
    pub fn z_max(&self) -> f32 {
        self.yarns.iter().map(|y| y.radius).fold(0.0, f32::max) + self.h
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weft_over_warp_exactly_where_p_is_one() {
        for name in crate::pattern::PRESETS {
            let p = WeavePattern::preset(name).unwrap();
            let set = YarnSet::new(&p, 3.0, 3.5);
            for i in 0..p.n_e() {
                for j in 0..p.n_a() {
                    let (x, y) = ((j as f32 + 0.5) * PITCH, (i as f32 + 0.5) * PITCH);
                    let zw = set.yarns[i].height.eval(x).0;
                    let za = set.yarns[p.n_e() + j].height.eval(y).0;
                    assert_eq!(zw > za, p.get(i, j), "{name} cell ({i},{j}): weft {zw} warp {za}");
                    assert!((zw - za).abs() > 0.5, "{name} ({i},{j}) crossing too flat");
                }
            }
        }
    }

    #[test]
    fn arc_length_exceeds_chord_and_closest_point_converges() {
        let set = YarnSet::new(&WeavePattern::preset("plain").unwrap(), 4.0, 4.0);
        let y = &set.yarns[0];
        assert!(y.arc_length(y.period()) > y.period());
        let p = y.point(7.3) + Vec3::new(0.0, 0.5, 1.0);
        let (d, s) = y.distance(p);
        let brute = (0..20000).map(|k| (p - y.point(k as f32 * 1e-3)).length()).fold(f32::MAX, f32::min);
        assert!((d - brute).abs() < 1e-3, "{d} vs {brute} at s={s}");
    }
}
