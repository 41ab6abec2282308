//! Noise post-estimation (`woven::noise`) and geometry export (`woven::export`).
//!
//! Noise: a residual with a known anisotropic band (seeded random-phase sinusoids around one
//! frequency + white noise, correlated channels) is fitted; a patch of another size is synthesized and
//! must match the residual's per-channel variance (±10%), its channel correlation signs and the
//! location of its spectral peak; degenerate residuals give clear errors.
//! Export: PLY header counts match the bodies, the Mitsuba curve files parse and their B-splines lie
//! on the renderer's yarn curves (after undoing the tile offset), the XML is well-formed, the view is
//! covered, and bad options are refused.

use glam::Vec3;
use rand::prelude::*;
use rustfft::num_complex::Complex;
use rustfft::FftPlanner;
use std::path::Path;
use woven::export::{bspline_point, export, ExportOptions};
use woven::geometry::yarn::{Family, YarnSet, YarnShape};
use woven::noise::{residual, NoiseError, NoiseModel};
use woven::params::{ClothParams, ParamFile};
use woven::scene::{Projection, Scene};
use woven::Image;

// ---------------------------------------------------------------- noise helpers

const BAND: (f64, f64) = (0.15, 0.05);

/// Scalar field: 6 random-phase sinusoids with frequencies within ±0.008 of `BAND`, plus white noise.
fn band_field(w: usize, h: usize, white: f64, seed: u64) -> Vec<f64> {
    let mut rng = StdRng::seed_from_u64(seed);
    let waves: Vec<(f64, f64, f64)> = (0..6)
        .map(|_| {
            (
                BAND.0 + rng.random_range(-0.008..0.008),
                BAND.1 + rng.random_range(-0.008..0.008),
                rng.random_range(0.0..std::f64::consts::TAU),
            )
        })
        .collect();
    let mut v = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            let s: f64 = waves
                .iter()
                .map(|&(fx, fy, ph)| (std::f64::consts::TAU * (fx * x as f64 + fy * y as f64) + ph).cos())
                .sum();
            // Approximately Gaussian white noise (sum of 4 uniforms, unit variance).
            let g: f64 = ((0..4).map(|_| rng.random::<f64>()).sum::<f64>() - 2.0) * 3f64.sqrt();
            v.push(s + white * g);
        }
    }
    v
}

fn band_residual(w: u32, h: u32, seed: u64) -> Image {
    let n = band_field(w as usize, h as usize, 0.3, seed);
    let mut rng = StdRng::seed_from_u64(seed + 100);
    let data = n
        .iter()
        .map(|&v| {
            let e = (rng.random::<f64>() - 0.5) * 6.0;
            [(0.10 * v) as f32, (0.05 * v + 0.05 * e) as f32, (-0.08 * v) as f32]
        })
        .collect();
    Image::new(w, h, data)
}

fn channel(img: &Image, c: usize) -> Vec<f64> {
    img.data.iter().map(|p| p[c] as f64).collect()
}

fn variance(v: &[f64]) -> f64 {
    let m = v.iter().sum::<f64>() / v.len() as f64;
    v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64
}

fn correlation(a: &[f64], b: &[f64]) -> f64 {
    let (ma, mb) = (a.iter().sum::<f64>() / a.len() as f64, b.iter().sum::<f64>() / b.len() as f64);
    let cov: f64 = a.iter().zip(b).map(|(x, y)| (x - ma) * (y - mb)).sum::<f64>() / a.len() as f64;
    cov / (variance(a) * variance(b)).sqrt()
}

/// Periodogram of a `w×h` field: (fx, fy, power) for every bin but DC.
fn periodogram(v: &[f64], w: usize, h: usize) -> Vec<(f64, f64, f64)> {
    let m = v.iter().sum::<f64>() / v.len() as f64;
    let mut buf: Vec<Complex<f64>> = v.iter().map(|x| Complex::new(x - m, 0.0)).collect();
    let mut pl = FftPlanner::new();
    pl.plan_fft_forward(w).process(&mut buf);
    let mut t = vec![Complex::new(0.0, 0.0); w * h];
    for y in 0..h {
        for x in 0..w {
            t[x * h + y] = buf[y * w + x];
        }
    }
    pl.plan_fft_forward(h).process(&mut t);
    let sgn = |k: usize, n: usize| if k > n / 2 { k as f64 - n as f64 } else { k as f64 };
    let mut out = Vec::new();
    for x in 0..w {
        for y in 0..h {
            if x + y > 0 {
                out.push((sgn(x, w) / w as f64, sgn(y, h) / h as f64, t[x * h + y].norm_sqr()));
            }
        }
    }
    out
}

/// Distance of (fx, fy) to ±BAND.
fn band_distance(fx: f64, fy: f64) -> f64 {
    ((fx - BAND.0).powi(2) + (fy - BAND.1).powi(2)).sqrt().min(((fx + BAND.0).powi(2) + (fy + BAND.1).powi(2)).sqrt())
}

