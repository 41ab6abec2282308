//! Tests of the synthetic training-set generator (`woven::datagen`): determinism across thread
//! counts and shards, interruption and resume, label round trip, recipe validation.

use sha2::{Digest, Sha256};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use woven::datagen::generate::{image_path, label_path};
use woven::datagen::{generate, GenerateOptions, Interrupted, Label, Manifest, Recipe};
use woven::progress::NoProgress;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn default_text() -> String {
    std::fs::read_to_string(repo().join("datagen/recipe.toml")).expect("datagen/recipe.toml")
}

/// The default recipe shrunk: 10 images of 32 px, 1 spp.
fn tiny() -> Recipe {
    let mut r = Recipe::from_str(&default_text()).unwrap();
    r.count = 10;
    r.image.size = 32;
    r.image.spp = 1;
    r.seed = 7;
    r
}

fn opts(dir: &Path, threads: usize) -> GenerateOptions {
    let mut o = GenerateOptions::new(dir, tiny());
    o.threads = Some(threads);
    o
}

/// Relative path → SHA-256 of every file under `dir` except the run log.
fn hashes(dir: &Path) -> BTreeMap<String, String> {
    fn walk(base: &Path, d: &Path, out: &mut BTreeMap<String, String>) {
        for e in std::fs::read_dir(d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(base, &p, out);
            } else {
                let rel = p.strip_prefix(base).unwrap().to_string_lossy().to_string();
                // The run log and the shard manifests record how the set was made, not what it is.
                if rel != "runs.jsonl" && !rel.starts_with("shards") {
                    let h: String =
                        Sha256::digest(std::fs::read(&p).unwrap()).iter().map(|b| format!("{b:02x}")).collect();
                    out.insert(rel, h);
                }
            }
        }
    }
    let mut m = BTreeMap::new();
    walk(dir, dir, &mut m);
    m
}

fn reference() -> (tempfile::TempDir, BTreeMap<String, String>) {
    let d = tempfile::tempdir().unwrap();
    let s = generate(&opts(d.path(), 1), &NoProgress).unwrap();
    assert_eq!((s.rendered, s.skipped, s.present), (10, 0, 10));
    assert!(s.complete);
    let h = hashes(d.path());
    (d, h)
}

#[test]
fn default_recipe_file_is_valid_and_matches_the_built_in_default() {
    let r = Recipe::load(&repo().join("datagen/recipe.toml")).unwrap();
    assert_eq!(r.count, 2000);
    let d = Recipe::default();
    for i in 0..40 {
        assert_eq!(r.sample(i, 3).unwrap(), d.sample(i, 3).unwrap(), "sample {i}");
    }
    let classes = r.classes();
    // No two classes are the same fabric; every preset and its rotation have a class.
    let pats: Vec<_> = classes.iter().filter_map(|c| c.pattern.clone()).collect();
    for (a, p) in pats.iter().enumerate() {
        for q in &pats[a + 1..] {
            assert!(!p.equivalent(q), "{p} ~ {q}");
        }
    }
    for name in woven::pattern::PRESETS {
        let p = woven::WeavePattern::preset(name).unwrap();
        assert!(pats.iter().any(|q| q.equivalent(&p)), "{name}");
        assert!(pats.iter().any(|q| q.equivalent(&p.rotated90())), "{name} rotated");
    }
    assert!(!classes.iter().any(|c| c.name == "plain_rot90"), "plain rotated is plain");
    assert_eq!(classes.last().unwrap().name, "random");
    assert!(classes.iter().enumerate().all(|(k, c)| c.id == k));
}

