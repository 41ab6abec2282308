//! The renderer: trace paths through one periodic tile of yarns, shade them with the BYSDF.
//!
//! Two entry points: [`render`] traces and shades each sample at once (plain images); [`PathCache`]
//! records the paths of a render so they can be re-shaded for new appearance parameters — and
//! differentiated exactly — without re-tracing geometry.

pub mod camera;
pub mod integrator;
pub mod lights;
pub mod shade;

use crate::geometry::ply::PlyModel;
use crate::geometry::tile::TileGeometry;
use crate::geometry::yarn::YarnSet;
use crate::image_io::Image;
use crate::params::{Appearance, BodyTexture, ClothParams, N_APPEARANCE};
use crate::pattern::WeavePattern;
use crate::progress::{NoProgress, Progress};
use crate::scene::Scene;
use crate::shading::bysdf::ShadeParams;
use crate::shading::real::{Dual, Real};
use camera::Camera;
use integrator::{sample_rng, LightHit, PathBuf, PathVertex, Tracer};
use lights::Light;
use rayon::prelude::*;

/// Switches for the skips and the parallelism of a render.
#[derive(Clone, Debug)]
pub struct RenderOptions {
    /// Skip x→y transmission paths when no light reaches the back of the cloth.
    pub skip_unlit_transmission: bool,
    /// Build geometry for every repeat in view instead of one periodic tile (for benchmarks).
    pub whole_fabric: bool,
    /// Render only this window `(x, y, w, h)` of the image.
    pub window: Option<(u32, u32, u32, u32)>,
    /// Worker threads (`None`: rayon's default).
    pub threads: Option<usize>,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions { skip_unlit_transmission: true, whole_fabric: false, window: None, threads: None }
    }
}

/// Geometry, lights and camera built for one cloth + scene.
pub struct Prepared {
    /// Tile geometry (BVH).
    pub geom: TileGeometry,
    /// Lights.
    pub lights: Vec<Light>,
    /// Camera.
    pub camera: Camera,
    /// Plies and fibers.
    pub plies: PlyModel,
    /// Whether transmission paths are traced.
    pub transmission: bool,
    /// Spatially varying body colour of the cloth.
    pub texture: Option<BodyTexture>,
    window: (u32, u32, u32, u32),
    spp: u32,
    seed: u64,
    exposure: f32,
    /// [`Scene::backdrop`]: what a camera sample that misses the cloth sees instead of the lights.
    backdrop: Option<[f32; 3]>,
    /// Pixel footprint handed to the tracer (0 when [`Scene::footprint_filter`] is off).
    footprint: f32,
}

impl Prepared {
    /// Build the BVH and the rest for `cloth` in `scene`.
    pub fn new(cloth: &ClothParams, scene: &Scene, opts: &RenderOptions) -> Self {
        let pattern = if opts.whole_fabric {
            let reps_x = (scene.camera.tiles.ceil() as usize + 1).max(1);
            let reps_y = ((scene.camera.tiles * scene.height as f32 / scene.width as f32).ceil() as usize + 1).max(1);
            let p = &cloth.pattern;
            let rows: Vec<Vec<bool>> =
                (0..p.n_e() * reps_y).map(|i| (0..p.n_a() * reps_x).map(|j| p.get(i, j)).collect()).collect();
            WeavePattern::from_rows_unreduced(&rows).unwrap_or_else(|_| cloth.pattern.clone())
        } else {
            cloth.pattern.clone()
        };
        let set = YarnSet::with_shape(&pattern, cloth.r_e, cloth.r_a, cloth.shape);
        let geom = TileGeometry::with_hair(set, &cloth.hair);
        let (tx, ty) = (cloth.pattern.n_a() as f32 * 10.0, cloth.pattern.n_e() as f32 * 10.0);
        let camera = Camera::new(&scene.camera, scene.width, scene.height, tx, ty, geom.z_top());
        let footprint = if scene.footprint_filter { camera.pixel_footprint() } else { 0.0 };
        let lights = Light::from_rig(&scene.lights);
        let transmission = !opts.skip_unlit_transmission || lights.iter().any(|l| l.lights_back());
        let window = opts.window.unwrap_or((0, 0, scene.width, scene.height));
        Prepared {
            geom,
            lights,
            camera,
            plies: PlyModel { n_p: cloth.n_p, n_f: cloth.n_f },
            transmission,
            texture: cloth.body_texture.clone(),
            window,
            spp: scene.spp,
            seed: scene.seed,
            exposure: scene.exposure,
            backdrop: scene.backdrop,
            footprint,
        }
    }

