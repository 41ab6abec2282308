//! One periodic tile of yarn tubes in an `obvhs` BVH, traced with wrap-around.
//!
//! Each yarn's centre curve is tessellated into short capsules (sphere-swept segments, one per
//! control interval) that extend one cell past the tile on both ends, so that a ray inside the tile's
//! xy-cell finds every tube that reaches into it. A ray leaving the cell re-enters on the opposite
//! side: one tile of the minimum pattern stands for the whole (infinite) fabric.

use super::hair::{Hair, HairFibre};
use super::yarn::{Anchor, YarnSet, PITCH};

/// Capsules per yarn per crossed cell. Shading uses the exact spline tube, so the capsule chain only
/// has to find hits: 6 per cell keeps the chain within ~0.07 units of the tube (sagitta of the crimp).
pub const SEGMENTS_PER_CELL: usize = 6;
use glam::{Vec3, Vec3A, Vec4};
use obvhs::{aabb::Aabb, cwbvh::CwBvh, ray::Ray, Boundable, BvhBuildParams};

/// A capsule: the set of points within `r` of segment `a–b`, tagged with its yarn.
#[derive(Clone, Copy, Debug)]
pub struct Capsule {
    a: Vec3A,
    b: Vec3A,
    /// `b − a`, `|b − a|²` and `r²·|b − a|²`, precomputed: every ray that reaches the capsule's
    /// box needs them (capsule intersection was a fifth of a render's profile).
    ba: Vec3A,
    baba: f32,
    rr_baba: f32,
    r: f32,
    yarn: u32,
}

impl Boundable for Capsule {
    fn aabb(&self) -> Aabb {
        let r = Vec3A::splat(self.r);
        Aabb::new(self.a.min(self.b) - r, self.a.max(self.b) + r)
    }
}

impl Capsule {
    fn new(a: Vec3A, b: Vec3A, r: f32, yarn: u32) -> Self {
        let ba = b - a;
        let baba = ba.dot(ba);
        Capsule { a, b, ba, baba, rr_baba: r * r * baba, r, yarn }
    }

    /// Entry distance along a unit-direction ray (near root); `INFINITY` if missed or if the origin
    /// is inside (a ray leaving a tube does not "hit" it). The tracer tests capsules four at a
    /// time (`CapsuleGroup::intersect`, the same operations lane-wise); this scalar form is the
    /// reference its tests compare against.
    #[cfg(test)]
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
                return f32::INFINITY;
            }
            let t = (-qb - h.sqrt()) / qa;
            let y = baoa + t * bard;
            if y > 0.0 && y < baba {
                return if t > 0.0 { t } else { f32::INFINITY };
            }
        }
        let sphere = |c: Vec3A| {
            let oc = o - c;
            let b = d.dot(oc);
            let h = b * b - (oc.dot(oc) - self.r * self.r);
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
        sphere(self.a).min(sphere(self.b))
    }
}

/// Capsules per [`CapsuleGroup`]: one SSE register of `f32` lanes. Eight (two registers, boxes
/// twice as long along the yarn) made a render 23 % slower (docs/benchmarks.md, session 15).
const LANES: usize = 4;

/// Margin added to every side of a [`CapsuleGroup`]'s box, so that the BVH never culls a group
/// whose capsule test would report a hit.
///
/// A box exactly as wide as its capsules (`a.min(b) − r`, `a.max(b) + r`) has its faces on the
/// tube's silhouette, where the capsule test's discriminant is zero and its rounding decides hit
/// or miss, while the BVH's slab test sees a different ray: an axis-parallel direction has its
/// zero components nudged to ±1e-7 (obvhs takes ±1/`f32::EPSILON` as their inverse), so a ray
/// on a face drifts `1.2e-7·t` out of the box and is culled. Vertical rays on the yarns' edges
/// (a plain weave's `x = 5 ± 2.5`) then missed tubes that the capsule test hits, and which of
/// them did depended on the BVH's boxes (session 15, `docs/benchmarks.md`: on a 60×60 grid over
/// the open plain the scalar test misses 888 rays, the per-capsule BVH missed 954, the grouped
/// one 922). The capsule test's own error at the silhouette is `|o − a|²·ε/(2r)` (the
/// cancellation in `qc`), under 1e-4 for origins within a tile of a few hundred units and
/// r ≥ 0.1, and the drift stays under it for `t` below 8000: 1e-3 (a ten-thousandth of a cell)
/// covers both and costs nothing measurable.
const BOX_PAD: f32 = 1e-3;

