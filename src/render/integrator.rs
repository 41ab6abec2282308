//! Path construction (design decision 5, docs/design.md §1.6): camera ray → x0 → y0 → x1 → y1 with
//! next-event estimation at every vertex, refraction always followed, implicit plies tested at
//! every tube crossing. Paths are recorded as [`PathVertex`]es whose weights are functions of the
//! appearance parameters only, so a recorded path can be re-shaded (and differentiated) without
//! re-tracing (design decision 6: sampling detached, weight `f(θ)/p(θ₀)`).

use super::camera::Camera;
use super::lights::{Light, LightSample};
use crate::geometry::ply::PlyModel;
use crate::geometry::tile::{TileGeometry, TubeHit};
use crate::geometry::yarn::{Anchor, Family};
use crate::params::Appearance;
use crate::shading::bysdf::VertexKind;
use crate::shading::ggx::{sample_reflection, sample_transmission};
use glam::Vec3;
use rand::rngs::SmallRng;
use rand::{RngExt, SeedableRng};

/// Maximum shading vertices per path (x0, y0, x1, y1).
pub const MAX_VERTICES: usize = 4;
/// Offset used to leave a surface.
const EPS: f32 = 1e-3;

/// A light sample that reached a vertex (direction in the vertex's local frame, `Le/pdf`).
#[derive(Clone, Copy, Debug)]
pub struct LightHit {
    /// Direction towards the light in the fiber frame (z = fiber normal).
    pub l: Vec3,
    /// `Le/pdf` with visibility applied.
    pub w: [f32; 3],
}

/// One recorded shading vertex.
#[derive(Clone, Copy, Debug)]
pub struct PathVertex {
    /// x (entry) or y (exit).
    pub kind: VertexKind,
    /// Yarn family (picks R^B / S^B).
    pub family: Family,
    /// Direction towards the previous vertex/camera in the fiber frame.
    pub v: Vec3,
    /// Ply-level AO.
    pub ao_p: f32,
    /// Fiber-level AO.
    pub ao_f: f32,
    /// Chord ‖y − x‖ (y vertices).
    pub chord: f32,
    /// Plies crossed `N_i` (y vertices).
    pub n_i: u32,
    /// Index of the first [`LightHit`] of this vertex and their count.
    pub lights: (u32, u32),
    /// Sampled refraction leaving this vertex: local direction and its pdf under θ₀.
    pub refr: Option<(Vec3, f32)>,
    /// Russian-roulette weight `1/q` applied after the refraction (1 if no roulette).
    pub rr: f32,
    /// Position in the tile as fractions (u along x, v along y) for body-colour textures.
    pub uv: [f32; 2],
    /// A flyaway fibre's vertex (`Tracer::hair_vertex`): shaded without the specular
    /// transmission lobe (see there).
    pub hair: bool,
}

/// A recorded path sample: escaped radiance plus vertices.
#[derive(Clone, Debug, Default)]
pub struct PathBuf {
    /// Radiance of a camera ray that escapes through a gap (independent of appearance).
    pub background: [f32; 3],
    /// Vertices.
    pub verts: Vec<PathVertex>,
    /// Light samples of all vertices.
    pub lights: Vec<LightHit>,
}

impl PathBuf {
    fn clear(&mut self) {
        self.background = [0.0; 3];
        self.verts.clear();
        self.lights.clear();
    }
}

/// Everything needed to trace paths for one cloth geometry.
pub struct Tracer<'a> {
    /// Tile geometry with BVH.
    pub geom: &'a TileGeometry,
    /// Ply/fiber model.
    pub plies: PlyModel,
    /// Lights.
    pub lights: &'a [Light],
    /// Camera.
    pub camera: &'a Camera,
    /// Appearance θ₀ used to sample refractions.
    pub sampling: &'a Appearance,
    /// Trace x→y transmission paths (false: skipped because nothing lights the back).
    pub transmission: bool,
    /// Display white in scene radiance (`1/exposure`): a light seen directly through a gap is
    /// clipped to it per sample (see [`Tracer::trace`]).
    pub white: f32,
    /// World size of a camera pixel on the cloth (0: point samples): fibers below it are sampled
    /// in strata of their phase at the first vertex ([`PlyModel::map_filtered`], docs/design.md §1.4).
    pub footprint: f32,
}

