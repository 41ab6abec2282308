//! Geometry export (docs/design.md §7): the yarn centre curves of a fitted cloth, tiled over a few pattern
//! repeats, in formats other tools read — PLY polylines, a PLY tube mesh (optionally the plies as
//! separate thinner tubes) and a Mitsuba 3 scene with B-spline curves, a stand-in material, the
//! camera and the lights. See `docs/export.md`.
//!
//! Units are the renderer's: the yarn pitch is 10, the cloth's mid-plane is z = 0 and its front faces
//! +z; weft yarns run along x, warp yarns along y (docs/design.md §0).
//!
//! Curves: each weft row of each repeat row is one continuous curve across all repeats along x (and
//! each warp column of each repeat column one curve along y), so the number of curves is
//! `n_e·repeats_y + n_a·repeats_x`. The Mitsuba curve files hold the exact uniform cubic B-spline of
//! the renderer's centre curve (the yarn height is a periodic cubic B-spline in `s`; the control
//! values are recovered from the spline's values at its knots), so the curve Mitsuba traces is the
//! renderer's curve, overhanging each end of the patch by half a control spacing.
//!
//! Yarn shape ([`YarnShape`](crate::geometry::yarn::YarnShape), fitted since session 7): the
//! centre curves use the cloth's crossing depth, and a flattened cloth (`aspect < 1`) is exported
//! as the renderer builds it, round tubes in a space whose z is stretched by `1/aspect`, mapped
//! back by `S⁻¹ = diag(1, 1, aspect)`: positions and curve heights are scaled in z, normals by
//! `diag(1, 1, 1/aspect)`, so the tube meshes hold the exact elliptical cross-sections. Mitsuba's
//! `bsplinecurve` is round, so a flattened cloth's scene uses `tubes.ply` instead of the curves.

use crate::geometry::ply::{element_radius, PLY_TWIST_DEG};
use crate::geometry::yarn::{Family, YarnCurve, YarnSet, CTRL_PER_CELL, PITCH};
use crate::params::ParamFile;
use crate::render::camera::Camera;
use crate::scene::{LightSpec, Projection};
use anyhow::{ensure, Context, Result};
use glam::Vec3;
use serde::Serialize;
use std::f32::consts::TAU;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Most repeats per axis (explicit or automatic).
pub const MAX_REPEATS: u32 = 64;
/// Automatic repeats are clamped to this per axis (a grazing perspective view sees the horizon).
pub const MAX_AUTO_REPEATS: u32 = 16;
/// Largest tube/ply mesh exported (vertices), to refuse runaway sizes with a clear message.
pub const MAX_MESH_VERTICES: usize = 20_000_000;

/// What to export.
#[derive(Clone, Debug, PartialEq)]
pub struct ExportOptions {
    /// Pattern repeats `[along x, along y]`; `None`: enough to cover the scene's view.
    pub repeats: Option<[u32; 2]>,
    /// Also write `plies.ply`: each ply as a thinner tube following its helix.
    pub plies: bool,
    /// Curve samples per pattern cell (pitch) for the polylines and meshes, [2, 256].
    pub samples_per_cell: u32,
    /// Vertices around each tube ring, [3, 64].
    pub ring: u32,
    /// Write the meshes as ASCII PLY (default: binary little-endian; `yarns.ply` is always ASCII).
    pub ascii: bool,
}

impl Default for ExportOptions {
    fn default() -> Self {
        ExportOptions { repeats: None, plies: false, samples_per_cell: 16, ring: 12, ascii: false }
    }
}

/// What was written (also saved as `export.json`).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ExportSummary {
    /// Output directory.
    pub dir: PathBuf,
    /// Files written (names inside `dir`).
    pub files: Vec<String>,
    /// Length unit: the yarn pitch is this many units.
    pub pitch: f32,
    /// Pattern repeats exported `[x, y]`.
    pub repeats: [u32; 2],
    /// Tile index of the patch's lower-left repeat: the patch covers
    /// `[origin_tile[0]·tile_size[0], (origin_tile[0] + repeats[0])·tile_size[0]]` along x, same for y.
    pub origin_tile: [i32; 2],
    /// Repeat size `[n_a·pitch, n_e·pitch]`.
    pub tile_size: [f32; 2],
    /// True when the automatic repeat count was clamped to [`MAX_AUTO_REPEATS`].
    pub clamped: bool,
    /// Weft curves (`n_e·repeats_y`).
    pub weft_curves: usize,
    /// Warp curves (`n_a·repeats_x`).
    pub warp_curves: usize,
    /// `yarns.ply` vertex count.
    pub polyline_vertices: usize,
    /// `yarns.ply` edge count.
    pub polyline_edges: usize,
    /// `tubes.ply` vertex count.
    pub tube_vertices: usize,
    /// `tubes.ply` triangle count.
    pub tube_faces: usize,
    /// `plies.ply` vertex count (0 without plies).
    pub ply_vertices: usize,
    /// `plies.ply` triangle count.
    pub ply_faces: usize,
    /// Mitsuba B-spline control points written (both curve files).
    pub control_points: usize,
}