/// Four consecutive capsules of one chain (a yarn or a hair), stored lane by lane (structure of
/// arrays) so that one ray is tested against all four at once with 4-wide SIMD (glam's `Vec4`,
/// SSE2 on x86-64). The BVH is built over groups: a quarter of the primitives, each box the union
/// of its four capsules' (the chain is straight to within the crimp's sagitta over four short
/// capsules, so the union is barely larger than one capsule's box).
///
/// Every lane computes exactly the scalar `Capsule::intersect`'s floating-point operations in the
/// same order (glam's 3-vector dot is `(x·x' + y·y') + z·z'`, repeated here lane-wise; IEEE
/// add, multiply, divide and square root round the same packed or scalar), and the branches
/// become lane selects, so each lane's distance is the scalar test's to the bit.
#[derive(Clone, Copy, Debug)]
struct CapsuleGroup {
    ax: Vec4,
    ay: Vec4,
    az: Vec4,
    bx: Vec4,
    by: Vec4,
    bz: Vec4,
    bax: Vec4,
    bay: Vec4,
    baz: Vec4,
    baba: Vec4,
    /// `1e-9·|b − a|²`: below it the segment is a point for the ray (the scalar test's threshold).
    flat: Vec4,
    rr_baba: Vec4,
    rr: Vec4,
    /// Index in `TileGeometry::caps` of each lane's capsule (a chain's last group repeats its
    /// last capsule in the unused lanes: a duplicate answers the same distance, so the minimum
    /// is unchanged).
    idx: [u32; LANES],
    yarn: u32,
    lo: Vec3A,
    hi: Vec3A,
}

impl Boundable for CapsuleGroup {
    fn aabb(&self) -> Aabb {
        Aabb::new(self.lo, self.hi)
    }
}

impl CapsuleGroup {
    /// The group of `caps[first..]` (up to [`LANES`] capsules of one chain, padded with the last).
    fn new(caps: &[Capsule], first: usize, count: usize) -> Self {
        let idx: [u32; LANES] = std::array::from_fn(|l| (first + l.min(count - 1)) as u32);
        let c: [&Capsule; LANES] = idx.map(|i| &caps[i as usize]);
        let lane = |f: &dyn Fn(&Capsule) -> f32| Vec4::new(f(c[0]), f(c[1]), f(c[2]), f(c[3]));
        let (mut lo, mut hi) = (Vec3A::splat(f32::INFINITY), Vec3A::splat(f32::NEG_INFINITY));
        for k in c {
            let b = k.aabb();
            lo = lo.min(b.min);
            hi = hi.max(b.max);
        }
        let (lo, hi) = (lo - Vec3A::splat(BOX_PAD), hi + Vec3A::splat(BOX_PAD));
        CapsuleGroup {
            ax: lane(&|k| k.a.x),
            ay: lane(&|k| k.a.y),
            az: lane(&|k| k.a.z),
            bx: lane(&|k| k.b.x),
            by: lane(&|k| k.b.y),
            bz: lane(&|k| k.b.z),
            bax: lane(&|k| k.ba.x),
            bay: lane(&|k| k.ba.y),
            baz: lane(&|k| k.ba.z),
            baba: lane(&|k| k.baba),
            flat: lane(&|k| 1e-9 * k.baba),
            rr_baba: lane(&|k| k.rr_baba),
            rr: lane(&|k| k.r * k.r),
            idx,
            yarn: c[0].yarn,
            lo,
            hi,
        }
    }

