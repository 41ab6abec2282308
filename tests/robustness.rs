//! Bad input to the `woven` binary outside the fit (issue 12, deliverable 7): each case fails with a
//! clear message and a non-zero exit — never a panic, an abort, a hang or a silent wrong result —
//! and leaves no partial output. Each test also runs the good neighbour of its bad input, so it
//! can fail.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

/// Run `woven args` with a time limit (a hang is a failure, not a stuck test run).
fn woven_in(dir: Option<&Path>, args: &[&str]) -> Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_woven"));
    cmd.args(args).env("RUST_BACKTRACE", "0").stdout(Stdio::piped()).stderr(Stdio::piped());
    if let Some(d) = dir {
        cmd.current_dir(d);
    }
    let mut child = cmd.spawn().expect("run woven");
    let start = Instant::now();
    loop {
        if child.try_wait().expect("wait").is_some() {
            break;
        }
        if start.elapsed() > Duration::from_secs(120) {
            child.kill().ok();
            child.wait().ok();
            panic!("woven {args:?} did not finish within 120 s (hang)");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let mut out = Vec::new();
    let mut err = Vec::new();
    child.stdout.take().expect("stdout").read_to_end(&mut out).ok();
    child.stderr.take().expect("stderr").read_to_end(&mut err).ok();
    Output { status: child.wait().expect("status"), stdout: out, stderr: err }
}

fn woven(args: &[&str]) -> Output {
    woven_in(None, args)
}

/// Stderr of a run that must fail cleanly.
fn fails(args: &[&str]) -> String {
    let out = woven(args);
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(!out.status.success(), "woven {args:?} should fail; stderr: {err}");
    assert!(!err.contains("panicked") && !err.contains("memory allocation"), "woven {args:?}: {err}");
    err
}

fn succeeds(args: &[&str]) -> Output {
    let out = woven(args);
    assert!(out.status.success(), "woven {args:?}: {}", String::from_utf8_lossy(&out.stderr));
    out
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// A parameter file of `preset` in `dir`.
fn param_file(dir: &Path, preset: &str) -> PathBuf {
    let out = succeeds(&["params", "--preset", preset]);
    let p = dir.join(format!("{preset}.json"));
    std::fs::write(&p, out.stdout).unwrap();
    p
}

/// A small render of a twill (a valid photo stand-in) as PNG.
fn twill_png(dir: &Path) -> PathBuf {
    let pf = param_file(dir, "twill22");
    let png = dir.join("twill.png");
    succeeds(&["render", "--params", s(&pf), "--out", s(&png), "--width", "96", "--height", "96", "--spp", "1"]);
    png
}

/// Patch the size a small tiled EXR declares to 100000×100000 (one tile of that size, so the file
/// stays consistent: one chunk, a few hundred bytes); decoding it would allocate 120 GB.
fn huge_exr(dir: &Path) -> PathBuf {
    let small = dir.join("small.exr");
    woven::Image::filled(8, 8, [0.5; 3]).save_exr(&small).unwrap();
    let mut b = std::fs::read(&small).unwrap();
    let mut patch = |name: &[u8], ty: &[u8], data: &[u8]| {
        let key = [name, b"\0", ty, b"\0"].concat();
        let at = b.windows(key.len()).position(|w| w == key.as_slice()).expect("attribute") + key.len() + 4;
        b[at..at + data.len()].copy_from_slice(data);
    };
    let window: Vec<u8> = [0i32, 0, 99_999, 99_999].iter().flat_map(|v| v.to_le_bytes()).collect();
    patch(b"dataWindow", b"box2i", &window);
    patch(b"displayWindow", b"box2i", &window);
    let tiles: Vec<u8> = [100_000u32.to_le_bytes(), 100_000u32.to_le_bytes()].concat();
    patch(b"tiles", b"tiledesc", &tiles);
    let p = dir.join("huge.exr");
    std::fs::write(&p, b).unwrap();
    p
}

#[test]
fn an_exr_declaring_ten_billion_pixels_is_refused_before_decoding() {
    let d = tempfile::tempdir().unwrap();
    let exr = huge_exr(d.path());
    let want = "declares 100000x100000 pixels";
    let e = fails(&["prep", s(&exr), "--out", s(&d.path().join("prep"))]);
    assert!(e.contains(want), "{e}");
    let e = fails(&["predict", s(&exr)]);
    assert!(e.contains(want), "{e}");
    let e = fails(&["fit", s(&exr), "--out", s(&d.path().join("fit"))]);
    assert!(e.contains(want), "{e}");
    // The unpatched file loads.
    assert_eq!(woven::Image::load(&d.path().join("small.exr"), 8).unwrap().width, 8);
}

#[test]
fn absurd_thread_counts_are_refused_with_a_hint() {
    let d = tempfile::tempdir().unwrap();
    let pf = param_file(d.path(), "plain");
    let png = d.path().join("a.png");
    let base = ["render", "--params", s(&pf), "--out", s(&png), "--width", "16", "--height", "16", "--spp", "1"];
    for bad in ["5000", "0", "-2"] {
        let e = fails(&[&base[..], &["--threads", bad]].concat());
        assert!(e.contains("threads must be a whole number from 1 to 256"), "{bad}: {e}");
    }
    assert!(!png.exists());
    succeeds(&[&base[..], &["--threads", "3"]].concat());
    assert!(png.is_file());
}

/// Without `--model`, `predict` reads with the model built into the binary (as the fit does), so
/// it works outside a checkout; a named file that is absent is still an error that says so.
#[test]
fn predict_uses_the_built_in_model_from_any_directory() {
    let d = tempfile::tempdir().unwrap();
    let png = twill_png(d.path());
    let out = woven_in(Some(d.path()), &["predict", s(&png), "--view", "--json"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(String::from_utf8_lossy(&out.stdout).contains("cell_logits"), "{err}");
    let out = woven_in(Some(d.path()), &["predict", s(&png), "--model", "models/pre_estimator.safetensors"]);
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("not found"));
}

#[test]
fn a_truncated_jpeg_is_refused() {
    let d = tempfile::tempdir().unwrap();
    let png = twill_png(d.path());
    let img = image::open(&png).unwrap().to_rgb8();
    let mut jpg = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut jpg), image::ImageFormat::Jpeg).unwrap();
    let whole = d.path().join("whole.jpg");
    std::fs::write(&whole, &jpg).unwrap();
    let cut = d.path().join("cut.jpg");
    std::fs::write(&cut, &jpg[..jpg.len() / 2]).unwrap();
    let e = fails(&["prep", s(&cut), "--out", s(&d.path().join("p"))]);
    assert!(e.contains("truncated JPEG"), "{e}");
    assert!(!d.path().join("p").exists(), "no output for a refused input");
    let e = fails(&["predict", s(&cut)]);
    assert!(e.contains("truncated JPEG") || e.contains("woven train"), "{e}");
    succeeds(&["prep", s(&whole), "--out", s(&d.path().join("q"))]);
}

#[test]
fn noise_is_not_prepared_as_a_weave() {
    let d = tempfile::tempdir().unwrap();
    // Grey xorshift noise that prep used to turn into a 2×5 yarn grid (period strength 0).
    let mut h = 0x2545_F491_4F6C_DD1Du64;
    let noise = image::RgbImage::from_fn(128, 96, |_, _| {
        h ^= h << 13;
        h ^= h >> 7;
        h ^= h << 17;
        let v = (h >> 56) as u8;
        image::Rgb([v, v, v])
    });
    let p = d.path().join("noise.png");
    noise.save(&p).unwrap();
    let e = fails(&["prep", s(&p), "--out", s(&d.path().join("n"))]);
    assert!(e.contains("no periodic yarn structure found") && e.contains("try "), "{e}");
    let e = fails(&["fit", s(&p), "--out", s(&d.path().join("f"))]);
    assert!(e.contains("no periodic yarn structure found"), "{e}");
    // A render of a real weave with a few repeats is prepared.
    let pf = param_file(d.path(), "twill22");
    let twill = d.path().join("t.png");
    succeeds(&["render", "--params", s(&pf), "--out", s(&twill), "--width", "192", "--height", "192", "--spp", "2"]);
    let out = succeeds(&["prep", s(&twill), "--out", s(&d.path().join("t"))]);
    assert!(String::from_utf8_lossy(&out.stdout).contains("n_e×n_a = 4×4"), "{}", String::from_utf8_lossy(&out.stdout));
}

#[test]
fn a_model_with_nan_weights_is_refused() {
    use woven::net::{NetSpec, OutputSpec};
    let d = tempfile::tempdir().unwrap();
    let mut spec = NetSpec::new(16, vec![OutputSpec::continuous("x", 0.0, 1.0)]);
    (spec.backbone, spec.px_per_cell) = (vec![4, 8], 4);
    spec.hidden = 8;
    let (vm, _) = woven::net::model::build(&spec, 1).unwrap();
    let good = d.path().join("good.safetensors");
    woven::net::train::save_model(&good, &vm, &spec, None).unwrap();
    // The same file with one tensor set to NaN (and no checksum, as a file written by another tool).
    let bytes = std::fs::read(&good).unwrap();
    let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
    let mut md = header.metadata().clone().unwrap();
    md.remove("woven.checksum");
    let mut tensors = st.tensors();
    tensors.sort_by(|a, b| a.0.cmp(&b.0));
    let nan: Vec<u8> = std::iter::repeat_n(f32::NAN.to_le_bytes(), tensors[0].1.data().len() / 4).flatten().collect();
    let first =
        safetensors::tensor::TensorView::new(tensors[0].1.dtype(), tensors[0].1.shape().to_vec(), &nan).unwrap();
    tensors[0].1 = first;
    let forged = safetensors::serialize(tensors.iter().map(|(n, t)| (n.as_str(), t)), Some(md)).unwrap();
    let bad = d.path().join("nan.safetensors");
    std::fs::write(&bad, forged).unwrap();
    let img = twill_png(d.path());
    let e = fails(&["predict", s(&img), "--model", s(&bad), "--json"]);
    assert!(e.contains("non-finite weight"), "{e}");
    let out = succeeds(&["predict", s(&img), "--model", s(&good), "--json"]);
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(v["outputs"][0]["value"].as_f64().unwrap().is_finite());
}

#[test]
fn floating_yarns_are_refused_by_params_render_and_export() {
    let d = tempfile::tempdir().unwrap();
    let e = fails(&["params", "--preset", "11/11"]);
    assert!(e.contains("not woven") && e.contains("weft 0 lies over every warp"), "{e}");
    let e = fails(&["params", "--preset", "10/10"]);
    assert!(e.contains("warp 0 lies under every weft"), "{e}");
    // A parameter file edited to an all-ones pattern.
    let good = param_file(d.path(), "plain");
    let text = std::fs::read_to_string(&good).unwrap();
    assert!(text.contains("\"10\",\n      \"01\""), "unexpected params layout: {text}");
    let bad = d.path().join("ones.json");
    std::fs::write(&bad, text.replace("\"10\",\n      \"01\"", "\"11\",\n      \"11\"")).unwrap();
    let png = d.path().join("a.png");
    let e = fails(&["render", "--params", s(&bad), "--out", s(&png), "--spp", "1"]);
    assert!(e.contains("weft 0 lies over every warp"), "{e}");
    assert!(!png.exists());
    let e = fails(&["export", s(&bad), "--out", s(&d.path().join("x"))]);
    assert!(e.contains("weft 0 lies over every warp"), "{e}");
    succeeds(&["render", "--params", s(&good), "--out", s(&png), "--width", "16", "--height", "16", "--spp", "1"]);
    succeeds(&["export", s(&good), "--out", s(&d.path().join("y")), "--repeats", "1"]);
}

/// `woven train` run from a checkout writes only into its work folder; replacing the shipped model
/// takes `--ship`; zero epochs are refused.
#[test]
fn train_never_replaces_the_shipped_model_by_default() {
    let d = tempfile::tempdir().unwrap();
    let repo = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    // A scratch checkout: the shipped files are sentinels.
    let root = d.path().join("repo");
    for f in ["models/pre_estimator.safetensors", "models/pre_estimator.json", "train/report.md", "train/curves.png"] {
        std::fs::create_dir_all(root.join(f).parent().unwrap()).unwrap();
        std::fs::write(root.join(f), b"shipped").unwrap();
    }
    let recipe = std::fs::read_to_string(repo.join("datagen/recipe.toml")).unwrap();
    std::fs::write(root.join("recipe.toml"), recipe).unwrap();
    std::fs::write(
        root.join("train/config.toml"),
        // 32 px views at the recipe's 8 px per cell: 4 × 4 cells, three pooled blocks.
        "input_size = 32\nbackbone = [4, 8, 8]\n[train]\nepochs = 1\nbatch_size = 8\nval_fraction = 0.0\n",
    )
    .unwrap();
    let run = |args: &[&str]| {
        let out = woven_in(Some(&root), args);
        (out.status.success(), String::from_utf8_lossy(&out.stderr).to_string())
    };
    let (ok, e) = run(&[
        "generate",
        "--out",
        "data",
        "--recipe",
        "recipe.toml",
        "--count",
        "12",
        "--size",
        "32",
        "--threads",
        "2",
    ]);
    assert!(ok, "{e}");
    let (ok, e) = run(&["train", "--data", "data", "--epochs", "0"]);
    assert!(!ok && e.contains("--epochs"), "{e}");
    let (ok, e) = run(&["train", "--data", "data"]);
    assert!(ok, "{e}");
    for f in ["models/pre_estimator.safetensors", "models/pre_estimator.json", "train/report.md", "train/curves.png"] {
        assert_eq!(std::fs::read(root.join(f)).unwrap(), b"shipped", "{f} was replaced");
    }
    for f in ["model.safetensors", "model.json", "report.md", "curves.png"] {
        assert!(root.join("train/run").join(f).is_file(), "train/run/{f}");
    }
    let (ok, e) = run(&["train", "--data", "data", "--ship"]);
    assert!(ok, "{e}");
    for f in ["models/pre_estimator.safetensors", "models/pre_estimator.json", "train/report.md", "train/curves.png"] {
        assert_ne!(std::fs::read(root.join(f)).unwrap(), b"shipped", "{f} was not shipped");
    }
    let card: serde_json::Value =
        serde_json::from_slice(&std::fs::read(root.join("models/pre_estimator.json")).unwrap()).unwrap();
    assert_eq!(card["weights"], "pre_estimator.safetensors");
}

#[test]
fn a_thin_strip_names_its_own_size() {
    let d = tempfile::tempdir().unwrap();
    // Two families of stripes, rotated by 10°: a weave-like grid that rectification turns.
    let (a, pitch) = (10f32.to_radians(), 12.0f32);
    let strip = image::RgbImage::from_fn(20_000, 40, |x, y| {
        let (u, v) = (x as f32 * a.cos() + y as f32 * a.sin(), -(x as f32) * a.sin() + y as f32 * a.cos());
        let c =
            0.5 + 0.25 * (u / pitch * std::f32::consts::TAU).cos() + 0.25 * (v / pitch * std::f32::consts::TAU).cos();
        let g = (c * 255.0) as u8;
        image::Rgb([g, g, g])
    });
    let p = d.path().join("strip.png");
    strip.save(&p).unwrap();
    let e = fails(&["prep", s(&p), "--out", s(&d.path().join("o"))]);
    assert!(e.contains("20000x40"), "the input's size is named: {e}");
}

#[test]
fn negative_seeds_get_a_hint() {
    let d = tempfile::tempdir().unwrap();
    let pf = param_file(d.path(), "plain");
    let png = d.path().join("a.png");
    let hint = "seed must be a non-negative integer";
    let e = fails(&["render", "--params", s(&pf), "--out", s(&png), "--seed", "-1"]);
    assert!(e.contains(hint), "{e}");
    let e = fails(&["generate", "--out", s(&d.path().join("g")), "--seed", "-1"]);
    assert!(e.contains(hint), "{e}");
    let e = fails(&["stress", "--count", "1", "--seed", "-5", "--out", s(&d.path().join("b.md"))]);
    assert!(e.contains(hint), "{e}");
    succeeds(&[
        "render",
        "--params",
        s(&pf),
        "--out",
        s(&png),
        "--seed",
        "3",
        "--width",
        "16",
        "--height",
        "16",
        "--spp",
        "1",
    ]);
}

#[test]
fn render_writes_both_images_or_neither() {
    let d = tempfile::tempdir().unwrap();
    let pf = param_file(d.path(), "plain");
    let png = d.path().join("a.png");
    // The EXR's folder is a file, so the EXR cannot be written.
    let blocker = d.path().join("blocker");
    std::fs::write(&blocker, b"x").unwrap();
    let exr = blocker.join("a.exr");
    let small = ["--width", "16", "--height", "16", "--spp", "1"];
    let e = fails(&[&["render", "--params", s(&pf), "--out", s(&png), "--exr", s(&exr)][..], &small].concat());
    assert!(e.contains("nothing was written") && e.contains("a.exr"), "{e}");
    assert!(!png.exists(), "the PNG must not be left behind");
    let names: Vec<String> =
        std::fs::read_dir(d.path()).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into()).collect();
    assert!(names.iter().all(|n| !n.contains(".tmp")), "temporaries left: {names:?}");
    let exr = d.path().join("a.exr");
    succeeds(&[&["render", "--params", s(&pf), "--out", s(&png), "--exr", s(&exr)][..], &small].concat());
    assert!(png.is_file() && exr.is_file());
}