fn mean_power_near(spec: &[(f64, f64, f64)], c: (f64, f64), r: f64) -> f64 {
    let near: Vec<f64> = spec
        .iter()
        .filter(|&&(fx, fy, _)| {
            ((fx - c.0).powi(2) + (fy - c.1).powi(2)).sqrt() < r || ((fx + c.0).powi(2) + (fy + c.1).powi(2)).sqrt() < r
        })
        .map(|s| s.2)
        .collect();
    near.iter().sum::<f64>() / near.len().max(1) as f64
}

// ---------------------------------------------------------------- noise tests

#[test]
fn noise_fit_and_synthesis_match_variance_correlation_and_peak() {
    let res = band_residual(128, 96, 11);
    let model = NoiseModel::fit(&res).expect("fit");
    model.validate().unwrap();
    assert!(!model.gaussians.is_empty() && model.gaussians.len() <= 4, "{model:?}");
    let (fx, fy) = model.dominant_frequency().unwrap();
    assert!(band_distance(fx as f64, fy as f64) < 0.02, "dominant Gaussian at ({fx}, {fy}), expected ±{BAND:?}");
    let band_weight: f32 =
        model.gaussians.iter().filter(|g| band_distance(g.fx as f64, g.fy as f64) < 0.03).map(|g| g.weight).sum();
    assert!(band_weight > 0.7, "band carries {band_weight} of the variance: {model:?}");
    for c in 0..3 {
        let v = variance(&channel(&res, c));
        assert!((model.variance[c] as f64 - v).abs() < 1e-3 * v + 1e-12, "variance[{c}]");
    }
    assert!(model.correlation[0] > 0.95 && model.correlation[2] < -0.95, "{:?}", model.correlation);
    assert!(model.correlation[1] > 0.5 && model.correlation[1] < 0.9, "{:?}", model.correlation);

    // Another size: variance within ±10%, same correlation signs, same spectral peak.
    let (w, h) = (200usize, 150usize);
    let syn = model.synthesize(w as u32, h as u32, 3);
    assert_eq!((syn.width, syn.height), (200, 150));
    assert!(syn.data.iter().flatten().all(|v| v.is_finite()));
    for c in 0..3 {
        let (vr, vs) = (variance(&channel(&res, c)), variance(&channel(&syn, c)));
        assert!((vs / vr - 1.0).abs() < 0.10, "channel {c}: synthesized variance {vs} vs residual {vr}");
    }
    let (r, g, b) = (channel(&syn, 0), channel(&syn, 1), channel(&syn, 2));
    assert!(correlation(&r, &b) < -0.9, "r-b correlation {}", correlation(&r, &b));
    let rg = correlation(&r, &g);
    assert!(rg > 0.5 && rg < 0.9, "r-g correlation {rg}");
    let spec = periodogram(&r, w, h);
    let peak = spec.iter().max_by(|a, b| a.2.total_cmp(&b.2)).unwrap();
    assert!(band_distance(peak.0, peak.1) < 0.02, "synthesized peak at ({}, {})", peak.0, peak.1);
    // Anisotropic: the band rotated by 90° carries little power.
    let on = mean_power_near(&spec, BAND, 0.02);
    let off = mean_power_near(&spec, (-BAND.1, BAND.0), 0.02);
    assert!(on > 20.0 * off, "band power {on} vs rotated {off}");

    // Deterministic in the seed.
    assert_eq!(model.synthesize(40, 30, 3), model.synthesize(40, 30, 3));
    assert_ne!(model.synthesize(40, 30, 3), model.synthesize(40, 30, 4));
    assert_eq!(model.synthesize(0, 5, 1).data.len(), 0);

    // JSON round trip.
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("noise.json");
    model.save(&f).unwrap();
    assert_eq!(NoiseModel::load(&f).unwrap(), model);

    // add_to: zero-mean noise of the residual's variance.
    let mut img = Image::filled(64, 48, [0.5, 0.5, 0.5]);
    model.add_to(&mut img, 9);
    let r = channel(&img, 0);
    let m = r.iter().sum::<f64>() / r.len() as f64;
    assert!((m - 0.5).abs() < 1e-4, "mean {m}");
    let vr = variance(&channel(&res, 0));
    assert!((variance(&r) / vr - 1.0).abs() < 0.10);
}

#[test]
fn white_residual_is_mostly_floor() {
    let mut rng = StdRng::seed_from_u64(77);
    let white: Vec<f64> = (0..96 * 96).map(|_| rng.random::<f64>() - 0.5).collect();
    let img = Image::new(96, 96, white.iter().map(|&v| [v as f32; 3]).collect());
    let m = NoiseModel::fit(&img).unwrap();
    let g: f32 = m.gaussians.iter().map(|g| g.weight).sum();
    assert!(m.floor > 0.6, "white noise should be mostly floor: floor {} gaussians {g} {m:?}", m.floor);
    let syn = m.synthesize(80, 64, 1);
    let spec = periodogram(&channel(&syn, 0), 80, 64);
    let lo = mean_power_near(&spec, (0.1, 0.0), 0.05);
    let hi = mean_power_near(&spec, (0.4, 0.3), 0.05);
    assert!(lo / hi < 3.0 && hi / lo < 3.0, "white spectrum not flat: {lo} vs {hi}");
}