/// The camera as Mitsuba needs it, derived from the renderer's own camera rays.
#[derive(Clone, Debug)]
struct View {
    projection: Projection,
    origin: Vec3,
    target: Vec3,
    up: Vec3,
    half_w: f32,
    fov_y_deg: f32,
    far: f32,
}

/// Height of the cloth's top in the world (the renderer's tubes live in a space stretched by
/// `1/aspect` in z).
fn world_z_max(set: &YarnSet) -> f32 {
    set.z_max() * set.shape.aspect
}

/// A point of the stretched space where the tubes are round, in the world: `S⁻¹ p`.
fn to_world(set: &YarnSet, p: Vec3) -> Vec3 {
    Vec3::new(p.x, p.y, p.z * set.shape.aspect)
}

fn camera(params: &ParamFile, set: &YarnSet) -> Camera {
    let sc = &params.scene;
    Camera::new(&sc.camera, sc.width, sc.height, set.tile_x, set.tile_y, world_z_max(set))
}

fn view_of(params: &ParamFile, set: &YarnSet) -> View {
    let sc = &params.scene;
    let cam = camera(params, set);
    let (w, h) = (sc.width as f32, sc.height as f32);
    let (o_c, f) = cam.ray(0.5 * w, 0.5 * h);
    let centre = o_c + f * (-o_c.z / f.z.min(-1e-6));
    let flat = |v: Vec3| v - f * v.dot(f);
    match sc.camera.projection {
        Projection::Orthographic => {
            let right = flat(cam.ray(w, 0.5 * h).0 - cam.ray(0.0, 0.5 * h).0);
            let upv = flat(cam.ray(0.5 * w, 0.0).0 - cam.ray(0.5 * w, h).0);
            let half_w = 0.5 * right.length();
            let half_h = 0.5 * upv.length();
            let dist = (world_z_max(set) + half_h + 1.0) / (-f.z).max(0.2);
            let origin = centre - f * dist;
            View {
                projection: Projection::Orthographic,
                origin,
                target: origin + f,
                up: upv.normalize(),
                half_w,
                fov_y_deg: 0.0,
                far: dist * 4.0 + 100.0,
            }
        }
        Projection::Perspective => {
            let (_, d_top) = cam.ray(0.5 * w, 0.0);
            let (_, d_bot) = cam.ray(0.5 * w, h);
            let fov = d_top.angle_between(d_bot).to_degrees();
            View {
                projection: Projection::Perspective,
                origin: o_c,
                target: centre,
                up: flat(d_top - d_bot).normalize(),
                half_w: 0.0,
                fov_y_deg: fov,
                far: (centre - o_c).length() * 20.0 + 1000.0,
            }
        }
    }
}

/// Repeats covering the scene's view and the tile index of the patch's lower-left repeat; the bool
/// says whether the count was clamped to [`MAX_AUTO_REPEATS`].
pub fn view_repeats(params: &ParamFile) -> ([u32; 2], [i32; 2], bool) {
    let set = YarnSet::new(&params.cloth.pattern, params.cloth.r_e, params.cloth.r_a);
    let sc = &params.scene;
    let cam = camera(params, &set);
    let (w, h) = (sc.width as f32, sc.height as f32);
    let (mut lo, mut hi) = ([f32::MAX; 2], [f32::MIN; 2]);
    let mut unbounded = false;
    let n = 8;
    for k in 0..=n {
        let t = k as f32 / n as f32;
        for (px, py) in [(t * w, 0.0), (t * w, h), (0.0, t * h), (w, t * h)] {
            let (o, d) = cam.ray(px, py);
            if d.z > -1e-3 {
                unbounded = true;
                continue;
            }
            for z in [-world_z_max(&set), world_z_max(&set)] {
                let p = o + d * ((z - o.z) / d.z);
                let q = [p.x / set.tile_x, p.y / set.tile_y];
                for a in 0..2 {
                    lo[a] = lo[a].min(q[a]);
                    hi[a] = hi[a].max(q[a]);
                }
            }
        }
    }
    let centre = [sc.camera.offset[0], sc.camera.offset[1]];
    let mut reps = [1u32; 2];
    let mut origin = [0i32; 2];
    let mut clamped = false;
    for a in 0..2 {
        let (mut l, mut u) = if lo[a] <= hi[a] { (lo[a], hi[a]) } else { (centre[a], centre[a]) };
        if unbounded || u - l > MAX_AUTO_REPEATS as f32 {
            let half = MAX_AUTO_REPEATS as f32 / 2.0;
            (l, u) = (centre[a] - half, centre[a] + half);
            clamped = true;
        }
        let i0 = (l + 1e-4).floor();
        let i1 = (u - 1e-4).ceil();
        let n = ((i1 - i0) as i64).clamp(1, MAX_AUTO_REPEATS as i64);
        reps[a] = n as u32;
        origin[a] = i0 as i32;
    }
    (reps, origin, clamped)
}