/// Shading frame at a vertex.
struct Frame {
    s: Vec3,
    t: Vec3,
    n: Vec3,
}

impl Frame {
    fn new(n: Vec3, t: Vec3) -> Self {
        let t = (t - n * n.dot(t)).normalize_or(super::lights::basis(n).0);
        Frame { s: t.cross(n), t, n }
    }
    fn to_local(&self, d: Vec3) -> Vec3 {
        Vec3::new(d.dot(self.s), d.dot(self.t), d.dot(self.n))
    }
    fn to_world(&self, d: Vec3) -> Vec3 {
        self.s * d.x + self.t * d.y + self.n * d.z
    }
}

/// The direction samplers of a vertex that can also reach a light (multiple importance sampling,
/// balance heuristic, against NEE): the specular reflection (x vertices) and the refraction the
/// path follows (θ₀ roughness and IOR). Without them a narrow lobe (small α^S) seen against the
/// back light's cone or the ambient dome is sampled only by NEE and shows as fireflies: PSNR
/// between two renders grew by only 2.6 dB per 4× samples (docs/forward-model.md).
#[derive(Clone, Copy)]
struct Strategies {
    /// Local direction towards the previous vertex.
    v: Vec3,
    /// Tube normal at the vertex.
    nt: Vec3,
    /// Reflection roughness (x vertices).
    refl: Option<f32>,
    /// Refraction roughness and IOR (when transmission is traced).
    refr: Option<(f32, f32)>,
    /// x vertices refract into the tube (`dir·nt < 0`), y vertices out of it (`dir·nt > 0`).
    inward: bool,
}

impl Strategies {
    /// Whether the tracer follows a refraction in world direction `lw`: into the tube at x, out
    /// of it at y.
    fn follows(&self, lw: Vec3) -> bool {
        let d = lw.dot(self.nt);
        if self.inward {
            d < 0.0
        } else {
            d > 0.0
        }
    }

    /// Summed density with which the vertex's own samplers produce local direction `l` (world
    /// `lw`); a refraction the tracer would not follow has density zero.
    fn pdf(&self, l: Vec3, lw: Vec3) -> f32 {
        let mut p = 0.0;
        if let Some(alpha) = self.refl {
            p += crate::shading::ggx::reflection_pdf(self.v, l, alpha);
        }
        if let Some((alpha, eta)) = self.refr.filter(|_| self.follows(lw)) {
            p += crate::shading::ggx::transmission_pdf(self.v, l, alpha, eta);
        }
        p
    }
}

/// The surface a path vertex lies on, for its shadow rays.
#[derive(Clone, Copy)]
enum Surface {
    /// Yarn `yarn` at a tile point, anchored to its nearest curve frame (computed once per
    /// vertex: each shadow ray into the own tube asks for the ply test and the exit there).
    Yarn { yarn: usize, anchor: Anchor },
    /// The flyaway fibre with id `id` ([`crate::geometry::tile::HairHit::id`]).
    Hair { id: usize },
}

/// Bit pattern of a vector, for exact-equality keys (`==` on floats would equate `0.0` and
/// `−0.0`, whose traces may differ in the last bit).
fn bits(v: Vec3) -> [u32; 3] {
    v.to_array().map(f32::to_bits)
}

/// Key of an exit query: yarn, anchor point, anchor centre, anchor tangent, direction (bits).
type ExitKey = (usize, [u32; 3], [u32; 3], [u32; 3], [u32; 3]);
/// Key of a closest-hit query: origin, direction, skip (bits).
type HitKey = ([u32; 3], [u32; 3], Option<(usize, u32)>);

/// The two geometric queries of a path's MIS shadow ray that the path itself asks again, kept
/// with the exact inputs they were answered for. A refraction sample at x is one of the MIS
/// strategies ([`Tracer::strategy_hits`]): its shadow ray into the own tube asks for the exit
/// distance along the refracted direction, the chord the path then needs to place y. At y the
/// refraction out of the tube is the shadow ray's direction and the next path segment's: both
/// start at `y + ε·n_t` with the own yarn skipped, so the path's next closest hit is the shadow
/// ray's first. The memo answers the second asking with the first answer when the inputs are
/// equal to the bit, so renders stay the same to the bit (a query is a pure function of them).
#[derive(Default)]
struct LegMemo {
    /// `(yarn, anchor point, anchor centre, anchor tangent, direction)` and the exit distance.
    exit: Option<(ExitKey, f32)>,
    /// `(origin, direction, skip)` and the closest tube hit.
    first: Option<(HitKey, Option<TubeHit>)>,
}

