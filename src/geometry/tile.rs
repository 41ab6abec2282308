//! One periodic tile of yarn tubes, traced with wrap-around.
//!
//! Each yarn's centre curve is tessellated into short capsules (sphere-swept segments,
//! [`SEGMENTS_PER_CELL`] per crossed cell) over one period of the curve; a ray inside the tile's
//! xy-cell looks them up by position (see [`TileGeometry::closest`]) and a ray leaving the cell
//! re-enters on the opposite side: one tile of the minimum pattern stands for the whole (infinite)
//! fabric.
//!
//! Why no BVH: the yarns of a weave sit on a regular grid (weft `i` at `y = (i + ½)·PITCH`, warp
//! `j` at `x = (j + ½)·PITCH`), so the yarns a ray segment can meet follow from the segment's
//! lateral extent, and the capsules of one yarn from its extent along the yarn (they are spaced
//! uniformly in `s`). That lookup replaced an 8-wide BVH over the same capsules, whose traversal
//! was a sixth of a render's profile (docs/benchmarks.md); the hits are the same capsules.

use super::bspline::floor_fast;
use super::yarn::{Family, YarnSet, PITCH};

/// Capsules per yarn per crossed cell. Shading uses the exact spline tube, so the capsule chain only
/// has to find hits: 6 per cell keeps the chain within ~0.07 units of the tube (sagitta of the crimp).
pub const SEGMENTS_PER_CELL: usize = 6;
use glam::{Vec3, Vec3A};

/// A capsule: the set of points within `r` of segment `a–b`.
#[derive(Clone, Copy, Debug)]
struct Capsule {
    a: Vec3A,
    b: Vec3A,
    /// `b − a`, `|b − a|²` and `r²·|b − a|²`, precomputed: every ray that reaches the capsule
    /// needs them (capsule intersection was a fifth of a render's profile).
    ba: Vec3A,
    baba: f32,
    rr_baba: f32,
    rr: f32,
}

impl Capsule {
    fn new(a: Vec3A, b: Vec3A, r: f32) -> Self {
        let ba = b - a;
        let baba = ba.dot(ba);
        Capsule { a, b, ba, baba, rr_baba: r * r * baba, rr: r * r }
    }

    /// Entry distance along a unit-direction ray (near root); `INFINITY` if missed or if the origin
    /// is inside (a ray leaving a tube does not "hit" it).
    #[inline]
    fn intersect(&self, o: Vec3A, d: Vec3A) -> f32 {
        let (ba, baba) = (self.ba, self.baba);
        let oa = o - self.a;
        let bard = ba.dot(d);
        let baoa = ba.dot(oa);
        let rdoa = d.dot(oa);
        let oaoa = oa.dot(oa);
        let qa = baba - bard * bard;
        let qb = baba * rdoa - baoa * bard;
        let qc = baba * oaoa - baoa * baoa - self.rr_baba;
        if qa > 1e-9 * baba {
            let h = qb * qb - qa * qc;
            if h < 0.0 {
                // The ray misses the infinite cylinder, which contains the capsule.
                return f32::INFINITY;
            }
            let t = (-qb - h.sqrt()) / qa;
            let y = baoa + t * bard;
            if y > 0.0 && y < baba {
                return if t > 0.0 { t } else { f32::INFINITY };
            }
        }
        // The end caps. Both are tested although the sphere at b is the next capsule's sphere at a:
        // a ray whose origin is inside this capsule's cylinder returns above without testing its
        // spheres, and the neighbour's test of the shared sphere keeps the hit set identical to
        // the whole capsules of the BVH this lookup replaced (equal renders, see the module doc).
        let sphere = |oc: Vec3A| {
            let b = d.dot(oc);
            let h = b * b - (oc.dot(oc) - self.rr);
            if h < 0.0 {
                return f32::INFINITY;
            }
            let t = -b - h.sqrt();
            if t > 0.0 {
                t
            } else {
                f32::INFINITY
            }
        };
        sphere(oa).min(sphere(o - self.b))
    }
}

/// A ray–tube hit in tile coordinates.
#[derive(Clone, Copy, Debug)]
pub struct TubeHit {
    /// Distance along the ray from the query origin (summed over wrap-arounds).
    pub t: f32,
    /// Hit point, wrapped into the tile.
    pub p: Vec3,
    /// Yarn index in [`YarnSet::yarns`].
    pub yarn: usize,
}

/// One yarn's capsule chain over one period of its curve.
struct Chain {
    /// Capsule `k` spans `s ∈ [k·ds, (k+1)·ds]`; capsule `k + m·n` is capsule `k` moved by
    /// `m·period` along the yarn.
    caps: Vec<Capsule>,
    inv_ds: f32,
    period: f32,
    r: f32,
}