#[test]
fn samples_are_deterministic_valid_and_follow_the_recipe() {
    let r = Recipe::default();
    let n = 400;
    let mut random = 0;
    for i in 0..n {
        let s = r.sample(i, 11).unwrap();
        assert_eq!(s, r.sample(i, 11).unwrap());
        assert_ne!(s.cloth, r.sample(i, 12).unwrap().cloth, "seed must matter");
        s.cloth.validate().unwrap();
        s.scene.validate().unwrap();
        assert_eq!((s.scene.width, s.scene.height, s.scene.spp, s.px_per_cell), (64, 64, 4, 8));
        let cam = &s.scene.camera;
        assert_eq!((cam.projection, cam.tilt_deg), (woven::scene::Projection::Orthographic, 0.0), "the fit's view");
        assert!(cam.rotation_deg.abs() <= 2.0 && (0.0..=0.8).contains(&s.noise.blur_px));
        // 8 cells across at 8 px per cell, whatever the repeat.
        assert!((cam.tiles * s.cloth.pattern.n_a() as f32 - 8.0).abs() < 1e-4, "{}", cam.tiles);
        let view = s.view_cells();
        assert_eq!((view.len(), view[0].len()), (8, 8));
        // Every pattern cell of a repeat of at most 8 cells a side is in the view.
        let n = s.cloth.pattern.n_e() * s.cloth.pattern.n_a();
        let mut seen = vec![false; n];
        view.iter().flatten().for_each(|&c| seen[c] = true);
        assert!(seen.iter().all(|&x| x), "a pattern cell is missing from the view of sample {i}");
        let c = &r.classes()[s.class_id];
        assert_eq!(c.name, s.class_name);
        match &c.pattern {
            Some(p) => assert_eq!(p, &s.cloth.pattern),
            None => {
                random += 1;
                let p = &s.cloth.pattern;
                assert!(p.n_e() <= 8 && p.n_a() <= 8 && !p.has_unbound_yarn(), "{p}");
                assert!(r.classes().iter().filter_map(|c| c.pattern.as_ref()).all(|q| !q.equivalent(p)), "{p}");
            }
        }
    }
    let share = random as f64 / n as f64;
    assert!((0.13..0.27).contains(&share), "random share {share}");
}

/// The view's cell map against the renderer: with red wefts and blue warps (touching yarns, no
/// specular, front light only), the centre of each grid cell shows the yarn that
/// `pattern[i][j]` puts on top, for views with random shift, sub-cell phase and rotation.
#[test]
fn view_cells_match_the_rendered_crossings() {
    use woven::render::{render, RenderOptions};
    let r = Recipe::default();
    let (mut right, mut total) = (0, 0);
    for i in 0..6 {
        let s = r.sample(i, 5).unwrap();
        let mut cloth = s.cloth.clone();
        (cloth.r_e, cloth.r_a) = (4.5, 4.5);
        let a = &mut cloth.appearance;
        (a.r_s, a.t_s, a.t_s_y, a.m_r) = ([0.0; 3], [0.0; 3], [0.0; 3], 0.8);
        (a.r_b_e, a.r_b_a, a.s_b_e, a.s_b_a) = ([0.9, 0.05, 0.05], [0.05, 0.05, 0.9], [0.0; 3], [0.0; 3]);
        let mut scene = s.scene.clone();
        scene.lights = woven::scene::LightRig::named("front").unwrap();
        scene.spp = 4;
        let img = render(&cloth, &scene, &RenderOptions { threads: Some(2), ..Default::default() });
        let p = &cloth.pattern;
        for (row, cells) in s.view_cells().iter().enumerate() {
            for (col, &c) in cells.iter().enumerate() {
                let (pi, pj) = (c / p.n_a(), c % p.n_a());
                let (x0, y0) = (col as u32 * 8 + 3, row as u32 * 8 + 3);
                let mut rgb = [0.0f32; 3];
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let v = img.get(x0 + dx, y0 + dy);
                    (0..3).for_each(|k| rgb[k] += v[k]);
                }
                let weft_on_top = rgb[0] > rgb[2];
                right += (weft_on_top == p.get(pi, pj)) as usize;
                total += 1;
            }
        }
    }
    // Cells whose centre lands within a pixel of a yarn edge may show the wrong yarn after
    // rotation and phase; the map itself must be right almost everywhere.
    assert!(right as f64 >= 0.97 * total as f64, "{right} of {total} cells show the mapped yarn on top");
}