    /// `Capsule::intersect` of the four lanes: entry distances, `INFINITY` where missed or where
    /// the origin is inside.
    #[inline]
    fn intersect(&self, o: Vec3A, d: Vec3A) -> Vec4 {
        let inf = Vec4::splat(f32::INFINITY);
        let zero = Vec4::ZERO;
        let (dx, dy, dz) = (Vec4::splat(d.x), Vec4::splat(d.y), Vec4::splat(d.z));
        let (ox, oy, oz) = (Vec4::splat(o.x), Vec4::splat(o.y), Vec4::splat(o.z));
        // Dot products summed as glam's `Vec3A::dot`: (x·x' + y·y') + z·z'.
        let dot = |x0: Vec4, y0: Vec4, z0: Vec4, x1: Vec4, y1: Vec4, z1: Vec4| x0 * x1 + y0 * y1 + z0 * z1;
        let (oax, oay, oaz) = (ox - self.ax, oy - self.ay, oz - self.az);
        let bard = dot(self.bax, self.bay, self.baz, dx, dy, dz);
        let baoa = dot(self.bax, self.bay, self.baz, oax, oay, oaz);
        let rdoa = dot(dx, dy, dz, oax, oay, oaz);
        let oaoa = dot(oax, oay, oaz, oax, oay, oaz);
        let baba = self.baba;
        let qa = baba - bard * bard;
        let qb = baba * rdoa - baoa * bard;
        let qc = baba * oaoa - baoa * baoa - self.rr_baba;
        let h = qb * qb - qa * qc;
        let t = (-qb - h.sqrt()) / qa;
        let y = baoa + t * bard;
        let body = y.cmpgt(zero) & y.cmplt(baba);
        let t_body = Vec4::select(t.cmpgt(zero), t, inf);
        let sphere = |cx: Vec4, cy: Vec4, cz: Vec4| {
            let (ocx, ocy, ocz) = (ox - cx, oy - cy, oz - cz);
            let b = dot(dx, dy, dz, ocx, ocy, ocz);
            let h = b * b - (dot(ocx, ocy, ocz, ocx, ocy, ocz) - self.rr);
            let t = -b - h.sqrt();
            // `h < 0` misses; `t > 0` is false for the NaN of a negative `h` as well.
            Vec4::select(h.cmplt(zero) | !t.cmpgt(zero), inf, t)
        };
        let ends = sphere(self.ax, self.ay, self.az).min(sphere(self.bx, self.by, self.bz));
        let cyl = qa.cmpgt(self.flat);
        // Cylinder wall (when the segment is not a point for the ray): a miss of the infinite
        // cylinder misses the capsule; a wall hit between the end planes is the entry; otherwise
        // the nearer end sphere.
        Vec4::select(cyl & h.cmplt(zero), inf, Vec4::select(cyl & body, t_body, ends))
    }
}

/// `x mod size` in `[0, size]` like `f32::rem_euclid` (which is an `fmodf` call, 1.5 % of a
/// render's profile): the quotient is floored in registers and one correction step absorbs its
/// rounding.
#[inline]
fn wrap_coord(x: f32, size: f32) -> f32 {
    if (0.0..size).contains(&x) {
        return x;
    }
    if x.abs() >= 1e6 || x.is_nan() {
        // Far from the tile the floored quotient loses precision: take the exact remainder (NaN
        // stays NaN, as with `rem_euclid`).
        return x.rem_euclid(size);
    }
    let mut r = x - super::bspline::floor_fast(x / size) * size;
    if r >= size {
        r -= size;
    }
    if r < 0.0 {
        r += size;
    }
    r
}

/// A ray–tube hit in tile coordinates.
#[derive(Clone, Copy, Debug)]
pub struct TubeHit {
    /// Distance along the ray from the query origin (summed over wrap-arounds).
    pub t: f32,
    /// Hit point, wrapped into the tile.
    pub p: Vec3,
    /// Yarn index in [`YarnSet::yarns`] (for a hair: the yarn it grows from).
    pub yarn: usize,
    /// Set when the ray hit a flyaway fibre ([`crate::geometry::hair`]) rather than a yarn tube.
    pub hair: Option<HairHit>,
}

/// Where a ray hit a hair: its id (for [`TileGeometry::closest`]'s `skip`) and its surface frame.
#[derive(Clone, Copy, Debug)]
pub struct HairHit {
    /// Id of the hair for the `skip` argument of [`TileGeometry::closest`] (past the yarn indices).
    pub id: usize,
    /// World unit outward normal of the fibre at the hit.
    pub normal: Vec3,
    /// World unit tangent of the fibre (root to tip).
    pub tangent: Vec3,
}

/// Geometry of one periodic tile: yarn curves, capsules and their BVH.
pub struct TileGeometry {
    /// The yarn curves.
    pub set: YarnSet,
    /// The flyaway fibres (empty when the layer is off), unwrapped (see [`TileGeometry::with_hair`]).
    pub hairs: Vec<HairFibre>,
    /// The capsules in build order: each chain's capsules consecutive.
    caps: Vec<Capsule>,
    /// The chains in groups of [`LANES`] consecutive capsules, in the BVH's primitive order.
    groups: Vec<CapsuleGroup>,
    bvh: CwBvh,
    z_lo: f32,
    z_hi: f32,
}

impl TileGeometry {
    /// Tessellate the yarns and build the BVH.
    pub fn new(set: YarnSet) -> Self {
        Self::with_hair(set, &Hair::default())
    }