/// One exported curve: a yarn of the set, shifted by whole repeats.
#[derive(Clone, Copy, Debug)]
struct Instance {
    yarn: usize,
    /// Lateral shift (y for weft, x for warp).
    shift: f32,
    /// Curve parameter range along its length.
    s0: f32,
    s1: f32,
}

impl Instance {
    fn point(&self, y: &YarnCurve, s: f32) -> Vec3 {
        let p = y.point(s);
        match y.family {
            Family::Weft => p + Vec3::Y * self.shift,
            Family::Warp => p + Vec3::X * self.shift,
        }
    }
}

/// Control values `c` of a uniform periodic cubic B-spline from its values `v_k = (c_{k−1} + 4c_k +
/// c_{k+1})/6` at the knots (Jacobi iteration; the system is diagonally dominant, error halves per step).
fn control_values(v: &[f32]) -> Vec<f32> {
    let n = v.len();
    let v: Vec<f64> = v.iter().map(|&x| x as f64).collect();
    let mut c = v.clone();
    for _ in 0..80 {
        c = (0..n).map(|k| (6.0 * v[k] - c[(k + n - 1) % n] - c[(k + 1) % n]) / 4.0).collect();
    }
    c.into_iter().map(|x| x as f32).collect()
}

/// Mitsuba control points `(x, y, z, radius)` of one instance (exact B-spline of the centre curve).
/// Curve heights are scaled by `aspect` into the world (a linear map commutes with the B-spline);
/// the radius is the half-width.
fn control_points(y: &YarnCurve, inst: &Instance, aspect: f32) -> Result<Vec<[f32; 4]>> {
    let k = (y.period() / PITCH).round() as usize * CTRL_PER_CELL;
    let delta = y.period() / k as f32;
    let knots: Vec<f32> = (0..k).map(|i| y.height.eval((i as f32 + 0.5) * delta).0).collect();
    let c = control_values(&knots);
    let ka = (inst.s0 / delta).round() as i64;
    let kb = (inst.s1 / delta).round() as i64;
    let mut pts = Vec::with_capacity((kb - ka + 4) as usize);
    for g in ka - 2..=kb + 1 {
        let s = (g as f32 + 0.5) * delta;
        let z = c[g.rem_euclid(k as i64) as usize] * aspect;
        let p = match y.family {
            Family::Weft => Vec3::new(s, y.offset + inst.shift, z),
            Family::Warp => Vec3::new(y.offset + inst.shift, s, z),
        };
        pts.push([p.x, p.y, p.z, y.radius]);
    }
    // Self-check: the B-spline of these points is the renderer's curve.
    for seg in [0, pts.len() / 2 - 1, pts.len() - 4] {
        let q = bspline_point(&pts[seg..seg + 4], 0.37);
        let s = match y.family {
            Family::Weft => q.x,
            Family::Warp => q.y,
        };
        let p = inst.point(y, s);
        let err = (Vec3::new(p.x, p.y, p.z * aspect) - q).length();
        ensure!(err < 1e-3, "internal error: exported B-spline deviates from yarn {} by {err}", y.index);
    }
    Ok(pts)
}

/// Uniform cubic B-spline segment through 4 control points at `t ∈ [0, 1]`.
pub fn bspline_point(p: &[[f32; 4]], t: f32) -> Vec3 {
    let b = [
        (1.0 - t).powi(3) / 6.0,
        (3.0 * t.powi(3) - 6.0 * t * t + 4.0) / 6.0,
        (-3.0 * t.powi(3) + 3.0 * t * t + 3.0 * t + 1.0) / 6.0,
        t.powi(3) / 6.0,
    ];
    (0..4).map(|i| Vec3::new(p[i][0], p[i][1], p[i][2]) * b[i]).sum()
}

#[derive(Default)]
struct Mesh {
    pos: Vec<Vec3>,
    nrm: Vec<Vec3>,
    yarn: Vec<u32>,
    tris: Vec<[u32; 3]>,
}