/// Geometry of one periodic tile: yarn curves and their capsule chains.
pub struct TileGeometry {
    /// The yarn curves.
    pub set: YarnSet,
    chains: Vec<Chain>,
    /// Index of the first warp in `set.yarns` (the wefts come first).
    n_weft: usize,
    z_lo: f32,
    z_hi: f32,
}

/// `x mod size` in `[0, size]` like `f32::rem_euclid` (which is an `fmodf` call, 1.5 % of a
/// render's profile): the quotient is floored in registers and one correction step absorbs its
/// rounding.
#[inline]
fn wrap_coord(x: f32, size: f32) -> f32 {
    if (0.0..size).contains(&x) {
        return x;
    }
    if x.is_nan() || x.abs() >= 1e6 {
        // Far from the tile the floored quotient loses precision: take the exact remainder.
        return x.rem_euclid(size);
    }
    let mut r = x - floor_fast(x / size) * size;
    if r >= size {
        r -= size;
    }
    if r < 0.0 {
        r += size;
    }
    r
}

impl TileGeometry {
    /// Tessellate the yarns into capsule chains.
    pub fn new(set: YarnSet) -> Self {
        let chains = set
            .yarns
            .iter()
            .map(|y| {
                let n = ((y.period() / PITCH).round() as usize * SEGMENTS_PER_CELL).max(1);
                let ds = y.period() / n as f32;
                let caps = (0..n)
                    .map(|k| {
                        let (s0, s1) = (k as f32 * ds, (k + 1) as f32 * ds);
                        Capsule::new(y.point(s0).into(), y.point(s1).into(), y.radius)
                    })
                    .collect();
                Chain { caps, inv_ds: 1.0 / ds, period: y.period(), r: y.radius }
            })
            .collect();
        let n_weft = set.yarns.iter().take_while(|y| y.family == Family::Weft).count();
        let z = set.z_max() + 0.05;
        TileGeometry { set, chains, n_weft, z_lo: -z, z_hi: z }
    }

    /// Number of capsules (one period of every yarn).
    pub fn capsule_count(&self) -> usize {
        self.chains.iter().map(|c| c.caps.len()).sum()
    }

    /// Top of the cloth slab.
    pub fn z_top(&self) -> f32 {
        self.z_hi
    }

    /// Wrap a point into the tile `[0, X) × [0, Y)`.
    pub fn wrap(&self, p: Vec3) -> Vec3 {
        Vec3::new(wrap_coord(p.x, self.set.tile_x), wrap_coord(p.y, self.set.tile_y), p.z)
    }

    /// Closest capsule entry of one family along `o + t·d`, `t ∈ (0, best.0)`, for a ray segment
    /// that stays inside the tile's xy-cell up to `best.0`; updates `best = (t, yarn)`.
    ///
    /// Yarn `first + i` of the family lies at lateral coordinate `(i + ½)·PITCH`; only the yarns
    /// whose tube reaches the segment's lateral extent are visited, and of each only the capsules
    /// whose extent along `s` meets the segment's.
    #[allow(clippy::too_many_arguments)]
    fn closest_family(
        &self,
        first: usize,
        count: usize,
        o: Vec3,
        d: Vec3,
        weft: bool,
        skip: Option<(usize, f32)>,
        travelled: f32,
        best: &mut (f32, usize),
    ) {
        if count == 0 {
            return;
        }
        // Lateral (across the yarns) and along-the-yarn coordinates of the ray.
        let (lo, ld, so, sd) = if weft { (o.y, d.y, o.x, d.x) } else { (o.x, d.x, o.y, d.y) };
        let r_max = self.chains[first..first + count].iter().map(|c| c.r).fold(0.0f32, f32::max);
        let l_end = lo + ld * best.0;
        let (l_min, l_max) = (lo.min(l_end), lo.max(l_end));
        let i0 = ((l_min - r_max) / PITCH - 0.5).ceil().max(0.0) as usize;
        let i1 = ((l_max + r_max) / PITCH - 0.5).floor();
        if i1 < 0.0 {
            return;
        }
        let i1 = (i1 as usize).min(count - 1);
        let (oa, da): (Vec3A, Vec3A) = (o.into(), d.into());
        for i in i0..=i1 {
            let yi = first + i;
            let ch = &self.chains[yi];
            let off = (i as f32 + 0.5) * PITCH;
            // Parameter interval inside the slab |lateral − off| ≤ r.
            let (mut ta, mut tb) = if ld.abs() > 1e-12 {
                let (t0, t1) = ((off - ch.r - lo) / ld, (off + ch.r - lo) / ld);
                (t0.min(t1), t0.max(t1))
            } else if (lo - off).abs() <= ch.r {
                (0.0, f32::INFINITY)
            } else {
                continue;
            };
            ta = ta.max(0.0);
            tb = tb.min(best.0);
            if ta > tb {
                continue;
            }
            // A point at lateral distance δ from the centre line meets capsule k only where
            // s ∈ [k·ds − √(r² − δ²), (k+1)·ds + √(r² − δ²)]: bound δ from below over the
            // interval (zero where the segment crosses the centre line).
            let (la, lb) = (lo + ld * ta - off, lo + ld * tb - off);
            let delta = if la * lb <= 0.0 { 0.0 } else { la.abs().min(lb.abs()) };
            let half = (ch.r * ch.r - delta * delta).max(0.0).sqrt();
            let (sa, sb) = (so + sd * ta, so + sd * tb);
            // k ≥ (s_min − half)/ds − 1 and k ≤ (s_max + half)/ds.
            let k0 = -floor_fast(-(sa.min(sb) - half) * ch.inv_ds) as i64 - 1;
            let k1 = floor_fast((sa.max(sb) + half) * ch.inv_ds) as i64;
            let n = ch.caps.len() as i64;
            for k in k0..=k1 {
                let j = k.rem_euclid(n);
                let shift = ((k - j) / n) as f32 * ch.period;
                let o_k = if shift == 0.0 {
                    oa
                } else if weft {
                    oa - Vec3A::new(shift, 0.0, 0.0)
                } else {
                    oa - Vec3A::new(0.0, shift, 0.0)
                };
                let t = ch.caps[j as usize].intersect(o_k, da);
                if t >= best.0 {
                    continue;
                }
                if let Some((sy, st)) = skip {
                    if sy == yi && travelled + t < st {
                        continue;
                    }
                }
                *best = (t, yi);
            }
        }
    }