    /// [`TileGeometry::new`] with the flyaway fibres of `hair` ([`crate::geometry::hair`]) added to
    /// the BVH as capsule chains whose ids follow the yarns' (hair `h` is id `yarns + h`). A hair
    /// that reaches out of the tile is added once more for every tile shift that brings part of
    /// its box back over the tile, so a ray wrapped into the tile meets it on both sides of the
    /// seam. The slab is raised and lowered to the hairs' tips. Off (density 0): the BVH and
    /// the slab are exactly the yarns' (renders are unchanged bit for bit).
    pub fn with_hair(set: YarnSet, hair: &Hair) -> Self {
        let hairs = super::hair::generate(&set, hair);
        let mut caps = Vec::new();
        // Each chain's capsule range `[start, end)` in `caps`, for the SIMD groups.
        let mut chains = Vec::new();
        for (yi, y) in set.yarns.iter().enumerate() {
            let start = caps.len();
            let n = (y.period() / PITCH).round() as i64 * SEGMENTS_PER_CELL as i64;
            let ds = y.period() / n as f32;
            let margin = SEGMENTS_PER_CELL as i64;
            for k in -margin..n + margin {
                let (s0, s1) = (k as f32 * ds, (k + 1) as f32 * ds);
                caps.push(Capsule::new(y.point(s0).into(), y.point(s1).into(), y.radius, yi as u32));
            }
            chains.push((start, caps.len()));
        }
        let z = set.z_max() + 0.05;
        let (mut z_lo, mut z_hi) = (-z, z);
        let (tx, ty) = (set.tile_x, set.tile_y);
        let n_yarns = set.yarns.len();
        for (h, f) in hairs.iter().enumerate() {
            let r = hair.radius;
            let lo = f.points.iter().fold(Vec3::splat(f32::INFINITY), |m, p| m.min(*p)) - r;
            let hi = f.points.iter().fold(Vec3::splat(f32::NEG_INFINITY), |m, p| m.max(*p)) + r;
            z_lo = z_lo.min(lo.z - 0.05);
            z_hi = z_hi.max(hi.z + 0.05);
            // Shifts k·tile with [lo + k·tile, hi + k·tile] overlapping [0, tile].
            let shifts = |lo: f32, hi: f32, size: f32| (-hi / size).ceil() as i64..=((size - lo) / size).floor() as i64;
            for kx in shifts(lo.x, hi.x, tx) {
                for ky in shifts(lo.y, hi.y, ty) {
                    let off = Vec3A::new(kx as f32 * tx, ky as f32 * ty, 0.0);
                    let start = caps.len();
                    for w in f.points.windows(2) {
                        let (a, b) = (Vec3A::from(w[0]) + off, Vec3A::from(w[1]) + off);
                        caps.push(Capsule::new(a, b, r, (n_yarns + h) as u32));
                    }
                    if caps.len() > start {
                        chains.push((start, caps.len()));
                    }
                }
            }
        }
        let mut groups = Vec::new();
        for (start, end) in chains {
            for first in (start..end).step_by(LANES) {
                groups.push(CapsuleGroup::new(&caps, first, (end - first).min(LANES)));
            }
        }
        let mut t = std::time::Duration::default();
        let bvh = obvhs::cwbvh::builder::build_cwbvh(&groups, BvhBuildParams::fast_build(), &mut t);
        // Reorder once so BVH primitive ids index `groups` directly.
        let groups: Vec<CapsuleGroup> = bvh.primitive_indices.iter().map(|&i| groups[i as usize]).collect();
        TileGeometry { set, hairs, caps, groups, bvh, z_lo, z_hi }
    }

    /// The hair-layer frame of a hit on capsule `c` at stretched-space point `p`, in the world.
    fn hair_hit(&self, c: &Capsule, p: Vec3A) -> HairHit {
        // Closest point of the capsule's axis: the outward normal is from there to `p`.
        let u = ((p - c.a).dot(c.ba) / c.baba.max(1e-12)).clamp(0.0, 1.0);
        let n = (p - (c.a + c.ba * u)).normalize_or(Vec3A::Z);
        // Hairs live in the stretched space of flattened yarns: normals and tangents map back.
        let y = &self.set.yarns[self.hair_root(c.yarn as usize)];
        HairHit {
            id: c.yarn as usize,
            normal: y.normal_to_world(n.into()),
            tangent: y.tangent_to_world(Vec3::from(c.ba).normalize_or(Vec3::X)),
        }
    }

    /// The yarn a hair with id `id` grows from (`id` past the yarns: see [`TileGeometry::with_hair`]).
    fn hair_root(&self, id: usize) -> usize {
        self.hairs[id - self.set.yarns.len()].yarn
    }

    /// Number of capsules in the BVH.
    pub fn capsule_count(&self) -> usize {
        self.caps.len()
    }

    /// Top of the cloth slab (world).
    pub fn z_top(&self) -> f32 {
        if self.set.shape.aspect == 1.0 {
            self.z_hi
        } else {
            self.z_hi * self.set.shape.aspect
        }
    }