    /// Trace one camera sample into `buf`; a sample that misses the cloth (no path vertex: the
    /// ray found no yarn, or only passed between plies) sees the scene's backdrop when it has one
    /// instead of the lights' own radiance.
    fn trace_sample(&self, tracer: &Tracer, x: u32, y: u32, s: u32, buf: &mut PathBuf) {
        let mut rng = sample_rng(self.seed, self.pixel_index(x, y), s as u64);
        let (jx, jy) = self.jitter(s, &mut rng);
        let phase = if self.footprint > 0.0 { self.fiber_phase(x, y, s) } else { 0.0 };
        tracer.trace(x as f32 + jx, y as f32 + jy, phase, &mut rng, buf);
        if let (Some(b), true) = (self.backdrop, buf.verts.is_empty()) {
            buf.background = b;
        }
    }

    fn tracer<'a>(&'a self, sampling: &'a Appearance) -> Tracer<'a> {
        Tracer {
            geom: &self.geom,
            plies: self.plies,
            lights: &self.lights,
            camera: &self.camera,
            sampling,
            transmission: self.transmission,
            white: 1.0 / self.exposure,
            footprint: self.footprint,
        }
    }

    fn pixel_index(&self, x: u32, y: u32) -> u64 {
        let (w, _) = self.camera.size();
        (y as u64) * w as u64 + x as u64
    }

    /// Stratum of the fiber phase of sample `s` of pixel `(x, y)` (docs/design.md §1.4): the
    /// pixel's samples split [0, 1) into `spp` strata, each jittered, behind one random rotation
    /// per pixel. Drawn from its own random stream, so the sample's other random numbers (and with
    /// them every render where fibers are above the pixel) stay as they were.
    fn fiber_phase(&self, x: u32, y: u32, s: u32) -> f32 {
        let mut rng = sample_rng(self.seed ^ 0xF1BE_F00D, self.pixel_index(x, y), u64::MAX);
        let base: f32 = rand::RngExt::random(&mut rng);
        let mut own = sample_rng(self.seed ^ 0xF1BE_F00D, self.pixel_index(x, y), s as u64);
        let jitter: f32 = rand::RngExt::random(&mut own);
        let u = base + (s as f32 + jitter) / self.spp.max(1) as f32;
        u - u.floor()
    }

    /// Position of sample `s` inside its pixel: stratified on a k×k grid (k² ≥ spp), jittered inside
    /// its stratum, so edges between bright gaps and dark yarns converge faster than with plain
    /// random jitter.
    fn jitter(&self, s: u32, rng: &mut rand::rngs::SmallRng) -> (f32, f32) {
        let k = (self.spp as f32).sqrt().ceil().max(1.0) as u32;
        let (sx, sy) = (s % k, (s / k) % k);
        let (u, v) = (rand::RngExt::random::<f32>(rng), rand::RngExt::random::<f32>(rng));
        ((sx as f32 + u) / k as f32, (sy as f32 + v) / k as f32)
    }

    /// Window size.
    pub fn size(&self) -> (u32, u32) {
        (self.window.2, self.window.3)
    }

    /// Trace and shade directly.
    pub fn render(&self, a: &Appearance) -> Image {
        self.render_with_progress(a, &NoProgress)
    }

