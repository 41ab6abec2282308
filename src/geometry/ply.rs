//! Implicit plies and fibers (docs/design.md §1.2–§1.4): helical plies inside the yarn tube,
//! fibers as 1D cross-section tables (normal perturbation and ambient occlusion per angle).

use super::yarn::{Anchor, YarnCurve};
use glam::{Quat, Vec2, Vec3};
use rand::prelude::*;
use std::f32::consts::{PI, TAU};
use std::sync::OnceLock;

/// Resolution of the 1D cross-section tables.
pub const TABLE_RES: usize = 512;
/// Ply twist angle against the yarn axis (κ_p = tan(angle)/R_p).
pub const PLY_TWIST_DEG: f32 = 25.0;
/// Fiber twist angle on the ply surface (opposite to the ply twist).
pub const FIBER_TWIST_DEG: f32 = 30.0;

/// A 1D table over the angle around a bundle of `n` circular elements (plies in a yarn or fibers
/// in a ply): for a point seen from angle ϑ, the visible element's normal perturbation, its ambient
/// occlusion (min–max normalised, 1 = least occluded) and its centre radius.
#[derive(Clone, Debug)]
pub struct CrossSection {
    /// Signed angle from the bundle normal to the element normal.
    pub pert: Vec<f32>,
    /// Normalised ambient occlusion in [0, 1].
    pub ao: Vec<f32>,
    /// Radius of the visible element's centre (bundle radius 1).
    pub centre_r: Vec<f32>,
}

impl CrossSection {
    /// Build for `n` elements of radius `er` with centres at radii `radii[i]`, angles `2πi/n`
    /// (bundle radius 1). AO is the cosine-weighted 2D visibility over the outward half-plane
    /// (ambiguity 13, docs/design.md), then min–max normalised.
    pub fn build(radii: &[f32], er: f32) -> Self {
        let n = radii.len();
        let centres: Vec<Vec2> = (0..n)
            .map(|i| {
                let a = TAU * i as f32 / n as f32;
                Vec2::new(a.cos(), a.sin()) * radii[i]
            })
            .collect();
        let hit_circle = |o: Vec2, d: Vec2, c: Vec2| -> Option<f32> {
            let oc = o - c;
            let b = oc.dot(d);
            let h = b * b - (oc.dot(oc) - er * er);
            if h < 0.0 {
                return None;
            }
            let t = -b - h.sqrt();
            (t > 1e-5).then_some(t)
        };
        let mut pert = vec![0.0; TABLE_RES];
        let mut occ = vec![0.0; TABLE_RES];
        let mut centre_r = vec![0.0; TABLE_RES];
        let dirs = 96;
        let mut last = 0usize;
        for k in 0..TABLE_RES {
            let th = TAU * k as f32 / TABLE_RES as f32;
            let radial = Vec2::new(th.cos(), th.sin());
            let o = radial * 1.5;
            let best = (0..n)
                .filter_map(|i| hit_circle(o, -radial, centres[i]).map(|t| (t, i)))
                .min_by(|a, b| a.0.total_cmp(&b.0));
            // A ray through a gap reuses the neighbouring element (ambiguity 14).
            let i = best.map(|b| b.1).unwrap_or(last);
            last = i;
            let p = best.map(|(t, _)| o - radial * t).unwrap_or(centres[i] + radial * er);
            let en = (p - centres[i]).normalize_or(radial);
            pert[k] = radial.perp_dot(en).atan2(radial.dot(en));
            centre_r[k] = radii[i];
            let mut blocked = 0.0;
            for m in 0..dirs {
                let u = (m as f32 + 0.5) / dirs as f32;
                let a = (2.0 * u - 1.0).asin(); // cosine-weighted in 2D
                let d = Vec2::from_angle(a).rotate(en);
                let q = p + en * 1e-4;
                if (0..n).any(|j| j != i && hit_circle(q, d, centres[j]).is_some()) {
                    blocked += 1.0;
                }
            }
            occ[k] = blocked / dirs as f32;
        }
        let (lo, hi) = occ.iter().fold((f32::MAX, f32::MIN), |(a, b), &x| (a.min(x), b.max(x)));
        let ao = occ.iter().map(|&x| if hi - lo > 1e-6 { 1.0 - (x - lo) / (hi - lo) } else { 1.0 }).collect();
        CrossSection { pert, ao, centre_r }
    }