    /// Wrap a point into the tile `[0, X) × [0, Y)`.
    pub fn wrap(&self, p: Vec3) -> Vec3 {
        Vec3::new(wrap_coord(p.x, self.set.tile_x), wrap_coord(p.y, self.set.tile_y), p.z)
    }

    /// Closest tube entry along `o + t·d` (unit `d`, world), `t > 0`. `skip = (yarn, t)` ignores
    /// entries of that yarn closer than `t` (a ray just leaving that yarn). Flattened yarns
    /// ([`crate::geometry::yarn::YarnShape`]) are traced as round tubes in the stretched space;
    /// `t` and the hit point come back in the world.
    pub fn closest(&self, o: Vec3, d: Vec3, skip: Option<(usize, f32)>) -> Option<TubeHit> {
        let a = self.set.shape.aspect;
        if a == 1.0 {
            return self.closest_round(o, d, skip);
        }
        let s = Vec3::new(d.x, d.y, d.z / a);
        let len = s.length();
        let hit = self.closest_round(Vec3::new(o.x, o.y, o.z / a), s / len, skip.map(|(y, t)| (y, t * len)))?;
        Some(TubeHit { t: hit.t / len, p: Vec3::new(hit.p.x, hit.p.y, hit.p.z * a), ..hit })
    }