    /// [`Prepared::render`], reporting each finished image row to `progress` (stage `render`, one
    /// step per row). The image is the same bit for bit: rows are independent and each sample's
    /// random numbers depend only on its pixel and index.
    pub fn render_with_progress(&self, a: &Appearance, progress: &dyn Progress) -> Image {
        let (wx, wy, w, h) = self.window;
        let sp = ShadeParams::new(a);
        let tracer = self.tracer(a);
        let mut data = vec![[0.0f32; 3]; (w * h) as usize];
        progress.begin("render", h as u64);
        data.par_chunks_mut(w as usize).enumerate().for_each(|(row, out)| {
            let mut buf = PathBuf::default();
            let y = wy + row as u32;
            for (col, px) in out.iter_mut().enumerate() {
                let x = wx + col as u32;
                let mut acc = [0.0f32; 3];
                for s in 0..self.spp {
                    self.trace_sample(&tracer, x, y, s, &mut buf);
                    let l =
                        shade::shade_path(&sp, buf.background, &buf.verts, &buf.lights, self.texture.as_ref(), None);
                    (0..3).for_each(|k| acc[k] += l[k]);
                }
                *px = acc.map(|v| v * self.exposure / self.spp as f32);
            }
            progress.advance(1);
        });
        progress.finish();
        Image::new(w, h, data)
    }

    /// Record all paths of the render (sampled with `sampling` = θ₀) for re-shading.
    pub fn record(&self, sampling: &Appearance) -> PathCache {
        let (wx, wy, w, h) = self.window;
        let tracer = self.tracer(sampling);
        let rows: Vec<RowCache> = (0..h)
            .into_par_iter()
            .map(|row| {
                let mut rc = RowCache::default();
                let mut buf = PathBuf::default();
                let y = wy + row;
                for col in 0..w {
                    let x = wx + col;
                    for s in 0..self.spp {
                        self.trace_sample(&tracer, x, y, s, &mut buf);
                        rc.push(col, &buf);
                    }
                }
                rc
            })
            .collect();
        PathCache { width: w, height: h, spp: self.spp, exposure: self.exposure, rows, texture: self.texture.clone() }
    }
}

#[derive(Default)]
struct RowCache {
    /// (column, background, first vertex, vertex count)
    samples: Vec<(u32, [f32; 3], u32, u32)>,
    verts: Vec<PathVertex>,
    lights: Vec<LightHit>,
}

impl RowCache {
    fn push(&mut self, col: u32, buf: &PathBuf) {
        let v0 = self.verts.len() as u32;
        let l0 = self.lights.len() as u32;
        for v in &buf.verts {
            let mut v = *v;
            v.lights.0 += l0;
            self.verts.push(v);
        }
        self.lights.extend_from_slice(&buf.lights);
        self.samples.push((col, buf.background, v0, buf.verts.len() as u32));
    }

    fn shade<T: Real + Send>(&self, p: &ShadeParams<T>, w: u32, scale: f32, tex: Option<&BodyTexture>) -> Vec<[T; 3]> {
        let mut out = vec![[T::c(0.0); 3]; w as usize];
        for &(col, bg, v0, nv) in &self.samples {
            let l = shade::shade_path(p, bg, &self.verts[v0 as usize..(v0 + nv) as usize], &self.lights, tex, None);
            for k in 0..3 {
                out[col as usize][k] += l[k] * scale;
            }
        }
        out
    }

    /// [`RowCache::shade`] with the 30 appearance derivatives ([`shade::shade_path_gradient`]).
    fn shade_gradient(
        &self,
        g: &shade::GradientParams,
        w: u32,
        scale: f32,
        tex: Option<&BodyTexture>,
    ) -> Vec<[Dual<N_APPEARANCE>; 3]> {
        let mut out = vec![[Dual::c(0.0); 3]; w as usize];
        for &(col, bg, v0, nv) in &self.samples {
            let l = shade::shade_path_gradient(g, bg, &self.verts[v0 as usize..(v0 + nv) as usize], &self.lights, tex);
            for k in 0..3 {
                out[col as usize][k] += l[k] * scale;
            }
        }
        out
    }
}