    /// Closest tube entry along `o + t·d` (unit `d`), `t > 0`. `skip = (yarn, t)` ignores entries of
    /// that yarn closer than `t` (a ray just leaving that yarn).
    pub fn closest(&self, o: Vec3, d: Vec3, skip: Option<(usize, f32)>) -> Option<TubeHit> {
        let (tx, ty) = (self.set.tile_x, self.set.tile_y);
        let mut o = self.wrap(o);
        let mut travelled = 0.0f32;
        let n_warp = self.set.yarns.len() - self.n_weft;
        for _ in 0..256 {
            if (d.z >= 0.0 && o.z >= self.z_hi) || (d.z <= 0.0 && o.z <= self.z_lo) {
                return None;
            }
            let t_slab = if d.z > 0.0 {
                (self.z_hi - o.z) / d.z
            } else if d.z < 0.0 {
                (self.z_lo - o.z) / d.z
            } else {
                f32::INFINITY
            };
            let exit = |p: f32, v: f32, size: f32| {
                if v > 0.0 {
                    (size - p) / v
                } else if v < 0.0 {
                    -p / v
                } else {
                    f32::INFINITY
                }
            };
            let t_cell = exit(o.x, d.x, tx).min(exit(o.y, d.y, ty)).max(0.0);
            let t_end = t_cell.min(t_slab);
            let mut best = (t_end + 1e-4, usize::MAX);
            self.closest_family(0, self.n_weft, o, d, true, skip, travelled, &mut best);
            self.closest_family(self.n_weft, n_warp, o, d, false, skip, travelled, &mut best);
            if best.1 != usize::MAX {
                let p = self.wrap(o + d * best.0);
                return Some(TubeHit { t: travelled + best.0, p, yarn: best.1 });
            }
            if t_slab <= t_cell {
                return None;
            }
            o += d * t_cell;
            travelled += t_cell;
            let eps = 1e-4;
            if d.x > 0.0 && o.x >= tx - eps {
                o.x -= tx;
            } else if d.x < 0.0 && o.x <= eps {
                o.x += tx;
            }
            if d.y > 0.0 && o.y >= ty - eps {
                o.y -= ty;
            } else if d.y < 0.0 && o.y <= eps {
                o.y += ty;
            }
        }
        None
    }