    /// [`TileGeometry::closest`] in the stretched space where the tubes are round.
    fn closest_round(&self, o: Vec3, d: Vec3, skip: Option<(usize, f32)>) -> Option<TubeHit> {
        let (tx, ty) = (self.set.tile_x, self.set.tile_y);
        let mut o = self.wrap(o);
        let mut travelled = 0.0f32;
        let da: Vec3A = d.into();
        // Axis-parallel rays make 0·∞ = NaN in the BVH's slab tests: nudge zero components.
        let nudge = |c: f32| if c.abs() < 1e-7 { 1e-7f32.copysign(c) } else { c };
        let d_bvh = Vec3A::new(nudge(d.x), nudge(d.y), nudge(d.z));
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
            let ray = Ray::new(o.into(), d_bvh, 0.0, t_end + 1e-4);
            // Closest entry and its capsule's index in `caps`.
            let mut best = (f32::INFINITY, 0usize);
            let oa: Vec3A = o.into();
            self.bvh.ray_traverse(ray, &mut obvhs::ray::RayHit::none(), |r, id| {
                let g = &self.groups[id];
                let mut ts = g.intersect(oa, da);
                if let Some((sy, st)) = skip {
                    if g.yarn as usize == sy {
                        ts = Vec4::select((Vec4::splat(travelled) + ts).cmplt(Vec4::splat(st)), Vec4::INFINITY, ts);
                    }
                }
                let t = ts.min_element();
                if t < r.tmax && t < best.0 {
                    // The first lane at the minimum (lanes are in chain order).
                    let lane = ts.to_array().iter().position(|&x| x == t).unwrap_or(0);
                    best = (t, g.idx[lane] as usize);
                }
                t
            });
            if best.0.is_finite() {
                let c = &self.caps[best.1];
                let p = self.wrap(o + d * best.0);
                let yarn = c.yarn as usize;
                if yarn < self.set.yarns.len() {
                    return Some(TubeHit { t: travelled + best.0, p, yarn, hair: None });
                }
                // The frame from the unwrapped point: the capsule may be a copy shifted off the tile.
                let hh = self.hair_hit(c, oa + da * best.0);
                return Some(TubeHit { t: travelled + best.0, p, yarn: self.hair_root(yarn), hair: Some(hh) });
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

    /// Distance along unit `d` from `p` (inside or on yarn `yarn`'s tube; world) to where the ray
    /// leaves the tube: Newton on `g(t) = dist(p + t d, curve) − r`, started at the far root of the
    /// local straight cylinder, with bisection as a fallback (in the stretched space of flattened
    /// yarns, the distance converted back to the world).
    pub fn exit_tube(&self, yarn: usize, p: Vec3, d: Vec3) -> f32 {
        self.exit_tube_at(yarn, &self.set.yarns[yarn].anchor(p), d)
    }

    /// [`TileGeometry::exit_tube`] from an anchored point of yarn `yarn`
    /// ([`crate::geometry::yarn::YarnCurve::anchor`]; `d` in the world): the same distance,
    /// without searching the curve again for the start's frame.
    pub fn exit_tube_at(&self, yarn: usize, anchor: &Anchor, d: Vec3) -> f32 {
        let y = &self.set.yarns[yarn];
        if y.aspect == 1.0 {
            return self.exit_round(yarn, anchor, d);
        }
        let (ds, len) = y.dir_to_round(d);
        self.exit_round(yarn, anchor, ds) / len
    }

    /// [`TileGeometry::exit_tube`] in the stretched space where the tubes are round, from the
    /// anchor's point `q` with the frame of its closest curve point.
    fn exit_round(&self, yarn: usize, anchor: &Anchor, d: Vec3) -> f32 {
        let y = &self.set.yarns[yarn];
        let r = y.radius;
        let (p, f) = (anchor.q, anchor.frame);
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
pub(crate) mod tests {
    use super::*;
    use crate::pattern::WeavePattern;

    /// The tile of preset `name` with both families' radius `r` (also the renderer's tests' tile).
    pub(crate) fn tile(name: &str, r: f32) -> TileGeometry {
        TileGeometry::new(YarnSet::new(&WeavePattern::preset(name).unwrap(), r, r))
    }

    #[test]
    fn a_capsule_group_answers_each_lanes_scalar_test_to_the_bit() {
        // Rays from all over and inside the slab, in every direction, against every group of a
        // twill with hair: each lane's distance has the scalar test's bits, padded lanes repeat
        // their capsule, and the sample exercises wall hits, end-sphere hits, misses and origins
        // inside a capsule.
        use rand::{RngExt, SeedableRng};
        let set = YarnSet::new(&WeavePattern::preset("twill22").unwrap(), 4.2, 3.6);
        let g = TileGeometry::with_hair(set, &Hair { density: 2.0, length: 6.0, radius: 0.12 });
        assert!(g.groups.len() * LANES >= g.caps.len() && g.groups.len() < g.caps.len());
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let (mut finite, mut inside, mut degenerate) = (0, 0, 0);
        for k in 0..4000 {
            let o = Vec3A::new(rng.random_range(-5.0..45.0), rng.random_range(-5.0..45.0), rng.random_range(-8.0..8.0));
            let mut d =
                Vec3A::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
            if k % 50 == 0 {
                d = Vec3A::new(0.0, 0.0, -1.0);
            } else if k % 50 == 1 {
                // Along a capsule's axis: the segment is a point for that capsule (end spheres).
                d = g.caps[k % g.caps.len()].ba;
            }
            let d = d.normalize_or(Vec3A::Z);
            for grp in &g.groups {
                let ts = grp.intersect(o, d).to_array();
                for (lane, &i) in grp.idx.iter().enumerate() {
                    let c = &g.caps[i as usize];
                    let want = c.intersect(o, d);
                    assert_eq!(ts[lane].to_bits(), want.to_bits(), "ray {k} capsule {i}: {} vs {want}", ts[lane]);
                    assert_eq!(grp.yarn, c.yarn);
                    finite += want.is_finite() as usize;
                    inside += ((o - c.a).length() < c.r) as usize;
                    degenerate += (c.baba - c.ba.dot(d) * c.ba.dot(d) <= 1e-9 * c.baba) as usize;
                }
            }
        }
        assert!(finite > 10_000 && inside > 100 && degenerate > 20, "{finite} {inside} {degenerate}");
    }

    /// What `closest` must answer, without the BVH: the scalar test of every capsule of the tile
    /// at every tile shift `(kx, ky)` in `kx_range × ky_range` (the unwrapped fabric, in the
    /// stretched space), the nearest entry as `(t, capsule index)`.
    fn brute_closest(
        g: &TileGeometry,
        o: Vec3A,
        d: Vec3A,
        kx_range: std::ops::RangeInclusive<i32>,
        ky_range: std::ops::RangeInclusive<i32>,
    ) -> Option<(f32, usize)> {
        let mut best: Option<(f32, usize)> = None;
        for kx in kx_range {
            for ky in ky_range.clone() {
                let shift = Vec3A::new(kx as f32 * g.set.tile_x, ky as f32 * g.set.tile_y, 0.0);
                for (i, c) in g.caps.iter().enumerate() {
                    let t = c.intersect(o - shift, d);
                    if t.is_finite() && best.is_none_or(|(bt, _)| t < bt) {
                        best = Some((t, i));
                    }
                }
            }
        }
        best
    }

    /// The tracer's id of capsule `i`'s chain: (yarn, hair id if a hair).
    fn chain_id(g: &TileGeometry, i: usize) -> (usize, Option<usize>) {
        let id = g.caps[i].yarn as usize;
        if id < g.set.yarns.len() {
            (id, None)
        } else {
            (g.hair_root(id), Some(id))
        }
    }

    #[test]
    fn bvh_closest_equals_brute_force_on_vertical_and_oblique_rays() {
        // Open plain and twill (r = 2.5 on pitch 10: wide gaps), bare and hairy. Vertical rays on a
        // grid of step 1/3, which puts whole columns and rows exactly on the tubes' edges
        // (x = 5 ± 2.5, …: the silhouettes, where the capsule test's rounding decides): the BVH
        // must not cull a group whose capsule test hits (a box face on the silhouette and the
        // ray's nudged zero components drifting out of it did, `BOX_PAD`), so the tracer's
        // distance has the scalar test's bits. Oblique rays, some with a zero x or y component,
        // wrap across the tile's seams: the tracer answers the unwrapped fabric's nearest entry
        // (to the wraps' rounding) on the same yarn or hair.
        let (mut graze, mut hits, mut misses, mut hair_hits, mut wraps) = (0, 0, 0, 0, 0);
        for name in ["plain", "twill22"] {
            let p = WeavePattern::preset(name).unwrap();
            for density in [0.0, 3.0] {
                let g = TileGeometry::with_hair(YarnSet::new(&p, 2.5, 2.5), &Hair { density, ..Hair::default() });
                let (tx, ty) = (g.set.tile_x, g.set.tile_y);
                let (nx, ny) = ((tx * 3.0) as usize, (ty * 3.0) as usize);
                for i in 0..nx {
                    for j in 0..ny {
                        let o = Vec3::new((i as f32 + 0.5) / 3.0, (j as f32 + 0.5) / 3.0, 40.0);
                        let got = g.closest(o, -Vec3::Z, None);
                        let want = brute_closest(&g, o.into(), -Vec3A::Z, 0..=0, 0..=0);
                        let on_edge = |c: f32| ((c - 2.5) / 5.0).fract() == 0.0;
                        graze += (on_edge(o.x) || on_edge(o.y)) as usize;
                        match (got, want) {
                            (None, None) => misses += 1,
                            (Some(h), Some((t, k))) => {
                                assert_eq!(
                                    h.t.to_bits(),
                                    t.to_bits(),
                                    "{name} {density} vertical at {o}: {} vs {t}",
                                    h.t
                                );
                                assert_eq!((h.yarn, h.hair.map(|x| x.id)), chain_id(&g, k), "{name} {density} at {o}");
                                hits += 1;
                                hair_hits += h.hair.is_some() as usize;
                            }
                            (h, w) => panic!("{name} {density} vertical at {o}: tracer {h:?}, brute force {w:?}"),
                        }
                    }
                }
                // Oblique rays from above the slab, azimuths every 25° (0°, 90°, 180°, 270° among
                // them: a zero x or y component) and three tilts, origins off any special value.
                let z0 = g.z_hi + 1.0;
                for k in 0..600 {
                    let az = (k % 15) as f32 * 25f32.to_radians();
                    let tilt = [0.4f32, 0.8, 1.2][k % 3];
                    let (s, c) = az.sin_cos();
                    let d = Vec3::new(tilt * c, tilt * s, -1.0).normalize();
                    let d =
                        Vec3::new(if c.abs() < 1e-6 { 0.0 } else { d.x }, if s.abs() < 1e-6 { 0.0 } else { d.y }, d.z);
                    let o =
                        Vec3::new((k as f32 * 0.618_034).fract() * tx, (k as f32 * 0.414_214 + 0.1).fract() * ty, z0);
                    // The ray's xy path through the slab, and the shifts whose copies can reach it.
                    let t_out = (z0 - g.z_lo) / -d.z;
                    let (x1, y1) = (o.x + d.x * t_out, o.y + d.y * t_out);
                    let span = |a: f32, b: f32, size: f32| {
                        (a.min(b) / size).floor() as i32 - 1..=(a.max(b) / size).floor() as i32 + 1
                    };
                    let want = brute_closest(&g, o.into(), d.into(), span(o.x, x1, tx), span(o.y, y1, ty));
                    match (g.closest(o, d, None), want) {
                        (None, None) => misses += 1,
                        (Some(h), Some((t, k2))) => {
                            assert!((h.t - t).abs() < 1e-3, "{name} {density} ray {k}: {} vs {t}", h.t);
                            assert_eq!((h.yarn, h.hair.map(|x| x.id)), chain_id(&g, k2), "{name} {density} ray {k}");
                            let p = o + d * t;
                            wraps += !(0.0..tx).contains(&p.x) as usize + !(0.0..ty).contains(&p.y) as usize;
                            hits += 1;
                            hair_hits += h.hair.is_some() as usize;
                        }
                        (h, w) => panic!("{name} {density} ray {k} ({o}, {d}): tracer {h:?}, brute force {w:?}"),
                    }
                }
            }
        }
        assert!(
            graze > 1000 && hits > 10_000 && misses > 2000 && hair_hits > 100 && wraps > 300,
            "{graze} {hits} {misses} {hair_hits} {wraps}"
        );
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

#[cfg(test)]
mod shape_tests {
    use super::*;
    use crate::geometry::yarn::YarnShape;
    use crate::pattern::WeavePattern;

    fn flat() -> TileGeometry {
        let shape = YarnShape { crossing: 0.5, aspect: 0.5, ..Default::default() };
        TileGeometry::new(YarnSet::with_shape(&WeavePattern::preset("plain").unwrap(), 4.0, 4.0, shape))
    }

    /// World implicit function of yarn `k`: stretched distance to the curve minus the radius.
    fn g(geom: &TileGeometry, k: usize, p: Vec3) -> f32 {
        let y = &geom.set.yarns[k];
        y.distance(y.to_round(p)).0 - y.radius
    }

    #[test]
    fn flattened_tubes_are_ellipses_with_finite_difference_normals() {
        let geom = flat();
        let y = &geom.set.yarns[0];
        // Seen from above, the flattened cloth is the round one (same crossing) squashed by the aspect.
        let round_shape = YarnShape { crossing: 0.5, aspect: 1.0, ..Default::default() };
        let round =
            TileGeometry::new(YarnSet::with_shape(&WeavePattern::preset("plain").unwrap(), 4.0, 4.0, round_shape));
        let top = geom.closest(Vec3::new(5.0, 5.0, 30.0), -Vec3::Z, None).unwrap();
        let want = 0.5 * round.closest(Vec3::new(5.0, 5.0, 30.0), -Vec3::Z, None).unwrap().p.z;
        assert!((top.p.z - want).abs() < 2e-2, "top {} vs {want}", top.p.z);
        assert!(geom.z_top() >= want);
        for k in 0..40 {
            let a = k as f32 * 0.31;
            let d = Vec3::new(a.cos() * 0.5, a.sin() * 0.5, -1.0).normalize();
            let o = Vec3::new(3.0 + k as f32 * 0.4, 2.0 + k as f32 * 0.3, 30.0);
            let Some(h) = geom.closest(o, d, None) else { continue };
            // The hit lies on the world surface (within the capsule chain's 0.07, SEGMENTS_PER_CELL)
            // and at distance t along the world ray.
            assert!(g(&geom, h.yarn, h.p).abs() < 0.1, "ray {k}: g = {}", g(&geom, h.yarn, h.p));
            let pw = o + d * h.t;
            assert!((geom.wrap(pw) - h.p).truncate().length() < 1e-2 || (pw.z - h.p.z).abs() < 1e-2);
            // The tube normal is the normalised gradient of g (central differences).
            let e = 1e-2;
            let fd = Vec3::new(
                g(&geom, h.yarn, h.p + Vec3::X * e) - g(&geom, h.yarn, h.p - Vec3::X * e),
                g(&geom, h.yarn, h.p + Vec3::Y * e) - g(&geom, h.yarn, h.p - Vec3::Y * e),
                g(&geom, h.yarn, h.p + Vec3::Z * e) - g(&geom, h.yarn, h.p - Vec3::Z * e),
            )
            .normalize();
            let n = geom.set.yarns[h.yarn].tube_normal(h.p);
            assert!(n.dot(fd) > 0.999, "ray {k}: normal {n} vs finite differences {fd}");
            // The exit point along a refracted direction is on the surface too.
            let dir = (d - n * 0.5).normalize();
            let t = geom.exit_tube(h.yarn, h.p, dir);
            assert!(g(&geom, h.yarn, h.p + dir * t).abs() < 2e-2, "ray {k}: exit off the surface");
        }
        let _ = y;
    }

    #[test]
    fn flattened_ply_frames_are_unit_and_face_out() {
        let geom = flat();
        let m = crate::geometry::ply::PlyModel { n_p: 3, n_f: 30 };
        let mut hits = 0;
        for k in 0..60 {
            let o = Vec3::new(1.0 + k as f32 * 0.3, 4.0 + (k % 7) as f32 * 0.2, 30.0);
            let Some(h) = geom.closest(o, -Vec3::Z, None) else { continue };
            let y = &geom.set.yarns[h.yarn];
            if let Some(ph) = m.map(y, h.p, -Vec3::Z, true) {
                hits += 1;
                assert!((ph.normal.length() - 1.0).abs() < 1e-3 && (ph.tangent.length() - 1.0).abs() < 1e-3);
                assert!(ph.normal.is_finite() && ph.t >= 0.0);
            }
        }
        assert!(hits > 30, "{hits}");
    }
}