#[test]
fn recipe_errors_name_the_field() {
    let text = default_text();
    let cases: &[(&str, &str, &str)] = &[
        ("count = 2000", "count = 0", "`count`"),
        ("m_r = { range = [0.2, 0.8] }", "m_r = { range = [0.1, 0.8] }", "priors.m_r.range"),
        ("r_s = { range = [0.0, 1.0] }", "r_s = { range = [0.0, 1.0], dist = \"loguniform\" }", "priors.r_s.dist"),
        ("n_p = { dist = \"uniform\" }", "n_p = { range = [1.5, 3] }", "priors.n_p.range"),
        ("g_f = { range = [0.0, 1.0] }", "g_f = { range = [0.0, 1.0] }\ng_x = {}", "g_x"),
        ("\"basket2\"", "\"basket3\"", "patterns.presets[1]"),
        ("blur_px = { range = [0.0, 0.8] }", "blur_px = { range = [0.8, 0.0] }", "camera.blur_px.range"),
        ("phase_cells = 0.25", "phase_cells = 0.5", "camera.phase_cells"),
        ("\"both\"]", "\"sideways\"]", "lights.rigs[3]"),
        ("px_per_cell = 8", "px_per_cell = 7", "image.size"),
        ("random_share = 0.2", "random_share = -0.1", "patterns.random_share"),
        ("\nsize = 64", "\nsize = 4", "image.size"),
        ("range = [0.6, 1.6]\ndist = \"loguniform\"", "range = [0.6, 1.6]\ndist = \"gaussian\"", "gaussian"),
        ("shot_gain = { range = [0.0, 0.002] }", "shot_gain = { range = [0.0, 2.0] }", "noise.shot_gain.range"),
        ("spp = 4", "spp = 4\nsamples = 3", "samples"),
    ];
    for (from, to, want) in cases {
        assert!(text.contains(from), "recipe text lacks {from}");
        let bad = text.replacen(from, to, 1);
        let e = match Recipe::from_str(&bad) {
            Ok(_) => panic!("{to}: accepted"),
            Err(e) => format!("{e:#}"),
        };
        assert!(e.contains(want), "{to}: error `{e}` does not name {want}");
    }
}

#[test]
fn same_files_whatever_the_thread_count() {
    let (a, ha) = reference();
    let b = tempfile::tempdir().unwrap();
    generate(&opts(b.path(), 2), &NoProgress).unwrap();
    let hb = hashes(b.path());
    assert_eq!(ha, hb);
    // Everything is there: 10 images, 10 labels, the aggregates.
    assert_eq!(ha.keys().filter(|k| k.starts_with("images/") && k.ends_with(".png")).count(), 10);
    assert_eq!(ha.keys().filter(|k| k.starts_with("labels/")).count(), 10);
    for f in ["labels.jsonl", "manifest.json", "preview.png", "dataset.json"] {
        assert!(ha.contains_key(f), "{f} missing");
    }
    // Images differ from each other (the samples really vary).
    let imgs: std::collections::BTreeSet<_> =
        ha.iter().filter(|(k, _)| k.starts_with("images/")).map(|(_, v)| v.clone()).collect();
    assert_eq!(imgs.len(), 10);
    // A different seed gives different images.
    let c = tempfile::tempdir().unwrap();
    let mut o = opts(c.path(), 2);
    o.seed = Some(8);
    generate(&o, &NoProgress).unwrap();
    assert_ne!(hashes(c.path()).get("images/000000.png"), ha.get("images/000000.png"));
    drop(a);
}

#[test]
fn union_of_shards_equals_the_full_set() {
    let (_a, ha) = reference();
    // Two shards into one directory.
    let d = tempfile::tempdir().unwrap();
    let mut o = opts(d.path(), 2);
    o.shard = (1, 2);
    let s = generate(&o, &NoProgress).unwrap();
    assert_eq!((s.rendered, s.present, s.complete), (5, 5, false));
    assert!(!d.path().join("labels.jsonl").exists(), "aggregates must wait for the whole set");
    assert!(label_path(d.path(), 1).exists() && !label_path(d.path(), 0).exists());
    o.shard = (0, 2);
    let s = generate(&o, &NoProgress).unwrap();
    assert_eq!((s.rendered, s.present, s.complete), (5, 10, true));
    assert_eq!(hashes(d.path()), ha);

    // Two shards into two directories, merged by copying, then finalised by a plain rerun.
    let e = tempfile::tempdir().unwrap();
    let f = tempfile::tempdir().unwrap();
    let mut o = opts(e.path(), 1);
    o.shard = (0, 2);
    generate(&o, &NoProgress).unwrap();
    let mut o = opts(f.path(), 1);
    o.shard = (1, 2);
    generate(&o, &NoProgress).unwrap();
    for sub in ["images", "labels"] {
        for ent in std::fs::read_dir(f.path().join(sub)).unwrap().flatten() {
            std::fs::copy(ent.path(), e.path().join(sub).join(ent.file_name())).unwrap();
        }
    }
    let s = generate(&opts(e.path(), 2), &NoProgress).unwrap();
    assert_eq!((s.rendered, s.skipped, s.complete), (0, 10, true));
    assert_eq!(hashes(e.path()), ha);
}