    /// Linear interpolation at angle `a` (radians, any value) of one of the tables.
    pub fn lookup(table: &[f32], a: f32) -> f32 {
        // Fraction of a turn, floored in registers (`rem_euclid` is an `fmodf` call).
        let turns = a * (1.0 / TAU);
        let u = (turns - super::bspline::floor_fast(turns)) * TABLE_RES as f32;
        let k = (u as usize).min(TABLE_RES - 1);
        let f = u - k as f32;
        table[k] * (1.0 - f) + table[(k + 1) % TABLE_RES] * f
    }
}

/// Radius of `n` touching circles on a ring inside a unit circle (ambiguity 19).
pub fn element_radius(n: u32) -> f32 {
    if n <= 1 {
        return 1.0;
    }
    let s = (PI / n as f32).sin();
    s / (1.0 + s)
}

/// Per-`n_p` constants of the ply loop: the element radius and the rotation by `2π/n_p`.
#[derive(Clone, Copy)]
struct PlyConsts {
    element_radius: f32,
    step: Vec2,
}

impl PlyConsts {
    fn compute(n: u32) -> Self {
        PlyConsts { element_radius: element_radius(n), step: Vec2::from_angle(TAU / n.max(1) as f32) }
    }
}

/// [`PlyConsts`] for `n_p`, tabulated once for 0–16 (a `sinf` per ply query otherwise).
fn ply_consts(n_p: u32) -> PlyConsts {
    static CONSTS: OnceLock<Vec<PlyConsts>> = OnceLock::new();
    let all = CONSTS.get_or_init(|| (0..=16u32).map(PlyConsts::compute).collect());
    all.get(n_p as usize).copied().unwrap_or_else(|| PlyConsts::compute(n_p))
}

/// The normal cross-section of a yarn at the point nearest `q`, with a ray direction `d`
/// projected into it (docs/design.md §1.3): the frame, the point `a` and direction `dv` in the
/// section, `|dv|²`, and the hit tolerance (10⁻³ of the radius).
struct Section {
    f: super::yarn::YarnFrame,
    a: Vec2,
    dv: Vec2,
    aa: f32,
    tol: f32,
}

impl Section {
    /// The section at an anchored point (`a.q` in the stretched space, `d` a stretched-space
    /// direction).
    fn at(yarn: &YarnCurve, anchor: &Anchor, d: Vec3) -> Self {
        let f = anchor.frame;
        let rel = anchor.q - f.c;
        let a = Vec2::new(rel.dot(f.ex), rel.dot(f.ey));
        let dv = Vec2::new(d.dot(f.ex), d.dot(f.ey));
        Section { a, dv, aa: dv.dot(dv), tol: 1e-3 * yarn.radius, f }
    }
}

/// `tan` of the ply and the fiber twist angles, computed once (a `tanf` per ply query otherwise).
fn twist_tans() -> (f32, f32) {
    static TANS: OnceLock<(f32, f32)> = OnceLock::new();
    *TANS.get_or_init(|| (PLY_TWIST_DEG.to_radians().tan(), FIBER_TWIST_DEG.to_radians().tan()))
}