#[test]
fn lowpass_residual_gives_a_centred_gaussian() {
    // White noise blurred by a 5×5 box: an isotropic low-pass spectrum around DC.
    let (w, h) = (96usize, 80usize);
    let mut rng = StdRng::seed_from_u64(21);
    let white: Vec<f64> = (0..w * h).map(|_| rng.random::<f64>() - 0.5).collect();
    let blur: Vec<f64> = (0..w * h)
        .map(|i| {
            let (x, y) = ((i % w) as i64, (i / w) as i64);
            let mut s = 0.0;
            for dy in -2..=2 {
                for dx in -2..=2 {
                    s += white[((y + dy).rem_euclid(h as i64) as usize) * w + (x + dx).rem_euclid(w as i64) as usize];
                }
            }
            s / 25.0
        })
        .collect();
    let img =
        Image::new(w as u32, h as u32, blur.iter().map(|&v| [v as f32, 0.5 * v as f32, 0.25 * v as f32]).collect());
    let m = NoiseModel::fit(&img).unwrap();
    let (fx, fy) = m.dominant_frequency().unwrap();
    assert!((fx * fx + fy * fy).sqrt() < 0.05, "low-pass peak at ({fx}, {fy}): {m:?}");
    let syn = m.synthesize(64, 64, 2);
    let r = channel(&syn, 0);
    assert!((variance(&r) / variance(&channel(&img, 0)) - 1.0).abs() < 0.10);
    let spec = periodogram(&r, 64, 64);
    let lo = mean_power_near(&spec, (0.0, 0.0), 0.06);
    let hi = mean_power_near(&spec, (0.3, 0.3), 0.06);
    assert!(lo > 10.0 * hi, "synthesized low-pass power {lo} vs high {hi}");
}

#[test]
fn noise_errors_are_clear() {
    let e = NoiseModel::fit(&Image::new(0, 0, vec![])).unwrap_err();
    assert!(matches!(e, NoiseError::Empty), "{e}");
    let e = NoiseModel::fit(&band_residual(8, 40, 1)).unwrap_err();
    assert!(e.to_string().contains("8x40") && e.to_string().contains("16x16"), "{e}");
    let mut r = band_residual(32, 32, 1);
    r.data[5 * 32 + 7][1] = f32::NAN;
    let e = NoiseModel::fit(&r).unwrap_err();
    assert!(e.to_string().contains("NaN") && e.to_string().contains("x=7, y=5"), "{e}");
    let e = NoiseModel::fit(&Image::filled(32, 32, [0.2, 0.3, 0.4])).unwrap_err();
    assert!(matches!(e, NoiseError::ZeroVariance), "{e}");

    let a = Image::filled(20, 10, [0.5, 0.5, 0.5]);
    let b = Image::filled(10, 20, [0.1, 0.2, 0.3]);
    let e = residual(&a, &b).unwrap_err();
    assert!(e.to_string().contains("20x10") && e.to_string().contains("10x20"), "{e}");
    let b = Image::filled(20, 10, [0.1, 0.2, 0.3]);
    let d = residual(&a, &b).unwrap();
    assert!(d.data.iter().all(|p| (p[0] - 0.4).abs() < 1e-6 && (p[2] - 0.2).abs() < 1e-6));
    let mut bad = b.clone();
    bad.data[3][0] = f32::INFINITY;
    assert!(matches!(residual(&a, &bad).unwrap_err(), NoiseError::NotFinite { .. }));

    // A tampered model file is refused with the reason.
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("noise.json");
    let m = NoiseModel::fit(&band_residual(32, 32, 2)).unwrap();
    let text = m.to_json().replacen("\"floor\": ", "\"floor\": 0.5e0 + ", 1);
    std::fs::write(&f, &text).unwrap();
    assert!(NoiseModel::load(&f).is_err());
    let mut m2 = m.clone();
    m2.floor += 1.0;
    m2.save(&f).unwrap();
    let e = NoiseModel::load(&f).unwrap_err().to_string();
    assert!(e.contains("floor"), "{e}");
    assert!(NoiseModel::load(&dir.path().join("missing.json")).unwrap_err().to_string().contains("missing.json"));
}

// ---------------------------------------------------------------- export helpers

struct Ply {
    ascii: bool,
    elements: Vec<(String, usize, Vec<String>)>,
    body: Vec<u8>,
}

fn read_ply(path: &Path) -> Ply {
    let bytes = std::fs::read(path).unwrap();
    let end = b"end_header\n";
    let pos = bytes.windows(end.len()).position(|w| w == end).expect("end_header") + end.len();
    let head = std::str::from_utf8(&bytes[..pos]).unwrap();
    let mut lines = head.lines();
    assert_eq!(lines.next(), Some("ply"));
    let mut ascii = None;
    let mut elements: Vec<(String, usize, Vec<String>)> = Vec::new();
    for l in lines {
        let t: Vec<&str> = l.split_whitespace().collect();
        match t.first().copied() {
            Some("format") => ascii = Some(t[1] == "ascii"),
            Some("element") => elements.push((t[1].to_string(), t[2].parse().unwrap(), vec![])),
            Some("property") => elements.last_mut().unwrap().2.push(t[1..].join(" ")),
            Some("comment") | Some("end_header") => {}
            other => panic!("unexpected PLY header line {other:?}"),
        }
    }
    Ply { ascii: ascii.unwrap(), elements, body: bytes[pos..].to_vec() }
}