#[test]
fn interrupted_run_resumes_to_the_same_files() {
    let (_a, ha) = reference();
    let d = tempfile::tempdir().unwrap();
    let mut o = opts(d.path(), 1);
    o.stop_after = Some(4);
    let e = generate(&o, &NoProgress).unwrap_err();
    let i = e.downcast_ref::<Interrupted>().expect("an Interrupted error");
    assert_eq!((i.rendered, i.remaining), (4, 6));
    let labels = (0..10).filter(|&k| label_path(d.path(), k).exists()).count();
    assert_eq!(labels, 4);
    assert!(!d.path().join("labels.jsonl").exists() && !d.path().join("manifest.json").exists());

    // Simulate a crash: a stale temporary file, a lost label, a truncated image.
    let done: Vec<usize> = (0..10).filter(|&k| label_path(d.path(), k).exists()).collect();
    std::fs::remove_file(label_path(d.path(), done[0])).unwrap();
    let png = image_path(d.path(), done[1]);
    let bytes = std::fs::read(&png).unwrap();
    std::fs::write(&png, &bytes[..bytes.len() / 2]).unwrap();
    let stale = d.path().join("images").join(".000009.png.4000000000.tmp.png");
    std::fs::write(&stale, b"half an image").unwrap();
    // A cancelled run renders nothing and leaves the directory as it was.
    let mut o = opts(d.path(), 2);
    o.cancel = Some(Arc::new(AtomicBool::new(true)));
    let e = generate(&o, &NoProgress).unwrap_err();
    assert_eq!(e.downcast_ref::<Interrupted>().unwrap().rendered, 0);

    let s = generate(&opts(d.path(), 2), &NoProgress).unwrap();
    assert_eq!((s.rendered, s.skipped, s.complete), (8, 2, true));
    assert!(!stale.exists(), "stale temporary file must be removed");
    assert_eq!(hashes(d.path()), ha);
    // A further rerun renders nothing and changes nothing.
    let s = generate(&opts(d.path(), 2), &NoProgress).unwrap();
    assert_eq!((s.rendered, s.skipped), (0, 10));
    assert_eq!(hashes(d.path()), ha);
}

#[test]
fn labels_round_trip_to_the_samples() {
    let d = tempfile::tempdir().unwrap();
    generate(&opts(d.path(), 2), &NoProgress).unwrap();
    let r = tiny();
    let text = std::fs::read_to_string(d.path().join("labels.jsonl")).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 10);
    let manifest: Manifest = serde_json::from_slice(&std::fs::read(d.path().join("manifest.json")).unwrap()).unwrap();
    assert_eq!(manifest.target_names.len(), 34);
    assert_eq!(manifest.count, 10);
    assert_eq!(manifest.class_counts.iter().sum::<usize>(), 10);
    assert_eq!(manifest.recipe, r);
    assert_eq!(manifest.recipe_sha256, woven::datagen::generate::sha256_hex(r.to_toml().as_bytes()));
    assert_eq!(Recipe::from_str(&r.to_toml()).unwrap(), r, "canonical TOML round trip");
    for (i, line) in lines.iter().enumerate() {
        let l: Label = serde_json::from_str(line).unwrap();
        let s = r.sample(i, 7).unwrap();
        assert_eq!(l.index, i);
        assert_eq!(l.cloth, s.cloth);
        assert_eq!(l.scene, s.scene);
        assert_eq!(l.noise, s.noise);
        assert_eq!((l.class_id, l.class_name.as_str()), (s.class_id, s.class_name.as_str()));
        assert_eq!(l.pattern.join("/"), s.cloth.pattern.to_string());
        assert_eq!(l.targets.len(), 34);
        let app = s.cloth.appearance.to_vec();
        for (k, rg) in woven::params::APPEARANCE_RANGES.iter().enumerate() {
            let back = rg.min + l.targets[k] * (rg.max - rg.min);
            assert!((back - app[k]).abs() < 1e-5, "{}: {back} vs {}", rg.name, app[k]);
        }
        assert!((1.0 + l.targets[32] * 4.0 - s.cloth.r_e).abs() < 1e-5);
        assert!((1.0 + l.targets[30] * 6.0 - s.cloth.n_p as f32).abs() < 1e-5);
        assert!(l.targets.iter().all(|t| (0.0..=1.0).contains(t)));
        let img = image::open(d.path().join(&l.image)).unwrap();
        assert_eq!((img.width(), img.height()), (32, 32));
    }
    let sheet = image::open(d.path().join("preview.png")).unwrap();
    assert!(sheet.width() >= 8 * 64 && sheet.height() >= 2 * 64, "{}x{}", sheet.width(), sheet.height());
}