impl LegMemo {
    fn exit_key(yarn: usize, anchor: &Anchor, d: Vec3) -> ExitKey {
        (yarn, bits(anchor.q), bits(anchor.frame.c), bits(anchor.frame.t), bits(d))
    }

    fn first_key(o: Vec3, d: Vec3, skip: Option<(usize, f32)>) -> HitKey {
        (bits(o), bits(d), skip.map(|(y, t)| (y, t.to_bits())))
    }

    /// [`TileGeometry::exit_tube_at`], answered from the memo when asked before with the same
    /// inputs, and remembered otherwise.
    fn exit(&mut self, geom: &TileGeometry, yarn: usize, anchor: &Anchor, d: Vec3) -> f32 {
        recall(&mut self.exit, Self::exit_key(yarn, anchor, d), || geom.exit_tube_at(yarn, anchor, d))
    }

    /// [`TileGeometry::closest`], answered from the memo when asked before with the same inputs,
    /// and remembered otherwise.
    fn closest(&mut self, geom: &TileGeometry, o: Vec3, d: Vec3, skip: Option<(usize, f32)>) -> Option<TubeHit> {
        recall(&mut self.first, Self::first_key(o, d, skip), || geom.closest(o, d, skip))
    }
}

/// The answer kept in `slot` when its key is `key`; otherwise `answer()`, kept there under `key`.
fn recall<K: PartialEq, V: Copy>(slot: &mut Option<(K, V)>, key: K, answer: impl FnOnce() -> V) -> V {
    match slot {
        Some((k, v)) if *k == key => *v,
        _ => {
            let v = answer();
            *slot = Some((key, v));
            v
        }
    }
}

/// Deterministic per-sample random numbers.
pub fn sample_rng(seed: u64, pixel: u64, sample: u64) -> SmallRng {
    let mut h = seed ^ 0x9E37_79B9_7F4A_7C15;
    for x in [pixel, sample] {
        h = (h ^ x).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        h ^= h >> 31;
    }
    SmallRng::seed_from_u64(h)
}