#[test]
fn fifos_and_devices_are_refused_not_read() {
    let d = tempfile::tempdir().unwrap();
    let fifo = d.path().join("fifo.png");
    let made = Command::new("mkfifo").arg(&fifo).status().map(|s| s.success()).unwrap_or(false);
    let png = d.path().join("a.png");
    if made {
        let want = "not a regular file";
        let e = fails(&["prep", s(&fifo), "--out", s(&d.path().join("p"))]);
        assert!(e.contains(want), "{e}");
        let e = fails(&["render", "--params", s(&fifo), "--out", s(&png)]);
        assert!(e.contains(want), "{e}");
        let e = fails(&["export", s(&fifo), "--out", s(&d.path().join("x"))]);
        assert!(e.contains(want), "{e}");
        let img = twill_png(d.path());
        let e = fails(&["predict", s(&img), "--model", s(&fifo)]);
        assert!(e.contains(want), "{e}");
        let e = fails(&["generate", "--out", s(&d.path().join("g")), "--recipe", s(&fifo)]);
        assert!(e.contains(want), "{e}");
    } else {
        eprintln!("mkfifo is not available; FIFO cases skipped");
    }
    if Path::new("/dev/zero").exists() {
        let e = fails(&["render", "--params", "/dev/zero", "--out", s(&png)]);
        assert!(e.contains("not a regular file"), "{e}");
    }
    // A parameter file over the 16 MiB cap is refused before it is read.
    let big = d.path().join("big.json");
    let f = std::fs::File::create(&big).unwrap();
    f.set_len(17 << 20).unwrap();
    let e = fails(&["render", "--params", s(&big), "--out", s(&png)]);
    assert!(e.contains("larger than the 16 MiB"), "{e}");
    assert!(!png.exists());
}