#[test]
fn another_recipe_is_refused_in_the_same_directory() {
    let d = tempfile::tempdir().unwrap();
    let mut o = opts(d.path(), 2);
    o.count = Some(2);
    generate(&o, &NoProgress).unwrap();
    o.seed = Some(99);
    let e = format!("{:#}", generate(&o, &NoProgress).unwrap_err());
    assert!(e.contains("another recipe or seed") && e.contains("seed is"), "{e}");
    // " px" (the unit, after a number), not "px": a random temp folder name may hold "px".
    assert!(!e.contains(" px"), "only the seed differs: {e}");
    // Another image size is named as such, not blamed on the seed.
    o.seed = None;
    o.size = Some(48);
    let e = format!("{:#}", generate(&o, &NoProgress).unwrap_err());
    assert!(e.contains("images are 32 px (this run: 48 px; --size)"), "{e}");
    assert!(!e.contains("seed is"), "{e}");
    // A larger count extends the same dataset.
    let mut o = opts(d.path(), 2);
    o.count = Some(3);
    let s = generate(&o, &NoProgress).unwrap();
    assert_eq!((s.rendered, s.skipped), (1, 2));
}

/// Speed and Monte-Carlo noise of the default recipe (run by hand:
/// `cargo test --release --test datagen -- --ignored --nocapture measure`).
#[test]
#[ignore]
fn measure_speed_and_noise() {
    let n: usize = std::env::var("WOVEN_MEASURE_COUNT").ok().and_then(|s| s.parse().ok()).unwrap_or(40);
    let threads: usize = std::env::var("WOVEN_MEASURE_THREADS").ok().and_then(|s| s.parse().ok()).unwrap_or(2);
    let d = tempfile::tempdir().unwrap();
    let out = std::env::var("WOVEN_MEASURE_OUT").map(PathBuf::from).unwrap_or_else(|_| d.path().to_path_buf());
    let mut o = GenerateOptions::new(&out, Recipe::default());
    o.count = Some(n);
    o.threads = Some(threads);
    let s = generate(&o, &NoProgress).unwrap();
    println!(
        "speed: {n} images of 128 px, spp 4, {threads} threads: {:.2} images/s (wall {:.1} s) -> 2000 images in {:.0} s",
        s.images_per_s,
        s.wall_s,
        2000.0 / s.images_per_s
    );
    // Monte-Carlo noise at 4 spp vs a 64-spp reference, before and after the 2x2 downsample.
    let spp: u32 = std::env::var("WOVEN_MEASURE_SPP").ok().and_then(|s| s.parse().ok()).unwrap_or(4);
    let r = Recipe::default();
    let (mut e128, mut e64, mut m, mut srgb_mae) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    let k = 4;
    for i in 0..k {
        let s = r.sample(i, 1).unwrap();
        let ro = woven::render::RenderOptions { threads: Some(threads), ..Default::default() };
        let mut low_scene = s.scene.clone();
        low_scene.spp = spp;
        let low = woven::render::render(&s.cloth, &low_scene, &ro);
        let mut hi_scene = s.scene.clone();
        hi_scene.spp = 64;
        hi_scene.seed ^= 0x55;
        let hi = woven::render::render(&s.cloth, &hi_scene, &ro);
        let (w, h) = (low.width, low.height);
        let down = |img: &woven::Image, x: u32, y: u32, c: usize| {
            (img.get(2 * x, 2 * y)[c]
                + img.get(2 * x + 1, 2 * y)[c]
                + img.get(2 * x, 2 * y + 1)[c]
                + img.get(2 * x + 1, 2 * y + 1)[c]) as f64
                / 4.0
        };
        let (mut a, mut b, mut mm) = (0.0, 0.0, 0.0);
        let (l8, h8) = (low.to_srgb8(), hi.to_srgb8());
        let mae8: f64 = l8.as_raw().iter().zip(h8.as_raw()).map(|(p, q)| (*p as f64 - *q as f64).abs()).sum::<f64>()
            / l8.as_raw().len() as f64;
        srgb_mae += mae8 / k as f64;
        for y in 0..h {
            for x in 0..w {
                for c in 0..3 {
                    a += ((low.get(x, y)[c] - hi.get(x, y)[c]) as f64).powi(2);
                    mm += hi.get(x, y)[c] as f64;
                }
            }
        }
        for y in 0..h / 2 {
            for x in 0..w / 2 {
                for c in 0..3 {
                    b += (down(&low, x, y, c) - down(&hi, x, y, c)).powi(2);
                }
            }
        }
        let np = (w * h * 3) as f64;
        e128 += (a / np).sqrt();
        e64 += (b / (np / 4.0)).sqrt();
        m += mm / np;
    }
    let (e128, e64, m) = (e128 / k as f64, e64 / k as f64, m / k as f64);
    println!("noise: mean |{spp} spp - 64 spp| in 8-bit sRGB levels at 128 px: {srgb_mae:.2}");
    println!(
        "noise: mean linear value {m:.4}; RMS({spp} spp - 64 spp) {e128:.4} ({:.1}% of mean) at 128 px, {e64:.4} ({:.1}%) after 2x2 downsample to 64 px",
        100.0 * e128 / m,
        100.0 * e64 / m
    );
}