/// Fiber cross-section for `n_f` fibers, cached (fixed seed per count: reproducible renders).
pub fn fiber_table(n_f: u32) -> &'static CrossSection {
    static TABLES: OnceLock<Vec<OnceLock<CrossSection>>> = OnceLock::new();
    let tables = TABLES.get_or_init(|| (0..=64).map(|_| OnceLock::new()).collect());
    let n = n_f.clamp(2, 64);
    tables[n as usize].get_or_init(|| {
        let er = element_radius(n);
        let mut rng = StdRng::seed_from_u64(0xF1BE_0000 + n as u64);
        let radii: Vec<f32> = (0..n).map(|_| (1.0 - er) - rng.random_range(0.0..0.8) * er).collect();
        CrossSection::build(&radii, er)
    })
}

/// Ply cross-section for `n_p` plies, cached.
pub fn ply_table(n_p: u32) -> &'static CrossSection {
    static TABLES: OnceLock<Vec<OnceLock<CrossSection>>> = OnceLock::new();
    let tables = TABLES.get_or_init(|| (0..=16).map(|_| OnceLock::new()).collect());
    let n = n_p.clamp(1, 16);
    tables[n as usize].get_or_init(|| {
        let er = element_radius(n);
        CrossSection::build(&vec![1.0 - er; n as usize], er)
    })
}

/// Ply and fiber layout of one yarn family.
#[derive(Clone, Copy, Debug)]
pub struct PlyModel {
    /// Plies per yarn.
    pub n_p: u32,
    /// Fibers per ply.
    pub n_f: u32,
}

/// Result of mapping a tube point + ray direction to the implicit plies (docs/design.md §1.3).
#[derive(Clone, Copy, Debug)]
pub struct PlyHit {
    /// Distance along the ray from the tube point to the ply surface (negative: behind).
    pub t: f32,
    /// Number of plies whose cross-section the projected line crosses (`N_i`).
    pub crossed: u32,
    /// Shading normal of the fiber at the hit.
    pub normal: Vec3,
    /// Fiber tangent at the hit.
    pub tangent: Vec3,
    /// Ply-level ambient occlusion `AO_p` ∈ \[0,1\] (1 for single-ply yarns).
    pub ao_p: f32,
    /// Fiber-level ambient occlusion `AO_f` ∈ \[0,1\].
    pub ao_f: f32,
}

impl PlyModel {
    /// Ply-circle geometry for a yarn of radius `r`: (ply radius, ring radius, twist per length).
    fn layout(&self, r: f32) -> (f32, f32, f32) {
        let rp = ply_consts(self.n_p).element_radius * r;
        let ring = r - rp;
        let kappa = if ring > 1e-6 { twist_tans().0 / ring } else { 0.0 };
        (rp, ring, kappa)
    }

    /// Ply and fiber twist rates of `yarn` (per unit arc length), rounded so that the plies advance
    /// by whole multiples of 2π/n_p and the fibers by whole turns per pattern repeat: the twist is
    /// periodic: one tile then joins its neighbours without a seam, and a
    /// tile of k repeats renders exactly like k tiles.
    pub fn twists(&self, yarn: &YarnCurve) -> (f32, f32) {
        let (rp, ring, _) = self.layout(yarn.radius);
        let (kappa, len) = self.ply_twist(yarn);
        let ply_len = len * (1.0 + (ring * kappa).powi(2)).sqrt();
        let kappa_f = if rp > 1e-6 { -whole_rate(twist_tans().1 / rp, ply_len, TAU) } else { 0.0 };
        (kappa, kappa_f)
    }

    /// Arc length along `yarn` over which its plies repeat (identical plies after `1/n_p` of a
    /// turn of the twist); the yarn's arc length per repeat for untwisted plies.
    pub fn ply_period(&self, yarn: &YarnCurve) -> f32 {
        let (kappa, len) = self.ply_twist(yarn);
        if kappa.abs() > 1e-9 {
            TAU / self.n_p as f32 / kappa.abs()
        } else {
            len
        }
    }