impl Mesh {
    /// Closed tube through `rings` (each: centre, unit radial basis u, v with u×v along the tube).
    fn tube(&mut self, rings: &[(Vec3, Vec3, Vec3)], radius: f32, k: usize, yarn: u32) {
        let base = self.pos.len() as u32;
        for &(c, u, v) in rings {
            for j in 0..k {
                let a = TAU * j as f32 / k as f32;
                let n = u * a.cos() + v * a.sin();
                self.pos.push(c + n * radius);
                self.nrm.push(n);
                self.yarn.push(yarn);
            }
        }
        let idx = |i: usize, j: usize| base + (i * k + j % k) as u32;
        for i in 0..rings.len() - 1 {
            for j in 0..k {
                self.tris.push([idx(i, j), idx(i, j + 1), idx(i + 1, j + 1)]);
                self.tris.push([idx(i, j), idx(i + 1, j + 1), idx(i + 1, j)]);
            }
        }
        // End caps (fans around a centre vertex).
        let last = rings.len() - 1;
        for (i, sign) in [(0, -1.0f32), (last, 1.0)] {
            let (c, u, v) = rings[i];
            let centre = self.pos.len() as u32;
            self.pos.push(c);
            self.nrm.push(u.cross(v).normalize() * sign);
            self.yarn.push(yarn);
            for j in 0..k {
                if sign < 0.0 {
                    self.tris.push([centre, idx(i, j + 1), idx(i, j)]);
                } else {
                    self.tris.push([centre, idx(i, j), idx(i, j + 1)]);
                }
            }
        }
    }

    /// Map a mesh built in the stretched space where the tubes are round to the world: positions
    /// by `S⁻¹ = diag(1, 1, aspect)`, normals by `Sᵀ = diag(1, 1, 1/aspect)` (renormalised).
    fn unstretch(&mut self, aspect: f32) {
        if aspect == 1.0 {
            return;
        }
        self.pos.iter_mut().for_each(|p| p.z *= aspect);
        self.nrm.iter_mut().for_each(|n| *n = Vec3::new(n.x, n.y, n.z / aspect).normalize_or(*n));
    }

    fn verts_per_tube(samples: usize, k: usize) -> usize {
        samples * k + 2
    }
}

fn ply_header(out: &mut Vec<u8>, ascii: bool, comments: &[String]) {
    let fmt = if ascii { "ascii" } else { "binary_little_endian" };
    out.extend_from_slice(format!("ply\nformat {fmt} 1.0\n").as_bytes());
    for c in comments {
        out.extend_from_slice(format!("comment {c}\n").as_bytes());
    }
}

fn write_mesh(path: &Path, mesh: &Mesh, ascii: bool, comments: &[String]) -> Result<()> {
    let mut out = Vec::new();
    ply_header(&mut out, ascii, comments);
    let head = format!(
        "element vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\n\
         property float ny\nproperty float nz\nproperty int yarn\nelement face {}\n\
         property list uchar int vertex_indices\nend_header\n",
        mesh.pos.len(),
        mesh.tris.len()
    );
    out.extend_from_slice(head.as_bytes());
    if ascii {
        let mut s = String::new();
        for ((p, n), y) in mesh.pos.iter().zip(&mesh.nrm).zip(&mesh.yarn) {
            let _ = writeln!(s, "{} {} {} {} {} {} {y}", p.x, p.y, p.z, n.x, n.y, n.z);
        }
        for t in &mesh.tris {
            let _ = writeln!(s, "3 {} {} {}", t[0], t[1], t[2]);
        }
        out.extend_from_slice(s.as_bytes());
    } else {
        out.reserve(mesh.pos.len() * 28 + mesh.tris.len() * 13);
        for ((p, n), y) in mesh.pos.iter().zip(&mesh.nrm).zip(&mesh.yarn) {
            for v in [p.x, p.y, p.z, n.x, n.y, n.z] {
                out.extend_from_slice(&v.to_le_bytes());
            }
            out.extend_from_slice(&(*y as i32).to_le_bytes());
        }
        for t in &mesh.tris {
            out.push(3);
            for &i in t {
                out.extend_from_slice(&(i as i32).to_le_bytes());
            }
        }
    }
    crate::io::write_atomic(path, &out).with_context(|| format!("writing {}", path.display()))
}

fn fmt_rgb(c: [f32; 3], scale: f32) -> String {
    format!("{}, {}, {}", c[0] * scale, c[1] * scale, c[2] * scale)
}

fn fmt_v(v: Vec3) -> String {
    format!("{}, {}, {}", v.x, v.y, v.z)
}