/// Without `--recipe`, `woven generate` uses the built-in copy of `datagen/recipe.toml`, from any
/// folder (it used to look for that path relative to the working directory and fail outside a
/// checkout): the manifest names the same recipe as the repository's file.
#[test]
fn the_built_in_recipe_is_the_repository_file_and_needs_no_checkout() {
    let file = Recipe::from_str(&default_text()).unwrap();
    assert_eq!(Recipe::embedded().to_toml(), file.to_toml());
    let d = tempfile::tempdir().unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_woven"))
        .args(["generate", "--count", "2", "--size", "16", "--threads", "1", "--out", "set"])
        .current_dir(d.path())
        .env("RUST_BACKTRACE", "0")
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let m: Manifest = serde_json::from_slice(&std::fs::read(d.path().join("set/manifest.json")).unwrap()).unwrap();
    assert_eq!((m.count, m.image_size), (2, 16));
    let with_file = tempfile::tempdir().unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_woven"))
        .args(["generate", "--count", "2", "--size", "16", "--threads", "1", "--out", "set", "--recipe"])
        .arg(repo().join("datagen/recipe.toml"))
        .current_dir(with_file.path())
        .output()
        .unwrap();
    assert!(out.status.success());
    assert_eq!(
        std::fs::read(d.path().join("set/manifest.json")).unwrap(),
        std::fs::read(with_file.path().join("set/manifest.json")).unwrap(),
        "the built-in recipe and the file make the same manifest"
    );
}