/// Vertices (x, y, z, yarn) and triangles of a mesh PLY (ASCII or binary), checking the body size.
fn read_mesh(path: &Path) -> (Vec<(Vec3, i32)>, Vec<[usize; 3]>) {
    let ply = read_ply(path);
    assert_eq!(ply.elements.len(), 2);
    let (nv, nf) = (ply.elements[0].1, ply.elements[1].1);
    assert_eq!(ply.elements[0].2, ["float x", "float y", "float z", "float nx", "float ny", "float nz", "int yarn"]);
    assert_eq!(ply.elements[1].2, ["list uchar int vertex_indices"]);
    let mut verts = Vec::with_capacity(nv);
    let mut faces = Vec::with_capacity(nf);
    if ply.ascii {
        let text = String::from_utf8(ply.body).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), nv + nf, "ASCII body lines vs header counts");
        for l in &lines[..nv] {
            let t: Vec<f32> = l.split_whitespace().map(|x| x.parse().unwrap()).collect();
            assert_eq!(t.len(), 7);
            verts.push((Vec3::new(t[0], t[1], t[2]), t[6] as i32));
        }
        for l in &lines[nv..] {
            let t: Vec<usize> = l.split_whitespace().map(|x| x.parse().unwrap()).collect();
            assert_eq!(t.len(), 4);
            assert_eq!(t[0], 3);
            faces.push([t[1], t[2], t[3]]);
        }
    } else {
        assert_eq!(ply.body.len(), nv * 28 + nf * 13, "binary body size vs header counts");
        let f = |o: usize| f32::from_le_bytes(ply.body[o..o + 4].try_into().unwrap());
        let i = |o: usize| i32::from_le_bytes(ply.body[o..o + 4].try_into().unwrap());
        for k in 0..nv {
            let o = k * 28;
            verts.push((Vec3::new(f(o), f(o + 4), f(o + 8)), i(o + 24)));
        }
        for k in 0..nf {
            let o = nv * 28 + k * 13;
            assert_eq!(ply.body[o], 3);
            faces.push([i(o + 1) as usize, i(o + 5) as usize, i(o + 9) as usize]);
        }
    }
    assert!(faces.iter().flatten().all(|&i| i < nv), "face index out of range");
    (verts, faces)
}

/// Distance from `p` to yarn `k` of `set` after undoing the whole-repeat lateral shift.
fn dist_to_yarn(set: &YarnSet, k: usize, p: Vec3) -> f32 {
    let y = &set.yarns[k];
    let q = match y.family {
        Family::Weft => p - Vec3::Y * ((p.y / set.tile_y).floor() * set.tile_y),
        Family::Warp => p - Vec3::X * ((p.x / set.tile_x).floor() * set.tile_x),
    };
    // Brute force around the projection (Newton from the projection can stall on steep crimp).
    let s0 = match y.family {
        Family::Weft => q.x,
        Family::Warp => q.y,
    };
    (0..=1600).map(|i| (q - y.point(s0 - 8.0 + i as f32 * 0.01)).length()).fold(f32::MAX, f32::min)
}

/// Point of yarn `k` at the same length coordinate as `p`, shifted like `p` (exact comparison).
fn on_yarn(set: &YarnSet, k: usize, p: Vec3) -> f32 {
    let y = &set.yarns[k];
    let q = match y.family {
        Family::Weft => y.point(p.x) + Vec3::Y * ((p.y / set.tile_y).floor() * set.tile_y),
        Family::Warp => y.point(p.y) + Vec3::X * ((p.x / set.tile_x).floor() * set.tile_x),
    };
    (p - q).length()
}

/// Curves of a Mitsuba B-spline curve file: blank-line separated, `x y z radius` per line.
fn read_curves(path: &Path) -> Vec<Vec<[f32; 4]>> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut curves = vec![];
    let mut cur: Vec<[f32; 4]> = vec![];
    for l in text.lines() {
        if l.trim().is_empty() {
            if !cur.is_empty() {
                curves.push(std::mem::take(&mut cur));
            }
            continue;
        }
        let t: Vec<f32> = l.split_whitespace().map(|x| x.parse().expect("number")).collect();
        assert_eq!(t.len(), 4, "line `{l}`");
        assert!(t.iter().all(|v| v.is_finite()));
        cur.push([t[0], t[1], t[2], t[3]]);
    }
    if !cur.is_empty() {
        curves.push(cur);
    }
    curves
}