/// `(pixel, texel slot, rgb)`: the part of a pixel that is linear in one texel's body multiplier.
pub type TexturePart = (u32, u32, [f32; 3]);

/// The recorded paths of a render: re-shade for new appearance without re-tracing.
pub struct PathCache {
    width: u32,
    height: u32,
    spp: u32,
    exposure: f32,
    rows: Vec<RowCache>,
    texture: Option<BodyTexture>,
}

impl PathCache {
    /// Image size.
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// Per pixel (row-major), the fraction of its samples that missed the cloth (no path vertex:
    /// they see the lights or the scene's backdrop through a gap) and what those samples add to the
    /// pixel (linear RGB, exposure applied): a fit replaces the second by a backdrop it solves
    /// for, `value − added + backdrop × coverage`, without re-tracing.
    pub fn misses(&self) -> (Vec<f32>, Vec<[f32; 3]>) {
        let n = (self.width * self.height) as usize;
        let (mut cov, mut rad) = (vec![0.0f32; n], vec![[0.0f32; 3]; n]);
        let (inv, scale) = (1.0 / self.spp as f32, self.exposure / self.spp as f32);
        for (row, r) in self.rows.iter().enumerate() {
            for &(col, bg, _, _) in r.samples.iter().filter(|s| s.3 == 0) {
                let p = row * self.width as usize + col as usize;
                cov[p] += inv;
                (0..3).for_each(|k| rad[p][k] += bg[k] * scale);
            }
        }
        (cov, rad)
    }

    /// The exposure the record's shading multiplies by.
    pub fn exposure(&self) -> f32 {
        self.exposure
    }

    /// Shade this record at another exposure from now on. The shading is linear in the
    /// exposure, so this is the record a trace at `exposure` makes, up to the one place the
    /// exposure enters the trace: a light seen directly through a gap, clipped per sample to the
    /// display white `1/exposure` ([`integrator`]). Used to score an exposure trade without a
    /// re-trace (`fit::family_level`).
    pub fn set_exposure(&mut self, exposure: f32) {
        self.exposure = exposure;
    }

    /// Total recorded vertices (memory use indicator).
    pub fn vertex_count(&self) -> usize {
        self.rows.iter().map(|r| r.verts.len()).sum()
    }

    /// Re-shade with new appearance parameters.
    pub fn shade(&self, a: &Appearance) -> Image {
        let sp = ShadeParams::new(a);
        let scale = self.exposure / self.spp as f32;
        let tex = self.texture.as_ref();
        let data: Vec<[f32; 3]> =
            self.rows.par_iter().flat_map_iter(|r| r.shade(&sp, self.width, scale, tex)).collect();
        Image::new(self.width, self.height, data)
    }