#[test]
fn command_entry_point() {
    let d = tempfile::tempdir().unwrap();
    let recipe = d.path().join("recipe.toml");
    std::fs::write(&recipe, tiny().to_toml()).unwrap();
    let set = d.path().join("set");
    let run = || {
        std::process::Command::new(env!("CARGO_BIN_EXE_woven"))
            .args(["generate", "--count", "3", "--size", "24", "--exr", "--threads", "2", "--out"])
            .arg(&set)
            .arg("--recipe")
            .arg(&recipe)
            .env("RUST_BACKTRACE", "0")
            .output()
            .unwrap()
    };
    let out = run();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let m: Manifest = serde_json::from_slice(&std::fs::read(set.join("manifest.json")).unwrap()).unwrap();
    assert_eq!((m.count, m.image_size, m.exr), (3, 24, true));
    let exr = woven::Image::load(&set.join("images/000002.exr"), 8).unwrap();
    assert_eq!(exr.width, 24);
    // A bad recipe file fails with the field named.
    std::fs::write(&recipe, tiny().to_toml().replace("random_share = 0.2", "random_share = 2.0")).unwrap();
    let out = run();
    assert!(!out.status.success());
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(e.contains("patterns.random_share"), "{e}");
}

/// Render shard `i/K` of [`tiny`] into its own folder (as one cluster task would).
fn shard_dir(i: usize, k: usize) -> tempfile::TempDir {
    let d = tempfile::tempdir().unwrap();
    let mut o = opts(d.path(), 1);
    o.shard = (i, k);
    generate(&o, &NoProgress).unwrap();
    d
}

#[test]
fn merged_shard_folders_equal_one_run_and_bad_shards_are_refused() {
    use woven::datagen::merge;
    let (_a, ha) = reference();
    let parts: Vec<tempfile::TempDir> = (0..3).map(|i| shard_dir(i, 3)).collect();
    let dirs: Vec<PathBuf> = parts.iter().map(|d| d.path().to_path_buf()).collect();
    assert!(dirs[1].join("shards/shard-1-of-3.json").is_file());
    let out = tempfile::tempdir().unwrap();
    let m = out.path().join("train");
    let s = merge(&dirs, &m, &NoProgress).unwrap();
    assert_eq!((s.count, s.shards, s.copied), (10, 3, 20));
    assert_eq!(hashes(&m), ha, "the merge must equal a one-machine run byte for byte");
    // Merging again (a retried merge step) copies nothing; a duplicated identical shard is fine.
    let twice = [dirs.clone(), vec![dirs[0].clone()]].concat();
    assert_eq!(merge(&twice, &m, &NoProgress).unwrap().copied, 0);

    // A missing shard is named with the command that makes it.
    let e = format!("{:#}", merge(&dirs[..2], &out.path().join("x"), &NoProgress).unwrap_err());
    assert!(e.contains("shards missing: 2/3") && e.contains("--shard I/3"), "{e}");
    // A folder that is not a finished shard.
    let e = format!("{:#}", merge(&[out.path().to_path_buf()], &out.path().join("y"), &NoProgress).unwrap_err());
    assert!(e.contains("no shard manifest"), "{e}");
    // Shards of another split, and of another dataset.
    let other_k = shard_dir(0, 2);
    let e = format!(
        "{:#}",
        merge(&[dirs[0].clone(), other_k.path().into()], &out.path().join("z"), &NoProgress).unwrap_err()
    );
    assert!(e.contains("split into 3"), "{e}");
    let other = tempfile::tempdir().unwrap();
    let mut o = opts(other.path(), 1);
    o.seed = Some(8);
    o.shard = (2, 3);
    generate(&o, &NoProgress).unwrap();
    let mixed = vec![dirs[0].clone(), dirs[1].clone(), other.path().into()];
    let e = format!("{:#}", merge(&mixed, &out.path().join("w"), &NoProgress).unwrap_err());
    assert!(e.contains("different datasets"), "{e}");
    // Into a folder that holds another dataset.
    let e = format!("{:#}", merge(&dirs, other.path(), &NoProgress).unwrap_err());
    assert!(e.contains("holds another dataset"), "{e}");
    // A file changed after its shard finished (a truncated copy) is caught before it is used.
    let png = image_path(&dirs[1], 4);
    let bytes = std::fs::read(&png).unwrap();
    std::fs::write(&png, &bytes[..bytes.len() / 2]).unwrap();
    let fresh = out.path().join("v");
    let e = format!("{:#}", merge(&dirs, &fresh, &NoProgress).unwrap_err());
    assert!(e.contains("000004.png") && e.contains("does not match its shard manifest"), "{e}");
    assert!(!fresh.join("manifest.json").exists(), "no manifest for an incomplete merge");
}