/// Minimal XML well-formedness check: balanced, properly nested tags; quoted attributes; comments
/// without `--`; no stray text. Returns the start tags as (name, attributes).
fn check_xml(text: &str) -> Vec<(String, Vec<(String, String)>)> {
    let mut stack: Vec<String> = vec![];
    let mut tags = vec![];
    let mut rest = text;
    let mut roots = 0;
    while let Some(i) = rest.find('<') {
        assert!(rest[..i].trim().is_empty(), "stray text {:?}", &rest[..i]);
        rest = &rest[i..];
        if let Some(r) = rest.strip_prefix("<!--") {
            let end = r.find("-->").expect("unterminated comment");
            assert!(!r[..end].contains("--"), "`--` inside a comment: {}", &r[..end]);
            rest = &r[end + 3..];
            continue;
        }
        if let Some(r) = rest.strip_prefix("<?") {
            assert!(stack.is_empty() && tags.is_empty(), "declaration must come first");
            rest = &r[r.find("?>").expect("unterminated declaration") + 2..];
            continue;
        }
        let end = rest.find('>').expect("unterminated tag");
        let tag = &rest[1..end];
        rest = &rest[end + 1..];
        if let Some(name) = tag.strip_prefix('/') {
            assert_eq!(stack.pop().as_deref(), Some(name.trim()), "mismatched end tag");
            continue;
        }
        let self_closing = tag.ends_with('/');
        let body = tag.trim_end_matches('/');
        let name_end = body.find(char::is_whitespace).unwrap_or(body.len());
        let name = &body[..name_end];
        assert!(!name.is_empty() && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_'), "name {name:?}");
        let mut attrs = vec![];
        let mut a = body[name_end..].trim();
        while !a.is_empty() {
            let eq = a.find('=').expect("attribute without =");
            let key = a[..eq].trim().to_string();
            let v = a[eq + 1..].trim_start();
            assert!(v.starts_with('"'), "unquoted attribute {key}");
            let close = v[1..].find('"').expect("unterminated attribute") + 1;
            let val = v[1..close].to_string();
            assert!(!val.contains('<') && !val.contains('&'), "unescaped attribute value {val:?}");
            attrs.push((key, val));
            a = v[close + 1..].trim_start();
        }
        if stack.is_empty() {
            roots += 1;
        }
        tags.push((name.to_string(), attrs));
        if !self_closing {
            stack.push(name.to_string());
        }
    }
    assert!(rest.trim().is_empty(), "trailing text");
    assert!(stack.is_empty(), "unclosed tags {stack:?}");
    assert_eq!(roots, 1, "exactly one root element");
    tags
}

fn attr<'a>(t: &'a (String, Vec<(String, String)>), k: &str) -> Option<&'a str> {
    t.1.iter().find(|(a, _)| a == k).map(|(_, v)| v.as_str())
}

fn twill() -> ParamFile {
    ParamFile { cloth: ClothParams::preset("twill31").unwrap(), scene: Scene::default() }
}

// ---------------------------------------------------------------- export tests