/// Export `params` into `dir` (see the module docs); every file is written atomically.
pub fn export(params: &ParamFile, dir: &Path, opts: &ExportOptions) -> Result<ExportSummary> {
    params.validate().context("invalid parameter file")?;
    ensure!(
        (2..=256).contains(&opts.samples_per_cell),
        "samples per cell must be in 2..=256, got {}",
        opts.samples_per_cell
    );
    ensure!((3..=64).contains(&opts.ring), "ring vertices must be in 3..=64, got {}", opts.ring);
    let cloth = &params.cloth;
    let set = YarnSet::with_shape(&cloth.pattern, cloth.r_e, cloth.r_a, cloth.shape);
    let (ne, na) = (cloth.pattern.n_e(), cloth.pattern.n_a());
    let (repeats, origin, clamped) = match opts.repeats {
        Some(r) => {
            ensure!(
                r.iter().all(|&n| (1..=MAX_REPEATS).contains(&n)),
                "repeats must be in 1..={MAX_REPEATS} per axis, got {}x{}",
                r[0],
                r[1]
            );
            let c = params.scene.camera.offset;
            let o = [(c[0] - r[0] as f32 / 2.0 + 0.5).floor() as i32, (c[1] - r[1] as f32 / 2.0 + 0.5).floor() as i32];
            (r, o, false)
        }
        None => view_repeats(params),
    };
    let (tx, ty) = (set.tile_x, set.tile_y);
    let k_s = opts.samples_per_cell as usize;
    let ring = opts.ring as usize;

    // Curve instances: weft rows per repeat row, then warp columns per repeat column.
    let mut instances = Vec::new();
    for ry in 0..repeats[1] as i32 {
        for i in 0..ne {
            let x0 = origin[0] as f32 * tx;
            let shift = (origin[1] + ry) as f32 * ty;
            instances.push(Instance { yarn: i, shift, s0: x0, s1: x0 + repeats[0] as f32 * tx });
        }
    }
    let weft_curves = instances.len();
    for rx in 0..repeats[0] as i32 {
        for j in 0..na {
            let y0 = origin[1] as f32 * ty;
            let shift = (origin[0] + rx) as f32 * tx;
            instances.push(Instance { yarn: ne + j, shift, s0: y0, s1: y0 + repeats[1] as f32 * ty });
        }
    }
    let warp_curves = instances.len() - weft_curves;
    let samples_of = |inst: &Instance| ((inst.s1 - inst.s0) / PITCH).round() as usize * k_s + 1;

    // Size guard before building anything big.
    let tube_verts: usize = instances.iter().map(|i| Mesh::verts_per_tube(samples_of(i), ring)).sum();
    ensure!(
        tube_verts <= MAX_MESH_VERTICES,
        "the tube mesh would have {tube_verts} vertices (limit {MAX_MESH_VERTICES}): lower the repeats, \
         the samples per cell or the ring vertices"
    );
    let n_p = cloth.n_p;
    let ply_mul = if opts.plies { n_p as usize } else { 0 };
    ensure!(
        tube_verts * ply_mul <= MAX_MESH_VERTICES * 4,
        "the ply mesh would be too large: lower the repeats or the samples per cell"
    );

    let units = format!(
        "units: yarn pitch = {PITCH} (renderer units), cloth mid-plane z = 0, front faces +z; weft along x, warp along y"
    );
    let about = format!(
        "woven export: pattern {}x{} (n_e x n_a), {}x{} repeats from tile ({}, {}), repeat size {} x {}",
        ne, na, repeats[0], repeats[1], origin[0], origin[1], tx, ty
    );
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut files = Vec::new();

    // (a) Polylines.
    let mut pl = String::new();
    let mut edges = String::new();
    let (mut nv, mut ne_count) = (0usize, 0usize);
    for (ci, inst) in instances.iter().enumerate() {
        let y = &set.yarns[inst.yarn];
        let n = samples_of(inst);
        for k in 0..n {
            let s = inst.s0 + (inst.s1 - inst.s0) * k as f32 / (n - 1) as f32;
            let p = to_world(&set, inst.point(y, s));
            let _ = writeln!(pl, "{} {} {} {} {} {}", p.x, p.y, p.z, y.radius, inst.yarn, ci);
            if k > 0 {
                let _ = writeln!(edges, "{} {}", nv + k - 1, nv + k);
                ne_count += 1;
            }
        }
        nv += n;
    }
    {
        let mut out = Vec::new();
        ply_header(
            &mut out,
            true,
            &[
                about.clone(),
                units.clone(),
                "yarn centre curves as polylines; yarn = index (weft rows 0..n_e, then warp columns), curve = curve id"
                    .into(),
                format!(
                    "radius = half-width across the cloth; the half-height through it is aspect * radius, aspect = {}",
                    set.shape.aspect
                ),
            ],
        );
        let head = format!(
            "element vertex {nv}\nproperty float x\nproperty float y\nproperty float z\nproperty float radius\n\
             property int yarn\nproperty int curve\nelement edge {ne_count}\nproperty int vertex1\n\
             property int vertex2\nend_header\n"
        );
        out.extend_from_slice(head.as_bytes());
        out.extend_from_slice(pl.as_bytes());
        out.extend_from_slice(edges.as_bytes());
        crate::io::write_atomic(&dir.join("yarns.ply"), &out).context("writing yarns.ply")?;
        files.push("yarns.ply".to_string());
    }

    // (b) Tubes.
    let mut mesh = Mesh::default();
    for inst in &instances {
        let y = &set.yarns[inst.yarn];
        let n = samples_of(inst);
        let rings: Vec<(Vec3, Vec3, Vec3)> = (0..n)
            .map(|k| {
                let s = inst.s0 + (inst.s1 - inst.s0) * k as f32 / (n - 1) as f32;
                let f = y.frame(s);
                (inst.point(y, s), f.ex, f.ey)
            })
            .collect();
        mesh.tube(&rings, y.radius, ring, inst.yarn as u32);
    }
    mesh.unstretch(set.shape.aspect);
    let mesh_comments = |what: &str| vec![about.clone(), units.clone(), what.to_string()];
    write_mesh(
        &dir.join("tubes.ply"),
        &mesh,
        opts.ascii,
        &mesh_comments("yarn tubes (closed, outward normals); yarn = index (weft rows, then warp columns)"),
    )?;
    files.push("tubes.ply".into());
    let (tube_vertices, tube_faces) = (mesh.pos.len(), mesh.tris.len());
    drop(mesh);

    // (b') Plies.
    let (mut ply_vertices, mut ply_faces) = (0, 0);
    if opts.plies {
        let mut mesh = Mesh::default();
        for inst in &instances {
            let y = &set.yarns[inst.yarn];
            let rp = element_radius(n_p) * y.radius;
            let ring_r = y.radius - rp;
            let (kappa, _) = crate::geometry::ply::PlyModel { n_p, n_f: cloth.n_f }.twists(y);
            // Enough samples for the helix: at most π/8 of twist per sample.
            let per_cell = k_s.max((kappa * PITCH * 1.2 / (std::f32::consts::PI / 8.0)).ceil() as usize);
            let n = ((inst.s1 - inst.s0) / PITCH).round() as usize * per_cell + 1;
            for pi in 0..n_p {
                let rings: Vec<(Vec3, Vec3, Vec3)> = (0..n)
                    .map(|k| {
                        let s = inst.s0 + (inst.s1 - inst.s0) * k as f32 / (n - 1) as f32;
                        let f = y.frame(s);
                        let beta = TAU * pi as f32 / n_p as f32 + kappa * f.arc;
                        let radial = f.ex * beta.cos() + f.ey * beta.sin();
                        let centre = inst.point(y, s) + radial * ring_r;
                        let tp = (f.t + (f.ey * beta.cos() - f.ex * beta.sin()) * (ring_r * kappa)).normalize();
                        let u = (radial - tp * radial.dot(tp)).normalize_or(f.ex);
                        (centre, u, tp.cross(u))
                    })
                    .collect();
                mesh.tube(&rings, rp, ring, inst.yarn as u32);
            }
        }
        mesh.unstretch(set.shape.aspect);
        write_mesh(
            &dir.join("plies.ply"),
            &mesh,
            opts.ascii,
            &mesh_comments(&format!(
                "{n_p} plies per yarn as helical tubes (twist {PLY_TWIST_DEG} deg, ply radius = element_radius(n_p) * R)"
            )),
        )?;
        files.push("plies.ply".into());
        ply_vertices = mesh.pos.len();
        ply_faces = mesh.tris.len();
    }

    // (c) Mitsuba curve files (no comments: Mitsuba's loader accepts only numbers and blank lines).
    let mut control = 0;
    for (fam, name, range) in [
        (Family::Weft, "curves_weft.txt", 0..weft_curves),
        (Family::Warp, "curves_warp.txt", weft_curves..instances.len()),
    ] {
        let mut s = String::new();
        for inst in &instances[range] {
            let y = &set.yarns[inst.yarn];
            debug_assert_eq!(y.family, fam);
            let pts = control_points(y, inst, set.shape.aspect)?;
            control += pts.len();
            for p in pts {
                let _ = writeln!(s, "{} {} {} {}", p[0], p[1], p[2], p[3]);
            }
            s.push('\n');
        }
        crate::io::write_atomic(&dir.join(name), s.as_bytes()).with_context(|| format!("writing {name}"))?;
        files.push(name.into());
    }

    // (c') Mitsuba scene.
    let xml = scene_xml(params, &set, &about, &units);
    crate::io::write_atomic(&dir.join("scene.xml"), xml.as_bytes()).context("writing scene.xml")?;
    files.push("scene.xml".into());

    let mut summary = ExportSummary {
        dir: dir.to_path_buf(),
        files,
        pitch: PITCH,
        repeats,
        origin_tile: origin,
        tile_size: [tx, ty],
        clamped,
        weft_curves,
        warp_curves,
        polyline_vertices: nv,
        polyline_edges: ne_count,
        tube_vertices,
        tube_faces,
        ply_vertices,
        ply_faces,
        control_points: control,
    };
    summary.files.push("export.json".into());
    let json = serde_json::to_string_pretty(&summary).context("serialising the export summary")? + "\n";
    crate::io::write_atomic(&dir.join("export.json"), json.as_bytes()).context("writing export.json")?;
    Ok(summary)
}