    /// Distance along unit `d` from `p` (inside or on yarn `yarn`'s tube) to where the ray leaves
    /// the tube: Newton on `g(t) = dist(p + t d, curve) − r`, started at the far root of the local
    /// straight cylinder, with bisection as a fallback.
    pub fn exit_tube(&self, yarn: usize, p: Vec3, d: Vec3) -> f32 {
        let y = &self.set.yarns[yarn];
        let r = y.radius;
        let (_, s0) = y.distance(p);
        let f = y.frame(s0);
        // Far root of |(p + t d − c) × T| = r.
        let q = p - f.c;
        let qp = q - f.t * q.dot(f.t);
        let dp = d - f.t * d.dot(f.t);
        let a = dp.dot(dp);
        let g = |t: f32| y.distance(p + d * t).0 - r;
        let mut t = if a > 1e-8 {
            let b = qp.dot(dp);
            let c = qp.dot(qp) - r * r;
            let h = (b * b - a * c).max(0.0);
            ((-b + h.sqrt()) / a).max(0.0)
        } else {
            2.0 * r
        };
        for _ in 0..4 {
            let pt = p + d * t;
            let s = y.closest_s(pt);
            let off = pt - y.point(s);
            let gt = off.length() - r;
            if gt.abs() < 1e-4 * r {
                return t;
            }
            let n = off.normalize_or_zero();
            let slope = d.dot(n);
            if slope < 0.1 {
                break;
            }
            t = (t - gt / slope).max(0.0);
        }
        // Bisection fallback on a bracket [inside, outside].
        let (mut lo, mut hi) = (0.0f32, 0.0f32);
        let step = r / 8.0;
        let mut found = false;
        for k in 1..=48 {
            let tk = k as f32 * step;
            if g(tk) > 0.0 {
                hi = tk;
                found = true;
                break;
            }
            lo = tk;
        }
        if !found {
            return lo;
        }
        for _ in 0..20 {
            let m = 0.5 * (lo + hi);
            if g(m) > 0.0 {
                hi = m;
            } else {
                lo = m;
            }
        }
        0.5 * (lo + hi)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pattern::WeavePattern;

    fn tile(name: &str, r: f32) -> TileGeometry {
        TileGeometry::new(YarnSet::new(&WeavePattern::preset(name).unwrap(), r, r))
    }

    #[test]
    fn vertical_rays_hit_the_top_yarn_and_tiles_are_seamless() {
        let g = tile("twill22", 4.0);
        let p = WeavePattern::preset("twill22").unwrap();
        for i in 0..4 {
            for j in 0..4 {
                let (x, y) = ((j as f32 + 0.5) * PITCH, (i as f32 + 0.5) * PITCH);
                for (ox, oy) in [(0.0, 0.0), (40.0, 0.0), (-40.0, 80.0)] {
                    let h = g.closest(Vec3::new(x + ox, y + oy, 20.0), -Vec3::Z, None).unwrap();
                    let want = if p.get(i, j) { i } else { 4 + j };
                    assert_eq!(h.yarn, want, "cell ({i},{j}) offset ({ox},{oy})");
                }
            }
        }
    }

    #[test]
    fn oblique_ray_wraps_and_matches_unwrapped_geometry() {
        // The same oblique ray traced against a 1-tile and a 3×3-tile geometry hits at equal t.
        let p = WeavePattern::preset("satin5").unwrap();
        let one = TileGeometry::new(YarnSet::new(&p, 3.0, 3.0));
        let big_rows: Vec<Vec<bool>> = (0..15).map(|i| (0..15).map(|j| p.get(i, j)).collect()).collect();
        let big = TileGeometry::new(YarnSet::new(&WeavePattern::from_rows_unreduced(&big_rows).unwrap(), 3.0, 3.0));
        let mut n = 0;
        for k in 0..200 {
            let a = k as f32 * 0.7;
            let d = Vec3::new(a.cos() * 0.8, a.sin() * 0.8, -0.35).normalize();
            let o = Vec3::new(75.0 + (k % 7) as f32, 75.0 + (k % 5) as f32, 9.0);
            let h1 = one.closest(o, d, None);
            let h2 = big.closest(o, d, None);
            match (h1, h2) {
                (Some(a), Some(b)) if b.t < 60.0 => {
                    assert!((a.t - b.t).abs() < 1e-3, "ray {k}: {} vs {}", a.t, b.t);
                    n += 1;
                }
                (None, Some(b)) => assert!(b.t >= 60.0, "ray {k} missed in tile"),
                _ => {}
            }
        }
        assert!(n > 150);
    }

    #[test]
    fn exit_distance_is_on_the_tube_surface() {
        let g = tile("plain", 4.0);
        let y = &g.set.yarns[0];
        for k in 0..50 {
            let s = k as f32 * 0.37;
            let f = y.frame(s);
            let p = f.c + f.ey * (y.radius - 1e-3);
            let d = (-f.ey + f.ex * (k as f32 * 0.1).sin() * 0.5).normalize();
            let t = g.exit_tube(0, p, d);
            let (dist, _) = y.distance(p + d * t);
            assert!((dist - y.radius).abs() < 1e-2, "s={s}: {dist}");
            assert!(t > 1.0);
        }
    }
}
