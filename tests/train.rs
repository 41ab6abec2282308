//! The pre-estimator on a tiny generated set: training lowers the loss, `woven predict` reads the
//! saved model, and bad model files / images give clear errors; the shipped model reads the
//! pattern of the fit's target.

use std::process::Command;
use woven::datagen::{generate, GenerateOptions, Recipe};
use woven::net::{read_view, NetSpec, PreEstimator, TrainConfig};
use woven::pre::{load_dataset, output_specs, DEFAULT_MODEL};
use woven::progress::NoProgress;

#[test]
fn tiny_generated_set_trains_and_predicts() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let mut opts = GenerateOptions::new(&data, Recipe::default());
    opts.count = Some(32);
    opts.size = Some(32);
    opts.recipe.image.spp = 1;
    generate(&opts, &NoProgress).unwrap();
    let (classes, samples, _) = load_dataset(&data, &NoProgress).unwrap();
    assert_eq!(samples.len(), 32);
    assert!(samples.iter().all(|s| s.targets.len() == output_specs().len()));
    assert!(samples.iter().all(|s| s.view_cells.len() == 4 && s.view_cells[0].len() == 4), "32 px = 4 × 4 cells");
    let mut spec = NetSpec::new(32, output_specs());
    spec.classes = classes;
    let cfg = TrainConfig { epochs: 12, batch_size: 16, lr: 3e-3, val_fraction: 0.0, ..TrainConfig::default() };
    let work = dir.path().join("run");
    let report = woven::net::train(&samples, &spec, &cfg, &work, false).unwrap();
    let first = report.epochs.first().unwrap().train_loss;
    let last = report.epochs.last().unwrap().train_loss;
    assert!(last < first - 0.05, "training loss {first} -> {last} did not fall");

    // The saved model predicts every output within its range, from the CLI too.
    let model = work.join("model.safetensors");
    let m = PreEstimator::load(&model).unwrap();
    let img = dir.path().join("data/images/000000.png");
    let p = m.predict(&woven::Image::load(&img, 8).unwrap().to_rgb32f()).unwrap();
    assert_eq!((p.cell_logits.len(), p.cell_logits[0].len()), (4, 4));
    for (o, s) in p.outputs.iter().zip(output_specs()) {
        assert!(o.value >= s.min - 1e-6 && o.value <= s.max + 1e-6, "{} = {}", o.name, o.value);
        assert!(o.sigma > 0.0 && o.sigma.is_finite(), "{} σ = {}", o.name, o.sigma);
    }
    let run = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_woven")).args(args).env("RUST_BACKTRACE", "0").output().unwrap()
    };
    let out = run(&["predict", img.to_str().unwrap(), "--model", model.to_str().unwrap(), "--view", "--json"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["outputs"].as_array().unwrap().len(), output_specs().len());
    assert_eq!(v["cell_logits"].as_array().unwrap().len(), 4);
    let out = run(&[
        "predict",
        img.to_str().unwrap(),
        "--model",
        model.to_str().unwrap(),
        "--one-repeat",
        "--grid",
        "3x2",
        "--json",
    ]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let rows = v["cell_logits"].as_array().unwrap();
    assert_eq!((rows.len(), rows[0].as_array().unwrap().len()), (3, 2), "one logit per cell of the 3×2 grid");

    // Missing and corrupt models, and bad images and grids, fail with a message and a non-zero exit.
    let out = run(&["predict", img.to_str().unwrap(), "--model", "/nonexistent/m.safetensors"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("woven train"), "should say how to train one");
    let bad = dir.path().join("bad.safetensors");
    std::fs::write(&bad, b"definitely not a model").unwrap();
    let out = run(&["predict", img.to_str().unwrap(), "--model", bad.to_str().unwrap()]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).to_lowercase().contains("corrupt"));
    let txt = dir.path().join("img.png");
    std::fs::write(&txt, b"not a png").unwrap();
    let out = run(&["predict", txt.to_str().unwrap(), "--model", model.to_str().unwrap()]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("cannot read image"));
    let out =
        run(&["predict", img.to_str().unwrap(), "--model", model.to_str().unwrap(), "--one-repeat", "--grid", "0x3"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("NExNA"));
}

/// The shipped model on the fit's own target: one repeat rendered as `fit_scene` renders it (12
/// px per cell, default rig), for presets it was trained on and a random pattern; the pattern it
/// reads must be the truth, cell for cell.
#[test]
fn shipped_model_reads_the_fit_targets_pattern() {
    use woven::fit::target::fit_scene;
    use woven::render::{render, RenderOptions};
    use woven::scene::LightRig;
    let model = PreEstimator::load(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(DEFAULT_MODEL)).unwrap();
    let mut wrong = Vec::new();
    for (k, name) in ["plain", "twill22", "satin5", "twill31", "1100/0111/0010"].iter().enumerate() {
        let mut cloth = woven::params::ClothParams::preset("plain").unwrap();
        cloth.pattern = name.parse().unwrap();
        (cloth.r_e, cloth.r_a) = (3.5 + 0.3 * k as f32, 4.0);
        let p = cloth.pattern.clone();
        let scene = fit_scene(p.n_e(), p.n_a(), 12, 16, 7 + k as u64, &LightRig::default_rig());
        let img = render(&cloth, &scene, &RenderOptions { threads: Some(2), ..Default::default() });
        let v = read_view(&model, &img, p.n_e(), p.n_a()).unwrap();
        let read = v.cells();
        let truth: Vec<Vec<bool>> = (0..p.n_e()).map(|i| (0..p.n_a()).map(|j| p.get(i, j)).collect()).collect();
        if read != truth {
            wrong.push(format!("{name}: read {read:?}"));
        }
        let r_e = v.output("r_e").unwrap();
        assert!(r_e.sigma > 0.0 && r_e.value >= 1.0 && r_e.value <= 5.0);
    }
    assert!(wrong.is_empty(), "patterns misread: {wrong:?}");
}

/// Milliseconds per training step (batch 32) of a few architectures (run by hand:
/// `cargo test --release --test train -- --ignored --nocapture step_cost`).
#[test]
#[ignore]
fn step_cost() {
    let threads: usize = std::env::var("WOVEN_STEP_THREADS").ok().and_then(|s| s.parse().ok()).unwrap_or(2);
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
    // (backbone, convs per block, cell convs, cell dilations, orientation planes + residual cells)
    let shipped = (vec![8, 32, 64], 1, vec![64], vec![], false);
    let wide = (vec![16, 32, 64], 2, vec![64; 4], vec![1, 2, 4, 1], true);
    let narrow = (vec![8, 32, 64], 2, vec![64; 4], vec![1, 2, 4, 1], true);
    for (backbone, per_block, cell, dil, extra) in [shipped, wide, narrow] {
        let mut spec = NetSpec::new(64, output_specs());
        (spec.backbone, spec.convs_per_block, spec.cell_convs) = (backbone.clone(), per_block, cell.clone());
        (spec.cell_dilations, spec.orientation_channels, spec.cell_residual) = (dil.clone(), extra, extra);
        let ms = pool.install(|| woven::net::bench_train_step(&spec, 32, 5).unwrap());
        println!("backbone {backbone:?} x{per_block} cell {cell:?} dilations {dil:?} orientation/residual {extra}: {ms:.0} ms per step of 32 on {threads} threads");
    }
}

/// Diagnostic (by hand): a few epochs on the first `WOVEN_DIAG_N` views of the dataset in
/// `WOVEN_DIAG_DATA`, printing the cells' training loss per epoch.
#[test]
#[ignore]
fn diag_cells() {
    let Ok(dir) = std::env::var("WOVEN_DIAG_DATA") else {
        eprintln!("WOVEN_DIAG_DATA not set; skipping");
        return;
    };
    let n: usize = std::env::var("WOVEN_DIAG_N").ok().and_then(|s| s.parse().ok()).unwrap_or(300);
    let pw: f64 = std::env::var("WOVEN_DIAG_PW").ok().and_then(|s| s.parse().ok()).unwrap_or(0.0);
    let (classes, mut samples, _) = load_dataset(std::path::Path::new(&dir), &NoProgress).unwrap();
    samples.truncate(n);
    if std::env::var("WOVEN_DIAG_BARS").is_ok() {
        for s in samples.iter_mut() {
            let lab = s.cell_labels();
            s.image = image::Rgb32FImage::from_fn(64, 64, |x, y| {
                let weft = lab[y as usize / 8][x as usize / 8];
                let on = if weft { (2..6).contains(&(y % 8)) } else { (2..6).contains(&(x % 8)) };
                image::Rgb([if on { 0.8 } else { 0.1 }; 3])
            });
        }
    }
    let mut spec = NetSpec::new(64, output_specs());
    spec.classes = classes;
    if let Ok(b) = std::env::var("WOVEN_DIAG_BACKBONE") {
        spec.backbone = b.split(',').map(|x| x.parse().unwrap()).collect();
    }
    let lr: f64 = std::env::var("WOVEN_DIAG_LR").ok().and_then(|s| s.parse().ok()).unwrap_or(2e-3);
    let cfg = TrainConfig {
        epochs: 4,
        lr,
        param_weight: pw,
        augment: false,
        val_fraction: 0.0,
        threads: 2,
        ..Default::default()
    };
    let work = tempfile::tempdir().unwrap();
    let r = woven::net::train(&samples, &spec, &cfg, work.path(), false).unwrap();
    for e in &r.epochs {
        println!("{}", e.summary(4));
        println!("  cell loss {:.4}", e.train_cell_loss);
    }
    println!("cells right {:.3}", r.cell_accuracy);
}