    /// Re-shade with a body-colour texture and return, for every pixel, the radiance that is linear
    /// in each texel's multiplier: `(pixel, slot, rgb)` with slot `2·texel` (weft) or `2·texel + 1`
    /// (warp). ∂pixel/∂multiplier = rgb, so any image loss gets its texel gradient from these.
    pub fn shade_texture_parts(&self, a: &Appearance, tex: &BodyTexture) -> (Image, Vec<TexturePart>) {
        let sp = ShadeParams::new(a);
        let scale = self.exposure / self.spp as f32;
        let w = self.width;
        let rows: Vec<(Vec<[f32; 3]>, Vec<TexturePart>)> = self
            .rows
            .par_iter()
            .enumerate()
            .map(|(row, r)| {
                let mut out = vec![[0.0f32; 3]; w as usize];
                let mut parts = Vec::new();
                let mut acc = Vec::new();
                for &(col, bg, v0, nv) in &r.samples {
                    acc.clear();
                    let l = shade::shade_path(
                        &sp,
                        bg,
                        &r.verts[v0 as usize..(v0 + nv) as usize],
                        &r.lights,
                        Some(tex),
                        Some(&mut acc),
                    );
                    (0..3).for_each(|k| out[col as usize][k] += l[k] * scale);
                    let px = row as u32 * w + col;
                    parts.extend(acc.iter().map(|(slot, b)| (px, *slot as u32, b.map(|x| x * scale))));
                }
                (out, parts)
            })
            .collect();
        let mut data = Vec::with_capacity((w * self.height) as usize);
        let mut parts = Vec::new();
        for (d, p) in rows {
            data.extend(d);
            parts.extend(p);
        }
        (Image::new(w, self.height, data), parts)
    }

    /// Re-shade with exact derivatives: per pixel and channel the value and ∂/∂θ for all
    /// [`N_APPEARANCE`] appearance scalars.
    pub fn shade_with_derivatives(&self, a: &Appearance) -> Vec<[Dual<N_APPEARANCE>; 3]> {
        let g = shade::GradientParams::new(a);
        let scale = self.exposure / self.spp as f32;
        let tex = self.texture.as_ref();
        self.rows.par_iter().flat_map_iter(|r| r.shade_gradient(&g, self.width, scale, tex)).collect()
    }

    /// Mean squared error against `target` and its exact gradient with respect to the appearance
    /// vector (chain rule through [`PathCache::shade_with_derivatives`]).
    pub fn mse_and_gradient(&self, a: &Appearance, target: &Image) -> (f32, [f32; N_APPEARANCE]) {
        let g = shade::GradientParams::new(a);
        let scale = self.exposure / self.spp as f32;
        let n = (self.width * self.height * 3) as f32;
        let (loss, grad) = self
            .rows
            .par_iter()
            .enumerate()
            .map(|(row, r)| {
                let px = r.shade_gradient(&g, self.width, scale, self.texture.as_ref());
                let mut loss = 0.0f32;
                let mut g = [0.0f32; N_APPEARANCE];
                for (col, p) in px.iter().enumerate() {
                    let t = target.get(col as u32, row as u32);
                    for k in 0..3 {
                        let e = p[k].v - t[k];
                        loss += e * e;
                        g.iter_mut().zip(p[k].d.iter()).for_each(|(gi, di)| *gi += 2.0 * e * di);
                    }
                }
                (loss, g)
            })
            .reduce(
                || (0.0, [0.0; N_APPEARANCE]),
                |(la, mut ga), (lb, gb)| {
                    ga.iter_mut().zip(gb.iter()).for_each(|(a, b)| *a += b);
                    (la + lb, ga)
                },
            );
        (loss / n, grad.map(|g| g / n))
    }
}

/// Render `cloth` in `scene` (convenience: prepare + render, optionally on `threads` threads).
pub fn render(cloth: &ClothParams, scene: &Scene, opts: &RenderOptions) -> Image {
    render_with_progress(cloth, scene, opts, &NoProgress)
}

/// [`render`], reporting finished rows to `progress` (see [`Prepared::render_with_progress`]).
pub fn render_with_progress(
    cloth: &ClothParams,
    scene: &Scene,
    opts: &RenderOptions,
    progress: &dyn Progress,
) -> Image {
    run_in_pool(opts.threads, || Prepared::new(cloth, scene, opts).render_with_progress(&cloth.appearance, progress))
}

/// Most worker threads a pool is built with: far above any core count this CPU renderer meets,
/// low enough that an absurd request (`--threads 5000`) neither exhausts the process limit nor
/// panics; larger requests are capped to it.
pub const MAX_THREADS: usize = 256;