    /// The ply twist rate of [`PlyModel::twists`] alone, with the yarn's arc length per repeat it
    /// was rounded to.
    fn ply_twist(&self, yarn: &YarnCurve) -> (f32, f32) {
        let (_, _, kappa0) = self.layout(yarn.radius);
        let len = yarn.arc_length(yarn.repeat).max(1e-6);
        // n_p identical plies repeat after 1/n_p of a turn, so that is the period the plies need.
        let kappa = if kappa0 > 0.0 { whole_rate(kappa0, len, TAU / self.n_p as f32) } else { 0.0 };
        (kappa, len)
    }

    /// The unit directions of the ply centres in the cross-section, with their indices: ply `i`
    /// sits at `β_i = 2πi/n_p + base` (`base` = κ·arc). One sincos for ply 0, then a rotation by
    /// 2π/n_p per ply (a sincos per ply and call was 4 % of a render's profile).
    fn ply_dirs(&self, base: f32) -> impl Iterator<Item = (usize, Vec2)> {
        let step = ply_consts(self.n_p).step;
        let first = Vec2::new(base.cos(), base.sin());
        (0..self.n_p as usize).scan(first, move |dir, i| {
            if i > 0 {
                *dir = step.rotate(*dir);
            }
            Some((i, *dir))
        })
    }

    /// Does the line through `q` along `d` cross any ply of `yarn` (ply visibility `V_p`, docs/design.md §1.7)?
    pub fn blocks(&self, yarn: &YarnCurve, q: Vec3, d: Vec3) -> bool {
        self.blocks_at(yarn, &yarn.anchor(q), d)
    }

    /// [`PlyModel::blocks`] at an anchored point ([`YarnCurve::anchor`]; `d` in the world): the
    /// same answer, without searching the curve again for the point's section.
    pub fn blocks_at(&self, yarn: &YarnCurve, anchor: &Anchor, d: Vec3) -> bool {
        let (ds, _) = yarn.dir_to_round(d);
        self.crosses(yarn, anchor, ds)
    }

    /// `intersect(yarn, q, d, true).is_some()` without the hit: the same ply tests, computed the
    /// same way in the same order, ending at the first ply the line enters ahead of `q` (`t₁ ≥
    /// −tol`), without the fiber twist and the hit's frame. Every shadow ray that meets a tube
    /// asks this (the shadow rays were 35 % of a fit's CPU, this test a third of them).
    fn crosses(&self, yarn: &YarnCurve, anchor: &Anchor, d: Vec3) -> bool {
        let (rp, ring, _) = self.layout(yarn.radius);
        let (kappa, _) = self.ply_twist(yarn);
        let Section { f, a, dv, aa, tol } = Section::at(yarn, anchor, d);
        for (_, dir) in self.ply_dirs(kappa * f.arc) {
            let c = dir * ring;
            let oc = a - c;
            let cc = oc.dot(oc) - rp * rp;
            if aa < 1e-10 {
                if cc <= 0.0 {
                    return true;
                }
                continue;
            }
            let b = oc.dot(dv);
            let disc = b * b - aa * cc;
            if disc >= 0.0 && (-b + disc.sqrt()) / aa >= -tol {
                return true;
            }
        }
        false
    }