/// The Mitsuba 3 scene (XML comments never contain a double hyphen).
fn scene_xml(params: &ParamFile, set: &YarnSet, about: &str, units: &str) -> String {
    let a = &params.cloth.appearance;
    let sc = &params.scene;
    let ex = sc.exposure;
    let view = view_of(params, set);
    let mut x = String::new();
    let _ = writeln!(x, "<?xml version=\"1.0\" encoding=\"utf-8\"?>");
    let _ = writeln!(x, "<!-- {about} -->");
    let _ = writeln!(x, "<!-- {units} -->");
    let _ = writeln!(
        x,
        "<!-- Load with mitsuba.load_file(\"scene.xml\") in a variant with curve support (llvm_ad_rgb or \
         cuda_ad_rgb). The materials are a STAND-IN for the fitted BYSDF: diffuse body colour plus a GGX \
         specular lobe, blended with a rough dielectric for light through the yarns; plies, fibers, \
         ply/fiber shadowing (G_p, G_f) and the BYSDF's exit-point terms are not reproduced. -->"
    );
    let _ = writeln!(x, "<scene version=\"3.0.0\">");
    let _ =
        writeln!(x, "  <integrator type=\"path\">\n    <integer name=\"max_depth\" value=\"16\"/>\n  </integrator>");

    // Camera.
    let _ = writeln!(
        x,
        "  <!-- Camera: the renderer's {:?} view ({}x{} px, {} spp). -->",
        sc.camera.projection, sc.width, sc.height, sc.spp
    );
    match view.projection {
        Projection::Orthographic => {
            let _ = writeln!(x, "  <sensor type=\"orthographic\">");
            let _ = writeln!(x, "    <float name=\"far_clip\" value=\"{}\"/>", view.far);
            let _ = writeln!(x, "    <transform name=\"to_world\">");
            let _ = writeln!(x, "      <scale x=\"{0}\" y=\"{0}\"/>", view.half_w);
        }
        Projection::Perspective => {
            let _ = writeln!(x, "  <sensor type=\"perspective\">");
            let _ = writeln!(x, "    <float name=\"fov\" value=\"{}\"/>", view.fov_y_deg);
            let _ = writeln!(x, "    <string name=\"fov_axis\" value=\"y\"/>");
            let _ = writeln!(x, "    <float name=\"far_clip\" value=\"{}\"/>", view.far);
            let _ = writeln!(x, "    <transform name=\"to_world\">");
        }
    }
    let _ = writeln!(
        x,
        "      <lookat origin=\"{}\" target=\"{}\" up=\"{}\"/>\n    </transform>",
        fmt_v(view.origin),
        fmt_v(view.target),
        fmt_v(view.up)
    );
    let _ = writeln!(
        x,
        "    <sampler type=\"independent\">\n      <integer name=\"sample_count\" value=\"{}\"/>\n    </sampler>",
        sc.spp
    );
    let _ = writeln!(
        x,
        "    <film type=\"hdrfilm\">\n      <integer name=\"width\" value=\"{}\"/>\n      <integer name=\"height\" \
         value=\"{}\"/>\n      <string name=\"pixel_format\" value=\"rgb\"/>\n    </film>\n  </sensor>",
        sc.width, sc.height
    );

    // Lights (scaled by the scene's exposure, which Mitsuba's film does not have).
    let _ = writeln!(x, "  <!-- Lights, scaled by the scene exposure {ex}. -->");
    if sc.lights.ambient.iter().any(|&v| v > 0.0) {
        let _ = writeln!(
            x,
            "  <emitter type=\"constant\">\n    <rgb name=\"radiance\" value=\"{}\"/>\n  </emitter>",
            fmt_rgb(sc.lights.ambient, ex)
        );
    }
    for l in &sc.lights.lights {
        match l {
            LightSpec::Directional { name, direction, irradiance, cone_deg } => {
                let d = Vec3::from(*direction).normalize();
                let note = if *cone_deg > 0.0 {
                    format!(" (a disc of {cone_deg} deg in the renderer; exported as a delta light, not visible through gaps)")
                } else {
                    String::new()
                };
                let _ = writeln!(x, "  <!-- {}{note} -->", xml_comment(name));
                let _ = writeln!(
                    x,
                    "  <emitter type=\"directional\">\n    <vector name=\"direction\" x=\"{}\" y=\"{}\" z=\"{}\"/>\n    \
                     <rgb name=\"irradiance\" value=\"{}\"/>\n  </emitter>",
                    0.0 - d.x,
                    0.0 - d.y,
                    0.0 - d.z,
                    fmt_rgb(*irradiance, ex)
                );
            }
            LightSpec::Point { name, position, intensity } => {
                let _ = writeln!(x, "  <!-- {} -->", xml_comment(name));
                let _ = writeln!(
                    x,
                    "  <emitter type=\"point\">\n    <point name=\"position\" x=\"{}\" y=\"{}\" z=\"{}\"/>\n    \
                     <rgb name=\"intensity\" value=\"{}\"/>\n  </emitter>",
                    position[0],
                    position[1],
                    position[2],
                    fmt_rgb(*intensity, ex)
                );
            }
        }
    }

    // Materials: stand-in per family.
    let alpha = |v: f32| v.clamp(0.01, 1.0);
    for (id, rb, sb) in [("weft", a.r_b_e, a.s_b_e), ("warp", a.r_b_a, a.s_b_a)] {
        let _ = writeln!(
            x,
            "  <!-- Stand-in material of the {id} yarns: m_r = {} of the light is reflected (diffuse R^B + GGX \
             R^S), the rest goes through a rough dielectric tinted by S^B. -->",
            a.m_r
        );
        let _ = writeln!(x, "  <bsdf type=\"blendbsdf\" id=\"mat_{id}\">");
        let _ = writeln!(x, "    <float name=\"weight\" value=\"{}\"/>", 1.0 - a.m_r);
        let _ = writeln!(x, "    <bsdf type=\"twosided\">\n      <bsdf type=\"roughplastic\">");
        let _ = writeln!(x, "        <string name=\"distribution\" value=\"ggx\"/>");
        let _ = writeln!(x, "        <float name=\"alpha\" value=\"{}\"/>", alpha(a.alpha_s));
        let _ = writeln!(x, "        <float name=\"int_ior\" value=\"{}\"/>", a.eta_s);
        let _ = writeln!(x, "        <rgb name=\"diffuse_reflectance\" value=\"{}\"/>", fmt_rgb(rb, 1.0));
        let _ = writeln!(x, "        <rgb name=\"specular_reflectance\" value=\"{}\"/>", fmt_rgb(a.r_s, 1.0));
        let _ = writeln!(x, "      </bsdf>\n    </bsdf>");
        let _ = writeln!(x, "    <bsdf type=\"roughdielectric\">");
        let _ = writeln!(x, "      <string name=\"distribution\" value=\"ggx\"/>");
        let _ = writeln!(x, "      <float name=\"alpha\" value=\"{}\"/>", alpha(a.alpha_s_y));
        let _ = writeln!(x, "      <float name=\"int_ior\" value=\"{}\"/>", a.eta_s_y);
        let _ = writeln!(x, "      <rgb name=\"specular_reflectance\" value=\"{}\"/>", fmt_rgb(a.t_s, 1.0));
        let _ = writeln!(x, "      <rgb name=\"specular_transmittance\" value=\"{}\"/>", fmt_rgb(sb, 1.0));
        let _ = writeln!(x, "    </bsdf>\n  </bsdf>");
    }

    // Shapes: Mitsuba's curves are round, so a flattened cloth uses the exact elliptical tube mesh.
    if set.shape.aspect != 1.0 {
        let _ = writeln!(
            x,
            "  <!-- Flattened yarns (aspect {}): Mitsuba's B-spline curves are round, so the tube mesh (exact \
             elliptical sections) is used; tubes.ply holds both families, split it by its yarn property for \
             per-family materials. -->\n  <shape type=\"ply\">\n    <string name=\"filename\" value=\"tubes.ply\"/>\n    \
             <ref id=\"mat_weft\"/>\n  </shape>\n</scene>",
            set.shape.aspect
        );
        return x;
    }
    for id in ["weft", "warp"] {
        let _ = writeln!(
            x,
            "  <shape type=\"bsplinecurve\">\n    <string name=\"filename\" value=\"curves_{id}.txt\"/>\n    \
             <ref id=\"mat_{id}\"/>\n  </shape>"
        );
    }
    let _ = writeln!(
        x,
        "  <!-- Without curve support (scalar variants lacking Embree), use the tube mesh instead of the two curve shapes:\n       \
         <shape type=\"ply\"><string name=\"filename\" value=\"tubes.ply\"/><ref id=\"mat_weft\"/></shape>\n       \
         (tubes.ply holds both families; split by its yarn property for per-family materials). -->"
    );
    let _ = writeln!(x, "</scene>");
    x
}

/// Text safe inside an XML comment (no double hyphens, no angle brackets).
fn xml_comment(s: &str) -> String {
    let mut t: String = s.chars().map(|c| if matches!(c, '<' | '>' | '&') { '_' } else { c }).collect();
    while t.contains("--") {
        t = t.replace("--", "-");
    }
    t.trim_end_matches('-').to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn control_values_invert() {
        let c: Vec<f32> = (0..24).map(|k| (k as f32 * 0.7).sin()).collect();
        let v: Vec<f32> = (0..24).map(|k| (c[(k + 23) % 24] + 4.0 * c[k] + c[(k + 1) % 24]) / 6.0).collect();
        for (a, b) in control_values(&v).iter().zip(&c) {
            assert!((a - b).abs() < 1e-5);
        }
        assert_eq!(xml_comment("a--b<c>"), "a-b_c_");
    }
}