impl Tracer<'_> {
    fn uv(&self, p: Vec3) -> [f32; 2] {
        let q = self.geom.wrap(p);
        [q.x / self.geom.set.tile_x, q.y / self.geom.set.tile_y]
    }

    /// Visibility along `dir` from world point `pw` on `surface`, testing the implicit plies at
    /// every tube crossing (ply visibility `V_p`, docs/design.md §1.7, ambiguity 17). From a yarn
    /// (tile point `pt`, tube normal `nt`), a direction into its own tube is blocked where it meets
    /// a ply and otherwise leaves through the far wall; from a hair, the ray leaves the fibre
    /// (a hair does not shadow itself). Hairs on the way block the ray: a fibre is opaque to
    /// shadow rays, as a ply is.
    ///
    /// With `memo`, the exit from the own tube and the first closest hit are asked through it
    /// (`LegMemo`: the path may ask them again).
    fn visible(
        &self,
        surface: Surface,
        pw: Vec3,
        nt: Vec3,
        dir: Vec3,
        max_dist: f32,
        mut memo: Option<&mut LegMemo>,
    ) -> bool {
        let mut start = pw;
        let mut travelled = 0.0;
        let mut skip = match surface {
            Surface::Yarn { yarn, .. } => Some((yarn, 1e-2)),
            Surface::Hair { id } => Some((id, f32::INFINITY)),
        };
        match surface {
            Surface::Yarn { yarn, anchor } if dir.dot(nt) < 0.0 => {
                // Towards the inside of its own yarn: blocked where the line meets a ply.
                let own = &self.geom.set.yarns[yarn];
                if self.plies.blocks_at(own, &anchor, dir) {
                    return false;
                }
                let te = match memo.as_deref_mut() {
                    Some(m) => m.exit(self.geom, yarn, &anchor, dir),
                    None => self.geom.exit_tube_at(yarn, &anchor, dir),
                };
                start = pw + dir * (te + EPS);
                travelled = te + EPS;
            }
            Surface::Hair { .. } if dir.dot(nt) < 0.0 => start += dir * EPS,
            _ => start += nt * EPS,
        }
        for leg in 0..32 {
            let hit = match memo.as_deref_mut() {
                Some(m) if leg == 0 => m.closest(self.geom, start, dir, skip),
                _ => self.geom.closest(start, dir, skip),
            };
            let Some(hit) = hit else { return true };
            if travelled + hit.t >= max_dist {
                return true;
            }
            if hit.hair.is_some() {
                return false;
            }
            let y = &self.geom.set.yarns[hit.yarn];
            // One anchor for the ply test and, when the ray passes between the plies, the exit.
            let anchor = y.anchor(hit.p);
            if self.plies.blocks_at(y, &anchor, dir) {
                return false;
            }
            let te = self.geom.exit_tube_at(hit.yarn, &anchor, dir);
            let step = hit.t + te + EPS;
            start += dir * step;
            travelled += step;
            skip = Some((hit.yarn, 1e-2));
        }
        true
    }

    /// Next-event estimation at a vertex: one sample per light, visibility applied. Samples of the
    /// cone and ambient lights are MIS-weighted against the vertex's own samplers (`st`, see
    /// [`Tracer::strategy_hits`]).
    #[allow(clippy::too_many_arguments)]
    fn sample_lights(
        &self,
        rng: &mut SmallRng,
        surface: Surface,
        pw: Vec3,
        frame: &Frame,
        st: &Strategies,
        out: &mut Vec<LightHit>,
    ) -> (u32, u32) {
        let start = out.len() as u32;
        for light in self.lights {
            let (u1, u2) = (rng.random::<f32>(), rng.random::<f32>());
            let ls = match light {
                // The environment is sampled ∝ |cos| about the shading normal on both sides (the BYSDF
                // reflects and transmits), which cancels the cosine of every lobe.
                Light::Ambient { l } => {
                    let (sign, u1) = if u1 < 0.5 { (1.0, 2.0 * u1) } else { (-1.0, 2.0 * u1 - 1.0) };
                    let r = u1.sqrt();
                    let phi = std::f32::consts::TAU * u2;
                    let z = (1.0 - u1).max(0.0).sqrt();
                    if z < 1e-6 {
                        continue;
                    }
                    let dir = frame.to_world(Vec3::new(r * phi.cos(), r * phi.sin(), sign * z)).normalize();
                    let w = std::f32::consts::TAU / z;
                    LightSample { dir, weight: l.map(|x| x * w), dist: f32::INFINITY }
                }
                _ => light.sample(pw, u1, u2),
            };
            if ls.weight.iter().all(|&w| w <= 0.0) {
                continue;
            }
            let l = frame.to_local(ls.dir);
            if l.z == 0.0 || !self.visible(surface, pw, st.nt, ls.dir, ls.dist, None) {
                continue;
            }
            let mis = match light.mis_pdf(l.z) {
                Some(p_l) => p_l / (p_l + st.pdf(l, ls.dir)),
                None => 1.0,
            };
            out.push(LightHit { l, w: ls.weight.map(|w| w * mis) });
        }
        (start, out.len() as u32 - start)
    }

    /// A direction drawn by one of the vertex's samplers (local `dir`), followed to the MIS lights
    /// it reaches, each weighted `Le/Σp` (balance heuristic over NEE and all samplers). Appends
    /// to `out` and returns how many hits were added.
    fn strategy_hits(
        &self,
        at: (Surface, Vec3),
        frame: &Frame,
        dir: Vec3,
        st: &Strategies,
        out: &mut Vec<LightHit>,
        memo: &mut LegMemo,
    ) -> u32 {
        let (surface, pw) = at;
        let dw = frame.to_world(dir);
        let p_own = st.pdf(dir, dw);
        let mut n = 0;
        let mut visible = None;
        for light in self.lights {
            let Some(p_l) = light.mis_pdf(dir.z) else { continue };
            let le = light.radiance(dw);
            if le.iter().all(|&x| x <= 0.0) || p_l + p_own <= 0.0 {
                continue;
            }
            if !*visible.get_or_insert_with(|| self.visible(surface, pw, st.nt, dw, f32::INFINITY, Some(&mut *memo))) {
                return n;
            }
            let w = 1.0 / (p_l + p_own);
            out.push(LightHit { l: dir, w: le.map(|x| x * w) });
            n += 1;
        }
        n
    }

    /// The shading vertex where a path meets a flyaway fibre (docs/forward-model.md, "Flyaway
    /// fibres"): an entry vertex x of the BYSDF in the fibre's own frame (normal out of the fibre,
    /// tangent along it), with the body colour of the yarn it grows from and no ply or fiber
    /// shadowing (a lone fibre is not shadowed by its neighbours). Its lights are sampled and its
    /// reflection is MIS-weighted as at a yarn's x; the path ends there: the fibre is thin, so the
    /// refraction into it is not followed. The light it passes on from behind is the body
    /// transmission `(1 − m_r)·S^B/π` only: the specular transmission lobe `T^S` of an x vertex is
    /// the rough refraction into a yarn's bulk, which keeps a straight-through beam straight; a
    /// fibre is a thin cylinder, whose two refractions (in and out) fan a beam across its axis
    /// (the TT lobe of Marschner et al. 2003 spreads over the azimuths), so a back light seen
    /// through a hair is dimmed, not passed on. Energy stays within the BYSDF's (≤ 1): a lobe is
    /// dropped, none added.
    #[allow(clippy::too_many_arguments)]
    fn hair_vertex(
        &self,
        rng: &mut SmallRng,
        family: Family,
        hh: crate::geometry::tile::HairHit,
        xw: Vec3,
        pt: Vec3,
        ray_d: Vec3,
        out: &mut Vec<LightHit>,
    ) -> PathVertex {
        // Facing the ray: a ray that starts inside a fibre (from a surface in contact) meets its
        // far wall, whose geometric normal points away.
        let n = if hh.normal.dot(ray_d) > 0.0 { -hh.normal } else { hh.normal };
        let frame = Frame::new(n, hh.tangent);
        let v = frame.to_local(-ray_d);
        let alpha = self.sampling.alpha_s;
        let st = Strategies { v, nt: n, refl: Some(alpha), refr: None, inward: true };
        let here = Surface::Hair { id: hh.id };
        let mut lights = self.sample_lights(rng, here, xw, &frame, &st, out);
        let (r1, r2) = (rng.random::<f32>(), rng.random::<f32>());
        if let Some((rl, _)) = sample_reflection(v, alpha, r1, r2) {
            lights.1 += self.strategy_hits((here, xw), &frame, rl, &st, out, &mut LegMemo::default());
        }
        PathVertex {
            kind: VertexKind::X,
            family,
            v,
            ao_p: 1.0,
            ao_f: 1.0,
            chord: 0.0,
            n_i: 0,
            lights,
            refr: None,
            rr: 1.0,
            uv: self.uv(pt),
            hair: true,
        }
    }

    /// Trace one camera sample through pixel position `(px, py)` into `buf`. `fiber_phase` ∈ [0, 1)
    /// is the sample's stratum of the fiber phase, used where fibers are below the pixel footprint.
    pub fn trace(&self, px: f32, py: f32, fiber_phase: f32, rng: &mut SmallRng, buf: &mut PathBuf) {
        buf.clear();
        let (o, d) = self.camera.ray(px, py);
        let mut ray_o = o;
        let mut ray_d = d;
        let mut skip: Option<(usize, f32)> = None;
        let mut depth = 0;
        let mut gaps = 0;
        // The MIS shadow rays' answers the path asks again (`LegMemo`).
        let mut memo = LegMemo::default();
        while buf.verts.len() < MAX_VERTICES && gaps < 16 {
            let Some(hit) = memo.closest(self.geom, ray_o, ray_d, skip) else {
                if depth == 0 {
                    // A light seen through a gap is clipped to the display white per sample (a
                    // sensor clips per pixel, after integration; this is a deliberate deviation):
                    // the back light's disc is ~5× white, so a gap-edge pixel was white as soon
                    // as 1 of its 16 samples saw the disc, and those pixels were the main Monte
                    // Carlo noise. Per-sample clipping gives gap edges their coverage instead.
                    // Appearance-independent, so the derivatives are unchanged.
                    for l in self.lights {
                        let r = l.radiance(ray_d);
                        (0..3).for_each(|k| buf.background[k] += r[k]);
                    }
                    buf.background = buf.background.map(|b| b.min(self.white));
                }
                return;
            };
            let yarn = &self.geom.set.yarns[hit.yarn];
            let xw = ray_o + ray_d * hit.t;
            if let Some(hh) = hit.hair {
                buf.verts.push(self.hair_vertex(rng, yarn.family, hh, xw, hit.p, ray_d, &mut buf.lights));
                return;
            }
            // Only the first vertex sees the pixel's footprint; deeper vertices sample their fiber
            // where the path lands, which is already spread over the fibers by the refraction.
            let footprint = (depth == 0).then_some((self.footprint, fiber_phase));
            // The hit's curve frame, found once for the ply hit, the tube normal, the shadow rays
            // into the own tube and the chord to the exit.
            let anchor = yarn.anchor(hit.p);
            let Some(ph) = self.plies.map_filtered_at(yarn, &anchor, ray_d, true, footprint) else {
                // Between plies: march on through this tube without shading (ambiguity 6).
                let te = self.geom.exit_tube_at(hit.yarn, &anchor, ray_d);
                ray_o = xw + ray_d * (te + EPS);
                skip = Some((hit.yarn, 1e-2));
                gaps += 1;
                continue;
            };
            depth += 1;
            let frame = Frame::new(ph.normal, ph.tangent);
            let v = frame.to_local(-ray_d);
            let nt = yarn.tube_normal_at(&anchor);
            let (alpha, eta) = (self.sampling.alpha_s, self.sampling.eta_s);
            let st =
                Strategies { v, nt, refl: Some(alpha), refr: self.transmission.then_some((alpha, eta)), inward: true };
            let here = Surface::Yarn { yarn: hit.yarn, anchor };
            let lights = self.sample_lights(rng, here, xw, &frame, &st, &mut buf.lights);
            let (u1, u2) = (rng.random::<f32>(), rng.random::<f32>());
            let (r1, r2) = (rng.random::<f32>(), rng.random::<f32>());
            let mut vx = PathVertex {
                kind: VertexKind::X,
                family: yarn.family,
                v,
                ao_p: ph.ao_p,
                ao_f: ph.ao_f,
                chord: 0.0,
                n_i: 0,
                lights,
                refr: None,
                rr: 1.0,
                uv: self.uv(hit.p),
                hair: false,
            };
            if let Some((rl, _)) = sample_reflection(v, alpha, r1, r2) {
                vx.lights.1 += self.strategy_hits((here, xw), &frame, rl, &st, &mut buf.lights, &mut memo);
            }
            if !self.transmission {
                buf.verts.push(vx);
                return;
            }
            // Refract into the yarn (always transmit), sampled with θ₀. The sample is drawn even
            // when the path ends here: it is one of the MIS strategies for the cone and ambient lights.
            let Some((tl, pdf)) = sample_transmission(v, alpha, eta, u1, u2) else {
                buf.verts.push(vx);
                return;
            };
            let tw = frame.to_world(tl);
            if !st.follows(tw) {
                buf.verts.push(vx);
                return;
            }
            vx.lights.1 += self.strategy_hits((here, xw), &frame, tl, &st, &mut buf.lights, &mut memo);
            if buf.verts.len() + 1 >= MAX_VERTICES {
                buf.verts.push(vx);
                return;
            }
            vx.refr = Some((tl, pdf));
            buf.verts.push(vx);
            // Exit point y: the far wall of the same tube along the refracted direction.
            let chord = memo.exit(self.geom, hit.yarn, &anchor, tw);
            let yt = hit.p + tw * chord;
            let yw = xw + tw * chord;
            let anchor_y = yarn.anchor(yt);
            let ny = yarn.tube_normal_at(&anchor_y);
            let Some(py) = self.plies.map_filtered_at(yarn, &anchor_y, tw, false, None) else {
                ray_o = yw + ny * EPS;
                ray_d = tw;
                skip = Some((hit.yarn, 1e-2));
                continue;
            };
            let fy = Frame::new(py.normal, py.tangent);
            let vy = fy.to_local(-tw);
            let (alpha, eta) = (self.sampling.alpha_s_y, self.sampling.eta_s_y);
            let st = Strategies { v: vy, nt: ny, refl: None, refr: Some((alpha, eta)), inward: false };
            let exit = Surface::Yarn { yarn: hit.yarn, anchor: anchor_y };
            let lights = self.sample_lights(rng, exit, yw, &fy, &st, &mut buf.lights);
            let (u1, u2) = (rng.random::<f32>(), rng.random::<f32>());
            let mut vyx = PathVertex {
                kind: VertexKind::Y,
                family: yarn.family,
                v: vy,
                ao_p: py.ao_p,
                ao_f: py.ao_f,
                chord,
                n_i: py.crossed.max(1),
                lights,
                refr: None,
                rr: 1.0,
                uv: self.uv(yt),
                hair: false,
            };
            let Some((ol, pdf)) = sample_transmission(vy, alpha, eta, u1, u2) else {
                buf.verts.push(vyx);
                return;
            };
            let ow = fy.to_world(ol);
            if !st.follows(ow) {
                buf.verts.push(vyx);
                return;
            }
            vyx.lights.1 += self.strategy_hits((exit, yw), &fy, ol, &st, &mut buf.lights, &mut memo);
            if buf.verts.len() + 1 >= MAX_VERTICES {
                buf.verts.push(vyx);
                return;
            }
            // Russian roulette past the first yarn: light that crossed a whole yarn is attenuated by
            // τ(A^B)^{N_i} (θ₀), so continue with that probability (floored) and weight 1/q.
            let q = (-self.sampling.a_b * chord * vyx.n_i as f32).exp().clamp(0.1, 1.0);
            if rng.random::<f32>() >= q {
                buf.verts.push(vyx);
                return;
            }
            vyx.refr = Some((ol, pdf));
            vyx.rr = 1.0 / q;
            buf.verts.push(vyx);
            ray_o = yw + ny * EPS;
            ray_d = ow;
            skip = Some((hit.yarn, 1e-2));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::tile::tests::tile;

    #[test]
    fn the_leg_memo_answers_only_a_query_equal_to_the_bit() {
        // Two geometries that answer the same ray differently: a memo filled on the first
        // answers an equal query with the first answer (no re-trace), and traces afresh when the
        // origin, the direction or the skip differs by a bit (−0.0 against 0.0 included).
        let (a, b) = (tile("twill22", 4.0), tile("plain", 3.0));
        let (o, d) = (Vec3::new(0.0, 7.3, 20.0), Vec3::new(0.2, 0.1, -1.0).normalize());
        let (ha, hb) = (a.closest(o, d, None).unwrap(), b.closest(o, d, None).unwrap());
        assert_ne!(ha.t.to_bits(), hb.t.to_bits());
        let mut m = LegMemo::default();
        assert_eq!(m.closest(&a, o, d, None).unwrap().t.to_bits(), ha.t.to_bits());
        assert_eq!(m.closest(&b, o, d, None).unwrap().t.to_bits(), ha.t.to_bits(), "answered from the memo");
        let o_neg = Vec3::new(-0.0, 7.3, 20.0);
        assert_eq!(m.closest(&b, o_neg, d, None).unwrap().t.to_bits(), b.closest(o_neg, d, None).unwrap().t.to_bits());
        let skip = Some((ha.yarn, 1e-2));
        assert_eq!(
            m.closest(&a, o_neg, d, skip).map(|h| h.t.to_bits()),
            a.closest(o_neg, d, skip).map(|h| h.t.to_bits())
        );
        // The exit chord likewise, keyed on the yarn, the anchor and the direction.
        let y = &a.set.yarns[0];
        let f = y.frame(3.0);
        let anchor = y.anchor(f.c + f.ey * (y.radius - 1e-3));
        let (d1, d2) = ((-f.ey + f.ex * 0.3).normalize(), (-f.ey + f.t * 0.8).normalize());
        let (e1, e2) = (a.exit_tube_at(0, &anchor, d1), a.exit_tube_at(0, &anchor, d2));
        assert_ne!(e1.to_bits(), e2.to_bits());
        assert_eq!(m.exit(&a, 0, &anchor, d1).to_bits(), e1.to_bits());
        assert_eq!(m.exit(&a, 0, &anchor, d1).to_bits(), e1.to_bits());
        assert_eq!(m.exit(&a, 0, &anchor, d2).to_bits(), e2.to_bits());
        let far = y.anchor(f.c + f.ex * (y.radius - 1e-2));
        assert_eq!(m.exit(&a, 0, &far, d2).to_bits(), a.exit_tube_at(0, &far, d2).to_bits());
    }
}