#[test]
fn export_files_are_consistent_and_on_the_yarn_curves() {
    let params = twill();
    let set = YarnSet::new(&params.cloth.pattern, params.cloth.r_e, params.cloth.r_a);
    let (ne, na) = (params.cloth.pattern.n_e(), params.cloth.pattern.n_a());
    let dir = tempfile::tempdir().unwrap();
    let s = export(&params, dir.path(), &ExportOptions::default()).unwrap();
    // Default view: tiles = 2 across a square image, centred at the origin.
    assert_eq!(s.repeats, [2, 2]);
    assert_eq!(s.origin_tile, [-1, -1]);
    assert_eq!((s.weft_curves, s.warp_curves), (ne * 2, na * 2));
    for f in ["yarns.ply", "tubes.ply", "curves_weft.txt", "curves_warp.txt", "scene.xml", "export.json"] {
        assert!(dir.path().join(f).is_file(), "{f} missing");
        assert!(s.files.iter().any(|x| x == f));
    }

    // (a) Polylines: counts, consistency, and every vertex on its yarn curve.
    let ply = read_ply(&dir.path().join("yarns.ply"));
    assert!(ply.ascii);
    assert_eq!(ply.elements[0].0, "vertex");
    assert_eq!(ply.elements[0].2, ["float x", "float y", "float z", "float radius", "int yarn", "int curve"]);
    assert_eq!(ply.elements[1].0, "edge");
    let (nv, ne_) = (ply.elements[0].1, ply.elements[1].1);
    assert_eq!((nv, ne_), (s.polyline_vertices, s.polyline_edges));
    assert_eq!(ne_, nv - (s.weft_curves + s.warp_curves), "one polyline per curve");
    let text = String::from_utf8(ply.body).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), nv + ne_);
    let mut worst: f32 = 0.0;
    let mut curve_ids = std::collections::BTreeSet::new();
    for l in &lines[..nv] {
        let t: Vec<f32> = l.split_whitespace().map(|x| x.parse().unwrap()).collect();
        let (p, k) = (Vec3::new(t[0], t[1], t[2]), t[4] as usize);
        assert_eq!(t[3], set.yarns[k].radius);
        worst = worst.max(on_yarn(&set, k, p));
        curve_ids.insert(t[5] as usize);
        assert!(p.x >= -s.tile_size[0] - 1e-3 && p.x <= s.tile_size[0] + 1e-3);
    }
    assert!(worst < 1e-3, "polyline vertex {worst} off its yarn curve");
    assert_eq!(curve_ids.len(), s.weft_curves + s.warp_curves);
    for l in &lines[nv..] {
        let t: Vec<usize> = l.split_whitespace().map(|x| x.parse().unwrap()).collect();
        assert!(t.len() == 2 && t[0] < nv && t[1] == t[0] + 1);
    }

    // (b) Tubes: binary body matches the header; vertices at the radius (or on the axis for caps).
    let (verts, faces) = read_mesh(&dir.path().join("tubes.ply"));
    assert_eq!((verts.len(), faces.len()), (s.tube_vertices, s.tube_faces));
    let per_weft = na * 2 * 16 + 1;
    let per_warp = ne * 2 * 16 + 1;
    let expect_v = s.weft_curves * (per_weft * 12 + 2) + s.warp_curves * (per_warp * 12 + 2);
    let expect_f = s.weft_curves * (2 * 12 * per_weft) + s.warp_curves * (2 * 12 * per_warp);
    assert_eq!((verts.len(), faces.len()), (expect_v, expect_f));
    for (p, k) in verts.iter().step_by(7) {
        let d = dist_to_yarn(&set, *k as usize, *p);
        let r = set.yarns[*k as usize].radius;
        assert!((d - r).abs() < 0.02 * r || d < 1e-3, "tube vertex at {d} from yarn {k} (radius {r})");
    }

    // (c) Curve files: one curve per yarn × repeat, B-splines on the renderer's curves.
    for (name, fam, count) in [("curves_weft.txt", Family::Weft, ne * 2), ("curves_warp.txt", Family::Warp, na * 2)] {
        let curves = read_curves(&dir.path().join(name));
        assert_eq!(curves.len(), count, "{name}");
        assert_eq!(
            std::fs::read_to_string(dir.path().join(name))
                .unwrap()
                .split("\n\n")
                .filter(|c| !c.trim().is_empty())
                .count(),
            count
        );
        for c in &curves {
            assert!(c.len() >= 4);
            let segs = c.len() - 3;
            let mut lo = f32::MAX;
            let mut hi = f32::MIN;
            for seg in 0..segs {
                for t in [0.0, 0.5] {
                    let p = bspline_point(&c[seg..seg + 4], t);
                    let along = if fam == Family::Weft { p.x } else { p.y };
                    lo = lo.min(along);
                    hi = hi.max(along);
                    // Which yarn: lateral coordinate modulo the repeat.
                    let (lat, tile) = if fam == Family::Weft { (p.y, s.tile_size[1]) } else { (p.x, s.tile_size[0]) };
                    let idx = (lat.rem_euclid(tile) / 10.0).floor() as usize;
                    let k = if fam == Family::Weft { idx } else { ne + idx };
                    assert_eq!(set.yarns[k].family, fam);
                    let d = on_yarn(&set, k, p);
                    assert!(d < 1e-3, "{name}: B-spline point {p} is {d} off yarn {k}");
                    assert!(c[seg].iter().all(|v| v.is_finite()));
                    assert_eq!(c[seg][3], set.yarns[k].radius);
                }
            }
            // The curve spans the whole patch along its length.
            let len = if fam == Family::Weft { s.tile_size[0] } else { s.tile_size[1] };
            assert!(lo <= -len + 1e-3 && hi >= len - 1e-3, "{name}: curve spans [{lo}, {hi}]");
        }
    }
    assert_eq!(
        s.control_points,
        read_curves(&dir.path().join("curves_weft.txt"))
            .iter()
            .chain(&read_curves(&dir.path().join("curves_warp.txt")))
            .map(|c| c.len())
            .sum::<usize>()
    );

    // (d) Scene XML: well-formed, references the curve files and defined materials, all lights.
    let xml = std::fs::read_to_string(dir.path().join("scene.xml")).unwrap();
    let tags = check_xml(&xml);
    assert_eq!(tags[0].0, "scene");
    let shapes: Vec<_> = tags.iter().filter(|t| t.0 == "shape").collect();
    assert_eq!(shapes.len(), 2);
    assert!(shapes.iter().all(|t| attr(t, "type") == Some("bsplinecurve")));
    for t in tags.iter().filter(|t| t.0 == "string" && attr(t, "name") == Some("filename")) {
        assert!(dir.path().join(attr(t, "value").unwrap()).is_file());
    }
    let ids: Vec<&str> = tags.iter().filter_map(|t| attr(t, "id")).collect();
    for t in tags.iter().filter(|t| t.0 == "ref") {
        assert!(ids.contains(&attr(t, "id").unwrap()), "dangling ref");
    }
    let emitters = tags.iter().filter(|t| t.0 == "emitter").count();
    assert_eq!(emitters, params.scene.lights.lights.len() + 1, "lights + ambient");
    let sensor = tags.iter().find(|t| t.0 == "sensor").unwrap();
    assert_eq!(attr(sensor, "type"), Some("orthographic"));
    let scale = tags.iter().find(|t| t.0 == "scale").unwrap();
    let half_w: f32 = attr(scale, "x").unwrap().parse().unwrap();
    assert!((half_w - 0.5 * 2.0 * s.tile_size[0]).abs() < 1e-3, "ortho half width {half_w}");
    assert!(xml.contains("pitch = 10") && xml.contains("STAND-IN"));
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("export.json")).unwrap()).unwrap();
    assert_eq!(meta["repeats"], serde_json::json!([2, 2]));
}