    /// Ply intersection in the yarn's normal cross-section at `q` (projected ray, docs/design.md §1.3).
    /// `entry`: the first ply surface at `t ≥ 0`; otherwise the last ply surface left at `t ≤ 0`.
    /// Returns (t, ply index, crossed count, 2D hit, ply centre, ply phase, frame, s).
    fn intersect(&self, yarn: &YarnCurve, anchor: &Anchor, d: Vec3, entry: bool) -> Option<PlyLocal> {
        let (rp, ring, _) = self.layout(yarn.radius);
        let (kappa, kappa_f) = self.twists(yarn);
        let Section { f, a, dv, aa, tol } = Section::at(yarn, anchor, d);
        let mut best: Option<(f32, usize, Vec2)> = None;
        let mut crossed = 0;
        for (i, dir) in self.ply_dirs(kappa * f.arc) {
            let c = dir * ring;
            let oc = a - c;
            let cc = oc.dot(oc) - rp * rp;
            if aa < 1e-10 {
                // Ray along the yarn axis: it "hits" the ply it starts in.
                if cc <= 0.0 {
                    crossed += 1;
                    best = Some((0.0, i, dir));
                }
                continue;
            }
            let b = oc.dot(dv);
            let disc = b * b - aa * cc;
            if disc < 0.0 {
                continue;
            }
            crossed += 1;
            let (t0, t1) = ((-b - disc.sqrt()) / aa, (-b + disc.sqrt()) / aa);
            let cand = if entry { (t1 >= -tol).then_some(t0.max(0.0)) } else { (t0 <= tol).then_some(t1.min(0.0)) };
            if let Some(t) = cand {
                let better = match best {
                    None => true,
                    Some((bt, _, _)) => (entry && t < bt) || (!entry && t > bt),
                };
                if better {
                    best = Some((t, i, dir));
                }
            }
        }
        let (t, i, dir) = best?;
        let beta = TAU * i as f32 / self.n_p as f32 + kappa * f.arc;
        Some(PlyLocal {
            t,
            crossed,
            hit: a + dv * t,
            centre: dir * ring,
            beta,
            beta_dir: dir,
            rp,
            ring,
            kappa,
            kappa_f,
            frame: f,
        })
    }

    /// Full ply/fiber mapping at a tube point: ply hit, fiber shading frame, AO values.
    pub fn map(&self, yarn: &YarnCurve, q: Vec3, d: Vec3, entry: bool) -> Option<PlyHit> {
        self.map_filtered(yarn, q, d, entry, None)
    }

    /// [`PlyModel::map`] for a camera sample whose pixel covers `footprint = (w, u)`: `w` world
    /// units on the cloth, `u` ∈ [0, 1) the sample's stratum of the fiber phase (docs/design.md
    /// §1.4, after the pixel-coverage idea of \[Khattar24\]). Where the footprint, stretched by the
    /// view's foreshortening, spans at least one fiber period of the table, the pixel's average is
    /// the angular average of the fiber table; the sample then reads the table at phase
    /// `θ_f = 2π(u + i)/n_f` (fiber `i` of the visible ply's ring) instead of the phase under the
    /// sample's exact position. Both are unbiased estimates of the pixel's mean, but the pixel's
    /// `spp` samples then cover the fiber period in strata instead of at random, and fibers below a
    /// pixel no longer show as sampling noise or moiré hatches. Below one period per footprint
    /// (fibers resolved) the mapping is [`PlyModel::map`] bit for bit.
    pub fn map_filtered(
        &self,
        yarn: &YarnCurve,
        q: Vec3,
        d: Vec3,
        entry: bool,
        footprint: Option<(f32, f32)>,
    ) -> Option<PlyHit> {
        self.map_filtered_at(yarn, &yarn.anchor(q), d, entry, footprint)
    }

