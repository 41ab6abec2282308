//! The `woven` binary: parameter files round-trip through `params` and `render`; bad input gives a
//! clear error and a non-zero exit, never a panic.

use std::process::Command;

fn woven(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_woven")).args(args).env("RUST_BACKTRACE", "0").output().expect("run woven")
}

#[test]
fn params_then_render_writes_png_and_exr() {
    let dir = tempfile::tempdir().unwrap();
    let out = woven(&["params", "--preset", "satin5", "--rotate", "90"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let json = String::from_utf8(out.stdout).unwrap();
    let p = woven::ParamFile::from_json(&json).expect("params output is a valid parameter file");
    assert_eq!((p.cloth.pattern.n_e(), p.cloth.pattern.n_a()), (5, 5));
    let pf = dir.path().join("p.json");
    std::fs::write(&pf, &json).unwrap();
    let png = dir.path().join("a.png");
    let exr = dir.path().join("a.exr");
    let args =
        ["render", "--params", pf.to_str().unwrap(), "--out", png.to_str().unwrap(), "--exr", exr.to_str().unwrap()];
    let out = woven(&[&args[..], &["--width", "24", "--height", "16", "--spp", "1"]].concat());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let img = image::open(&png).unwrap();
    assert_eq!((img.width(), img.height()), (24, 16));
    let back = woven::Image::load(&exr, 1).unwrap();
    assert_eq!((back.width, back.height), (24, 16));
    assert!(back.data.iter().flatten().all(|v| v.is_finite() && *v >= 0.0));
}

fn render_error(json: &str) -> String {
    let dir = tempfile::tempdir().unwrap();
    let pf = dir.path().join("p.json");
    std::fs::write(&pf, json).unwrap();
    let png = dir.path().join("a.png");
    let out = woven(&["render", "--params", pf.to_str().unwrap(), "--out", png.to_str().unwrap(), "--spp", "1"]);
    assert!(!out.status.success(), "bad input must fail");
    assert!(!png.exists(), "no output on failure");
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(!err.contains("panicked"), "must not panic: {err}");
    err
}

#[test]
fn bad_parameter_files_are_refused_with_the_field_named() {
    let good = String::from_utf8(woven(&["params", "--preset", "plain"]).stdout).unwrap();
    let e = render_error(&good.replace("\"eta_s\": 1.5", "\"eta_s\": 2.5"));
    assert!(e.contains("eta_s") && e.contains("[1.4, 1.6]"), "{e}");
    let e = render_error(&good.replace("\"n_p\": 3", "\"n_p\": 9"));
    assert!(e.contains("n_p") && e.contains("[1, 7]"), "{e}");
    let e = render_error(&good.replace("\"a_b\": 0.15", "\"a_b\": NaN"));
    assert!(e.contains("malformed"), "{e}");
    let e = render_error(&good.replace("\"a_b\": 0.15", "\"a_b\": 1e999"));
    assert!(e.contains("malformed") || e.contains("a_b"), "{e}");
    let e = render_error(&good.replace("\"10\"", "\"12\""));
    assert!(e.contains("non-binary"), "{e}");
    let e = render_error(&good.replace("\"tiles\": 2.0", "\"tiles\": 0.0"));
    assert!(e.contains("scene.camera.tiles"), "{e}");
    let e = render_error("{ not json");
    assert!(e.contains("malformed"), "{e}");
    let e = render_error(&good.replace("\"g_f\"", "\"g_q\""));
    assert!(e.contains("g_q"), "{e}");
}

#[test]
fn missing_files_and_unknown_presets_fail_cleanly() {
    let out = woven(&["render", "--params", "/nonexistent/p.json", "--out", "/tmp/x.png"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("cannot read parameter file"));
    let out = woven(&["params", "--preset", "herringbone"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("unknown weave preset"));
    let out = woven(&["params", "--preset", "10/1"]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("ragged"));
}

/// `woven prep PHOTO | head -1`: the reader leaves after one line. The pipe is closed before the
/// process starts, so every write to stdout fails with `BrokenPipe`; the command must still run to
/// its end (files written, exit 0) instead of panicking in `println!` (exit 101).
#[test]
fn a_closed_stdout_pipe_neither_panics_nor_stops_the_job() {
    let dir = tempfile::tempdir().unwrap();
    let params = dir.path().join("p.json");
    let out = woven(&["params", "--preset", "plain"]);
    assert!(out.status.success());
    std::fs::write(&params, &out.stdout).unwrap();
    let photo = dir.path().join("r.png");
    let args = ["render", "--params", params.to_str().unwrap(), "--out", photo.to_str().unwrap()];
    let out = woven(&[&args[..], &["--width", "96", "--height", "96", "--spp", "2", "--tiles", "4"]].concat());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));

    let prep_dir = dir.path().join("prep");
    let (reader, writer) = std::io::pipe().unwrap();
    drop(reader);
    let out = Command::new(env!("CARGO_BIN_EXE_woven"))
        .args(["prep", photo.to_str().unwrap(), "--out", prep_dir.to_str().unwrap()])
        .env("RUST_BACKTRACE", "0")
        .stdout(writer)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "exit {:?}: {stderr}", out.status.code());
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(prep_dir.join("prep.json").is_file() && prep_dir.join("crop.png").is_file());
}

/// `woven prep` on a photo without a yarn grid: a clear refusal and a non-zero exit, what
/// preparation saw written beside the output (`OUT.prep-grid.png`), and the output folder itself
/// not created.
#[test]
fn a_refused_preparation_says_why_and_leaves_the_overlay() {
    let dir = tempfile::tempdir().unwrap();
    let photo = dir.path().join("grey.png");
    image::RgbImage::from_pixel(96, 96, image::Rgb([120, 118, 110])).save(&photo).unwrap();
    let out_dir = dir.path().join("prep");
    let out = woven(&["prep", photo.to_str().unwrap(), "--out", out_dir.to_str().unwrap()]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("no periodic yarn structure found") && stderr.contains("try a sharp"), "{stderr}");
    assert!(stderr.contains("prep.prep-grid.png"), "{stderr}");
    let overlay = image::open(dir.path().join("prep.prep-grid.png")).expect("the overlay is a PNG");
    // The rectified photo: the input less a margin the rectification leaves out.
    assert!((48..=96).contains(&overlay.width()) && (48..=96).contains(&overlay.height()));
    assert!(!out_dir.exists(), "a refused preparation creates no output folder");
}