#[test]
fn export_ascii_plies_and_perspective() {
    let mut params = twill();
    params.scene.camera.projection = Projection::Perspective;
    params.scene.camera.tilt_deg = 20.0;
    params.scene.camera.fov_deg = 35.0;
    let set = YarnSet::new(&params.cloth.pattern, params.cloth.r_e, params.cloth.r_a);
    let dir = tempfile::tempdir().unwrap();
    let opts = ExportOptions { repeats: Some([1, 2]), plies: true, samples_per_cell: 8, ring: 6, ascii: true };
    let s = export(&params, dir.path(), &opts).unwrap();
    assert_eq!(s.repeats, [1, 2]);
    let (verts, faces) = read_mesh(&dir.path().join("tubes.ply"));
    assert_eq!((verts.len(), faces.len()), (s.tube_vertices, s.tube_faces));
    // Plies stay inside their yarn and reach its surface.
    let (pv, pf) = read_mesh(&dir.path().join("plies.ply"));
    assert_eq!((pv.len(), pf.len()), (s.ply_vertices, s.ply_faces));
    assert!(pv.len() > (params.cloth.n_p as usize - 1) * s.tube_vertices / 2);
    let mut reach: f32 = 0.0;
    for (p, k) in pv.iter().step_by(3) {
        let r = set.yarns[*k as usize].radius;
        let d = dist_to_yarn(&set, *k as usize, *p);
        assert!(d <= r * 1.03 + 1e-3, "ply vertex {d} outside yarn radius {r}");
        reach = reach.max(d / r);
    }
    assert!(reach > 0.95, "plies reach only {reach} of the radius");
    let xml = std::fs::read_to_string(dir.path().join("scene.xml")).unwrap();
    let tags = check_xml(&xml);
    let sensor = tags.iter().find(|t| t.0 == "sensor").unwrap();
    assert_eq!(attr(sensor, "type"), Some("perspective"));
    let fov = tags.iter().find(|t| t.0 == "float" && attr(t, "name") == Some("fov")).unwrap();
    let fov: f32 = attr(fov, "value").unwrap().parse().unwrap();
    assert!((fov - 35.0).abs() < 0.05, "fov {fov}");
}

#[test]
fn automatic_repeats_cover_a_rotated_view() {
    let mut params = twill();
    params.scene.camera.rotation_deg = 30.0;
    params.scene.camera.tiles = 3.0;
    params.scene.camera.offset = [0.3, -0.2];
    params.scene.width = 160;
    params.scene.height = 96;
    let (reps, origin, clamped) = woven::export::view_repeats(&params);
    assert!(!clamped);
    let set = YarnSet::new(&params.cloth.pattern, params.cloth.r_e, params.cloth.r_a);
    let cam = woven::render::camera::Camera::new(&params.scene.camera, 160, 96, set.tile_x, set.tile_y, set.z_max());
    for (px, py) in [(0.0, 0.0), (160.0, 0.0), (0.0, 96.0), (160.0, 96.0), (80.0, 48.0)] {
        let (o, d) = cam.ray(px, py);
        let p = o + d * (-o.z / d.z);
        let (u, v) = (p.x / set.tile_x, p.y / set.tile_y);
        assert!(u >= origin[0] as f32 && u <= (origin[0] + reps[0] as i32) as f32, "x {u} outside {origin:?}+{reps:?}");
        assert!(v >= origin[1] as f32 && v <= (origin[1] + reps[1] as i32) as f32, "y {v} outside {origin:?}+{reps:?}");
    }
    // Not wastefully large either: the rotated 3×1.8-repeat frame fits in 5×5.
    assert!(reps[0] <= 5 && reps[1] <= 5, "{reps:?}");
}