    /// [`PlyModel::map_filtered`] at an anchored point ([`YarnCurve::anchor`]; `d` in the world):
    /// the same hit, without searching the curve again for the point's section.
    pub fn map_filtered_at(
        &self,
        yarn: &YarnCurve,
        anchor: &Anchor,
        d: Vec3,
        entry: bool,
        footprint: Option<(f32, f32)>,
    ) -> Option<PlyHit> {
        // Flattened yarns: the mapping runs in the stretched space where the tube is round, and
        // the frame comes back through the map (world `t`: divide by `|S d|`).
        let (d, len) = yarn.dir_to_round(d);
        let l = self.intersect(yarn, anchor, d, entry)?;
        let f = l.frame;
        let n2 = (l.hit - l.centre).normalize_or(Vec2::Y);
        let ply_t = (f.t + (f.ey * l.beta_dir.x - f.ex * l.beta_dir.y) * (l.ring * l.kappa)).normalize();
        let mut np = f.ex * n2.x + f.ey * n2.y;
        np = (np - ply_t * np.dot(ply_t)).normalize_or(f.ey);
        // Ply-level AO at the untwisted angle of the hit around the yarn centre.
        let ao_p = if self.n_p > 1 {
            CrossSection::lookup(&ply_table(self.n_p).ao, l.hit.y.atan2(l.hit.x) - l.kappa * f.arc)
        } else {
            1.0
        };
        // Fiber table at θ_f = u_p + κ_f ℓ_p (ply azimuth + fiber twist × ply arc length).
        let u_p = n2.y.atan2(n2.x) - l.beta;
        let ell_p = f.arc * (1.0 + (l.ring * l.kappa).powi(2)).sqrt();
        let kappa_f = l.kappa_f;
        let mut theta_f = u_p + kappa_f * ell_p;
        if let Some((w, u)) = footprint.filter(|f| f.0 > 0.0) {
            // θ_f changes by 1/r_p per unit length around the ply (foreshortened by the view, the
            // cosine floored at 0.2) and by κ_f along it: the footprint spans |∇θ_f|·w radians.
            let cos = d.dot(np).abs().max(0.2);
            let grad = ((1.0 / (l.rp.max(1e-6) * cos)).powi(2) + kappa_f * kappa_f).sqrt();
            let period = TAU / self.n_f.clamp(2, 64) as f32;
            if w * grad >= period {
                // Keep the fiber index under the sample (the table's fibers differ in depth) and
                // take the phase inside it from the stratum.
                theta_f = (super::bspline::floor_fast(theta_f / period) + u) * period;
            }
        }
        let fib = fiber_table(self.n_f);
        // The fibre's normal turned from the ply's, scaled by the yarn's relief (`YarnShape::relief`).
        let pert = CrossSection::lookup(&fib.pert, theta_f) * yarn.relief;
        let ao_f = CrossSection::lookup(&fib.ao, theta_f);
        let rf = CrossSection::lookup(&fib.centre_r, theta_f);
        let circ = ply_t.cross(np);
        let tangent = (ply_t + circ * (rf * l.rp * kappa_f)).normalize();
        let n0 = (np - tangent * np.dot(tangent)).normalize_or(np);
        let normal = (Quat::from_axis_angle(tangent, pert) * n0).normalize();
        if yarn.aspect != 1.0 {
            let (normal, tangent) = (yarn.normal_to_world(normal), yarn.tangent_to_world(tangent));
            return Some(PlyHit { t: l.t / len, crossed: l.crossed, normal, tangent, ao_p, ao_f });
        }
        Some(PlyHit { t: l.t, crossed: l.crossed, normal, tangent, ao_p, ao_f })
    }
}

struct PlyLocal {
    t: f32,
    crossed: u32,
    hit: Vec2,
    centre: Vec2,
    beta: f32,
    /// `(cos β, sin β)`.
    beta_dir: Vec2,
    rp: f32,
    ring: f32,
    kappa: f32,
    kappa_f: f32,
    frame: super::yarn::YarnFrame,
}