/// `datagen/cluster/shard.sh` as a Slurm array task and as a Kubernetes Indexed Job pod: the
/// scheduler's index is the shard index; K processes run at once; `woven merge` of their folders
/// equals a one-machine run.
#[test]
fn cluster_array_tasks_map_their_index_to_the_shard_and_merge_to_one_run() {
    let (_a, ha) = reference();
    let work = tempfile::tempdir().unwrap();
    let recipe = work.path().join("tiny.toml");
    std::fs::write(&recipe, tiny().to_toml()).unwrap();
    let script = repo().join("datagen/cluster/shard.sh");
    let bin = env!("CARGO_BIN_EXE_woven");
    let k = 3;
    for (scheduler, index_var, count_var) in
        [("slurm", "SLURM_ARRAY_TASK_ID", "SLURM_ARRAY_TASK_COUNT"), ("k8s", "JOB_COMPLETION_INDEX", "WOVEN_SHARDS")]
    {
        let data = work.path().join(scheduler);
        let tasks: Vec<std::process::Child> = (0..k)
            .map(|i| {
                std::process::Command::new("bash")
                    .arg(&script)
                    .args(["--recipe", recipe.to_str().unwrap(), "--threads", "1"])
                    .env_remove("WOVEN_SHARD_INDEX")
                    .env_remove("WOVEN_SHARDS")
                    .env_remove("SLURM_ARRAY_TASK_ID")
                    .env_remove("JOB_COMPLETION_INDEX")
                    .env(index_var, i.to_string())
                    .env(count_var, k.to_string())
                    .env("WOVEN", bin)
                    .env("WOVEN_DATA", &data)
                    .stderr(std::process::Stdio::null())
                    .spawn()
                    .unwrap()
            })
            .collect();
        for mut t in tasks {
            assert!(t.wait().unwrap().success(), "{scheduler} task failed");
        }
        for i in 0..k {
            assert!(data.join(format!("shard-{i}/shards/shard-{i}-of-{k}.json")).is_file(), "{scheduler} shard {i}");
        }
        let out = work.path().join(format!("{scheduler}-train"));
        let st = std::process::Command::new(bin)
            .arg("merge")
            .arg("--out")
            .arg(&out)
            .args((0..k).map(|i| data.join(format!("shard-{i}"))))
            .output()
            .unwrap();
        assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
        assert_eq!(hashes(&out), ha, "{scheduler}: merged set differs from a one-machine run");
    }
    // Without an index the script refuses to guess; an index past K is refused too.
    let run = |envs: &[(&str, &str)]| {
        let mut c = std::process::Command::new("bash");
        c.arg(&script).env("WOVEN", bin).env("WOVEN_DATA", work.path());
        for v in [
            "WOVEN_SHARD_INDEX",
            "WOVEN_SHARDS",
            "SLURM_ARRAY_TASK_ID",
            "SLURM_ARRAY_TASK_COUNT",
            "JOB_COMPLETION_INDEX",
        ] {
            c.env_remove(v);
        }
        c.envs(envs.iter().copied()).output().unwrap()
    };
    let o = run(&[]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("no shard index"));
    let o = run(&[("JOB_COMPLETION_INDEX", "3"), ("WOVEN_SHARDS", "3")]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("not in 0..3"));
    // The job files name the script and agree on K.
    let yaml = std::fs::read_to_string(repo().join("datagen/cluster/k8s-indexed-job.yaml")).unwrap();
    assert!(yaml.contains("completionMode: Indexed") && yaml.contains("shard.sh"));
    let completions = yaml.lines().find_map(|l| l.trim().strip_prefix("completions:")).unwrap().trim().to_string();
    assert!(yaml.contains(&format!("value: \"{completions}\"")), "WOVEN_SHARDS must equal completions");
    let sbatch = std::fs::read_to_string(repo().join("datagen/cluster/slurm.sbatch")).unwrap();
    assert!(sbatch.contains("#SBATCH --array=0-") && sbatch.contains("shard.sh"));
}