#[test]
fn export_refuses_bad_options_and_cli_works() {
    let params = twill();
    let dir = tempfile::tempdir().unwrap();
    let bad = |o: ExportOptions| export(&params, dir.path(), &o).unwrap_err().to_string();
    assert!(bad(ExportOptions { repeats: Some([0, 1]), ..Default::default() }).contains("repeats"));
    assert!(bad(ExportOptions { samples_per_cell: 1, ..Default::default() }).contains("samples per cell"));
    assert!(bad(ExportOptions { ring: 2, ..Default::default() }).contains("ring"));

    // The command line (the clap types live in the binary): flags reach the library, bad repeat
    // counts are refused by the parser, a missing file is named.
    let pf = dir.path().join("p.json");
    params.save(&pf).unwrap();
    let out = dir.path().join("out");
    let woven = |args: &[&str]| {
        std::process::Command::new(env!("CARGO_BIN_EXE_woven")).args(args).env("RUST_BACKTRACE", "0").output().unwrap()
    };
    let (pfs, outs) = (pf.to_str().unwrap(), out.to_str().unwrap());
    let r = woven(&["export", pfs, "--out", outs, "--repeats", "2x1", "--samples-per-cell", "4", "--plies"]);
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    assert!(String::from_utf8_lossy(&r.stdout).contains("exported 2x1 repeats"));
    for f in ["yarns.ply", "tubes.ply", "plies.ply", "curves_weft.txt", "curves_warp.txt", "scene.xml"] {
        assert!(out.join(f).is_file(), "{f}");
    }
    for bad in ["0", "2x"] {
        let r = woven(&["export", pfs, "--out", outs, "--repeats", bad]);
        assert!(!r.status.success() && String::from_utf8_lossy(&r.stderr).contains("--repeats"), "{bad}");
    }
    let r = woven(&["export", "/nonexistent/p.json", "--out", outs]);
    assert!(!r.status.success());
    let e = String::from_utf8_lossy(&r.stderr);
    assert!(e.contains("/nonexistent/p.json"), "{e}");
}

/// Loads the exported scene in Mitsuba 3 when its Python package is installed (it is not on CI).
#[test]
#[ignore]
fn mitsuba_loads_the_scene() {
    let ok = std::process::Command::new("python3").args(["-c", "import mitsuba"]).status().map(|s| s.success());
    if !matches!(ok, Ok(true)) {
        eprintln!("mitsuba is not installed; skipping");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    export(&twill(), dir.path(), &ExportOptions { repeats: Some([1, 1]), ..Default::default() }).unwrap();
    let script = "import mitsuba as mi, sys\nmi.set_variant('scalar_rgb')\ns = mi.load_file(sys.argv[1])\n\
                  img = mi.render(s, spp=4)\nprint(img.shape)";
    let st = std::process::Command::new("python3")
        .args(["-c", script, dir.path().join("scene.xml").to_str().unwrap()])
        .status()
        .unwrap();
    assert!(st.success());
}

/// A fitted shape (deep crossings, flattened yarns) is exported as the renderer builds it: every
/// tube vertex lies on the renderer's elliptical surface (at the radius once mapped into the
/// stretched space where the tubes are round), the curves' heights follow the crossing depth, and
/// the Mitsuba scene uses the mesh because its curves are round.
#[test]
fn export_keeps_the_fitted_yarn_shape() {
    let mut params = twill();
    params.cloth.shape = YarnShape { crossing: 0.45, aspect: 0.6, ..Default::default() };
    let set = YarnSet::with_shape(&params.cloth.pattern, params.cloth.r_e, params.cloth.r_a, params.cloth.shape);
    let dir = tempfile::tempdir().unwrap();
    let s = export(&params, dir.path(), &ExportOptions { repeats: Some([1, 1]), ..Default::default() }).unwrap();
    let (verts, _) = read_mesh(&dir.path().join("tubes.ply"));
    assert_eq!(verts.len(), s.tube_vertices);
    let mut worst = 0.0f32;
    let mut top = f32::MIN;
    for (p, k) in verts.iter().step_by(5) {
        let y = &set.yarns[*k as usize];
        let d = dist_to_yarn(&set, *k as usize, y.to_round(*p));
        if d > 1e-3 {
            worst = worst.max((d - y.radius).abs() / y.radius);
        }
        top = top.max(p.z);
    }
    assert!(worst < 0.02, "tube vertex {worst} of a radius off the renderer's flattened tube");
    // World top of the cloth: aspect × (crossing height + radius), well below the round default.
    let expect_top = 0.6 * (set.h + params.cloth.r_e.max(params.cloth.r_a));
    assert!((top - expect_top).abs() < 0.05 * expect_top, "top {top} vs {expect_top}");
    let round = YarnSet::new(&params.cloth.pattern, params.cloth.r_e, params.cloth.r_a);
    assert!(top < 0.7 * round.z_max(), "flattened cloth as high as the round one: {top} vs {}", round.z_max());
    // Curve control heights are the world heights: at most aspect × crossing height.
    let h_world = 0.6 * set.h;
    for c in read_curves(&dir.path().join("curves_weft.txt")) {
        assert!(c.iter().all(|p| p[2].abs() <= h_world * 1.6 + 1e-3), "control heights beyond the crossing depth");
    }
    let xml = std::fs::read_to_string(dir.path().join("scene.xml")).unwrap();
    assert!(xml.contains("<shape type=\"ply\">") && !xml.contains("<shape type=\"bsplinecurve\">"), "{xml}");
    // The default shape still exports curves.
    let dir2 = tempfile::tempdir().unwrap();
    export(&twill(), dir2.path(), &ExportOptions { repeats: Some([1, 1]), ..Default::default() }).unwrap();
    let xml2 = std::fs::read_to_string(dir2.path().join("scene.xml")).unwrap();
    assert!(xml2.contains("<shape type=\"bsplinecurve\">"));
}