/// Rate `k` rounded so that `k·l` is a whole number of `step`s (at least one): the periodic
/// twist of [`PlyModel::twists`].
fn whole_rate(k: f32, l: f32, step: f32) -> f32 {
    (k * l / step).round().max(1.0) * step / l
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::yarn::YarnSet;
    use crate::pattern::WeavePattern;

    #[test]
    fn tables_are_normalised_and_finite() {
        for n in [20, 35, 50] {
            let t = fiber_table(n);
            assert!(t.ao.iter().all(|a| (0.0..=1.0).contains(a)));
            assert!(t.ao.iter().any(|&a| a < 0.2) && t.ao.iter().any(|&a| a > 0.8));
            assert!(t.pert.iter().all(|p| p.is_finite() && p.abs() < PI / 2.0 + 1e-3));
        }
        for n in 1..=7 {
            let t = ply_table(n);
            assert!(t.ao.iter().all(|a| a.is_finite()));
        }
    }

    #[test]
    fn plies_fit_inside_the_yarn_and_top_down_rays_hit() {
        let set = YarnSet::new(&WeavePattern::preset("plain").unwrap(), 4.0, 4.0);
        let y = &set.yarns[0];
        for n_p in 1..=7 {
            let m = PlyModel { n_p, n_f: 30 };
            let (rp, ring, _) = m.layout(4.0);
            assert!(rp + ring <= 4.0 + 1e-4);
            let mut hits = 0;
            for k in 0..100 {
                let s = k as f32 * 0.2;
                let f = y.frame(s);
                let q = f.c + f.ey * 4.0 + f.ex * ((k % 9) as f32 - 4.0) * 0.3;
                if let Some(h) = m.map(y, q, -f.ey, true) {
                    hits += 1;
                    assert!(h.t >= 0.0 && h.t < 8.0 && h.normal.is_finite() && h.tangent.is_finite());
                    assert!(h.crossed >= 1 && h.crossed <= n_p);
                    assert!((h.normal.length() - 1.0).abs() < 1e-3);
                }
            }
            assert!(hits > 50, "n_p={n_p}: only {hits} hits");
        }
    }

    /// Without fibre relief the shading normal is the ply's: the same whatever the fibres
    /// (their count sets the fibre table), while with the full relief the fibres turn it; half
    /// the relief turns it half as far.
    #[test]
    fn without_relief_the_fibres_leave_the_normal_alone() {
        use crate::geometry::yarn::YarnShape;
        let normals = |relief: f32, n_p: u32, n_f: u32| -> Vec<Vec3> {
            let shape = YarnShape { relief, ..Default::default() };
            let set = YarnSet::with_shape(&WeavePattern::preset("plain").unwrap(), 4.0, 4.0, shape);
            let y = &set.yarns[0];
            let m = PlyModel { n_p, n_f };
            (0..100)
                .filter_map(|k| {
                    let f = y.frame(k as f32 * 0.2);
                    let q = f.c + f.ey * 4.0 + f.ex * ((k % 9) as f32 - 4.0) * 0.3;
                    m.map(y, q, -f.ey, true).map(|h| h.normal)
                })
                .collect()
        };
        let worst = |a: &[Vec3], b: &[Vec3]| a.iter().zip(b).map(|(x, y)| x.angle_between(*y)).fold(0.0f32, f32::max);
        for n_p in [1, 3] {
            let (a, b) = (normals(0.0, n_p, 20), normals(0.0, n_p, 50));
            assert!(a.len() > 50 && a.len() == b.len(), "n_p={n_p}: {} and {} hits", a.len(), b.len());
            assert!(worst(&a, &b) < 1e-4, "n_p={n_p}: relief 0 still turns by {}", worst(&a, &b));
            let full = worst(&normals(1.0, n_p, 20), &a);
            let half = worst(&normals(0.5, n_p, 20), &a);
            assert!(full > 0.5, "n_p={n_p}: the fibres turn the normal by {full} rad at most");
            assert!((half - 0.5 * full).abs() < 0.05 * full, "n_p={n_p}: half relief {half} vs full {full}");
        }
    }

    /// The early-exit test of a shadow ray against the plies answers what the full intersection
    /// answers, ray for ray, on round and flattened yarns and every ply count.
    #[test]
    fn crossing_any_ply_is_the_full_intersection_found() {
        use crate::geometry::yarn::YarnShape;
        use rand::{RngExt, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let (mut yes, mut no) = (0, 0);
        for (aspect, n_p) in [(1.0f32, 1u32), (1.0, 3), (0.6, 4), (1.0, 7), (0.5, 2)] {
            let shape = YarnShape { crossing: 0.5, aspect, ..Default::default() };
            let set = YarnSet::with_shape(&WeavePattern::preset("twill22").unwrap(), 3.5, 4.0, shape);
            let m = PlyModel { n_p, n_f: 30 };
            for y in &set.yarns {
                for _ in 0..400 {
                    let s = rng.random::<f32>() * y.period();
                    let f = y.frame(s);
                    let r = y.radius * rng.random::<f32>();
                    let ang = std::f32::consts::TAU * rng.random::<f32>();
                    let q = f.c + (f.ex * ang.cos() + f.ey * ang.sin()) * r;
                    let d = Vec3::new(rng.random::<f32>() - 0.5, rng.random::<f32>() - 0.5, rng.random::<f32>() - 0.5)
                        .normalize_or(Vec3::Z);
                    // Along the yarn axis now and then (the projected-ray degenerate case).
                    let d = if rng.random::<f32>() < 0.05 { f.t } else { d };
                    let (ds, _) = y.dir_to_round(d);
                    let full = m.intersect(y, &y.anchor(q), ds, true).is_some();
                    assert_eq!(m.blocks(y, q, d), full, "aspect {aspect} n_p {n_p} s {s} d {d}");
                    if full {
                        yes += 1;
                    } else {
                        no += 1;
                    }
                }
            }
        }
        assert!(yes > 500 && no > 500, "both answers exercised: {yes} crossing, {no} not");
    }

    /// One anchor per tube point, reused for every direction asked there (as a path vertex
    /// reuses it for all its shadow rays), answers what a fresh curve search per question
    /// answers, to the bit: the ply test, the ply mapping (entry and exit), the exit distance
    /// and the tube normal, on round and flattened yarns.
    #[test]
    fn an_anchor_reused_across_directions_answers_as_a_fresh_search() {
        use crate::geometry::tile::TileGeometry;
        use crate::geometry::yarn::YarnShape;
        use rand::{RngExt, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(12);
        let (mut mapped, mut exits) = (0, 0);
        for (aspect, n_p) in [(1.0f32, 3u32), (0.5, 4)] {
            let shape = YarnShape { crossing: 0.5, aspect, ..Default::default() };
            let set = YarnSet::with_shape(&WeavePattern::preset("twill22").unwrap(), 3.5, 4.0, shape);
            let geom = TileGeometry::new(set);
            let m = PlyModel { n_p, n_f: 30 };
            for (yi, y) in geom.set.yarns.iter().enumerate() {
                for _ in 0..100 {
                    // A world point on the tube (the round tube's point mapped out of the
                    // stretched space).
                    let f = y.frame(rng.random::<f32>() * y.period());
                    let ang = std::f32::consts::TAU * rng.random::<f32>();
                    let q = f.c + (f.ex * ang.cos() + f.ey * ang.sin()) * y.radius * 0.999;
                    let p = Vec3::new(q.x, q.y, q.z * aspect);
                    let anchor = y.anchor(p);
                    assert_eq!(y.tube_normal_at(&anchor).to_array(), y.tube_normal(p).to_array());
                    for _ in 0..8 {
                        let d =
                            Vec3::new(rng.random::<f32>() - 0.5, rng.random::<f32>() - 0.5, rng.random::<f32>() - 0.5)
                                .normalize_or(Vec3::Z);
                        assert_eq!(m.blocks_at(y, &anchor, d), m.blocks(y, p, d));
                        for entry in [true, false] {
                            let (a, b) = (m.map_filtered_at(y, &anchor, d, entry, None), m.map(y, p, d, entry));
                            assert_eq!(format!("{a:?}"), format!("{b:?}"));
                            mapped += a.is_some() as usize;
                        }
                        if d.dot(y.tube_normal(p)) < 0.0 {
                            let te = geom.exit_tube_at(yi, &anchor, d);
                            assert_eq!(te.to_bits(), geom.exit_tube(yi, p, d).to_bits());
                            exits += (te > 0.0) as usize;
                        }
                    }
                }
            }
        }
        assert!(mapped > 1000 && exits > 1000, "{mapped} ply hits, {exits} exits exercised");
    }
}