/// Run `f` in a rayon pool of `threads` threads (or the global pool). The count is clamped to
/// `1..=`[`MAX_THREADS`]; if the system refuses to start the pool's threads, `f` runs on the
/// global pool instead of failing (the result does not depend on the thread count).
pub fn run_in_pool<R: Send>(threads: Option<usize>, f: impl FnOnce() -> R + Send) -> R {
    match threads.map(|n| rayon::ThreadPoolBuilder::new().num_threads(n.clamp(1, MAX_THREADS)).build()) {
        Some(Ok(pool)) => pool.install(f),
        Some(Err(_)) | None => f(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicU64, Ordering};

    struct Rows(AtomicU64, AtomicU64);
    impl Progress for Rows {
        fn begin(&self, _stage: &str, total: u64) {
            self.0.store(total, Ordering::SeqCst);
        }
        fn advance(&self, n: u64) {
            self.1.fetch_add(n, Ordering::SeqCst);
        }
    }

    #[test]
    fn progress_counts_rows_and_keeps_the_image() {
        let cloth = ClothParams::preset("twill22").unwrap();
        let scene = Scene { width: 24, height: 17, spp: 2, ..Scene::default() };
        let rows = Rows(AtomicU64::new(0), AtomicU64::new(0));
        let a = render_with_progress(&cloth, &scene, &RenderOptions::default(), &rows);
        assert_eq!((rows.0.load(Ordering::SeqCst), rows.1.load(Ordering::SeqCst)), (17, 17));
        // Same bytes whatever the thread count, including an absurd one (capped, no panic).
        for threads in [Some(1), Some(100_000), None] {
            let b = render(&cloth, &scene, &RenderOptions { threads, ..Default::default() });
            assert_eq!(a, b, "{threads:?}");
        }
    }

    /// FNV-1a over the bits of an image's values.
    #[cfg(all(target_arch = "x86_64", target_os = "linux"))]
    fn image_hash(img: &Image) -> u64 {
        img.data
            .iter()
            .flatten()
            .fold(0xcbf2_9ce4_8422_2325u64, |h, v| (h ^ v.to_bits() as u64).wrapping_mul(0x100_0000_01b3))
    }

    /// The renders of the code before the shared tube anchors (`YarnCurve::anchor`: one curve
    /// search per vertex and per tube a shadow ray meets, instead of one per question), to the
    /// bit: the hashes were taken from that code (session 12) for a round-yarn twill under the
    /// default rig, and flattened yarns with flyaway fibres lit front and back (every shadow ray
    /// into a vertex's own tube, between plies, through a flattened tube, past a hair). A change
    /// of the renderer's arithmetic or random streams changes them; a pure speed-up must not.
    /// The hashes are of an x86-64 Linux build (glibc's `sinf`/`cosf`); a libm that rounds a
    /// last bit differently changes them without any change here: then take them again from
    /// commit d91f2f6 (the code before the anchors) on that platform.
    #[test]
    #[cfg(all(target_arch = "x86_64", target_os = "linux"))]
    fn the_anchored_tracer_renders_the_pre_anchor_images_to_the_bit() {
        let round = ClothParams::preset("twill22").unwrap();
        let scene = Scene { width: 24, height: 20, spp: 2, ..Scene::default() };
        let mut flat = round.clone();
        flat.shape = crate::geometry::yarn::YarnShape { crossing: 0.5, aspect: 0.5, ..Default::default() };
        flat.hair = crate::geometry::hair::Hair { density: 2.0, length: 6.0, radius: 0.12 };
        let both = Scene { lights: crate::scene::LightRig::named("both").unwrap(), ..scene.clone() };
        let opts = RenderOptions { threads: Some(1), ..Default::default() };
        let got = [image_hash(&render(&round, &scene, &opts)), image_hash(&render(&flat, &both, &opts))];
        assert_eq!(got, [17_396_025_342_954_943_802, 2_507_361_471_051_459_545]);
    }
}
