//! The pre-estimator on a tiny generated set: training lowers the loss, `woven predict` reads the
//! saved model, and bad model files / images give clear errors.

use std::process::Command;
use woven::datagen::{generate, GenerateOptions, Recipe};
use woven::net::{NetSpec, PreEstimator, TrainConfig};
use woven::pre::{load_dataset, output_specs};
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
    let spec = NetSpec::new(32, classes, output_specs());
    let cfg = TrainConfig { epochs: 12, batch_size: 16, lr: 3e-3, val_fraction: 0.0, ..TrainConfig::default() };
    let work = dir.path().join("run");
    let report = woven::net::train(&samples, &spec, &cfg, &work, false).unwrap();
    let first = report.epochs.first().unwrap().train_loss;
    let last = report.epochs.last().unwrap().train_loss;
    assert!(last < 0.5 * first, "training loss {first} -> {last} did not halve");

    // The saved model predicts every output within its range, from the CLI too.
    let model = work.join("model.safetensors");
    let m = PreEstimator::load(&model).unwrap();
    let img = dir.path().join("data/images/000000.png");
    let p = m.predict(&woven::Image::load(&img, 8).unwrap().to_rgb32f()).unwrap();
    for (o, s) in p.outputs.iter().zip(output_specs()) {
        assert!(o.value >= s.min - 1e-6 && o.value <= s.max + 1e-6, "{} = {}", o.name, o.value);
    }
    let out = Command::new(env!("CARGO_BIN_EXE_woven"))
        .args(["predict", img.to_str().unwrap(), "--model", model.to_str().unwrap(), "--json"])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["outputs"].as_array().unwrap().len(), output_specs().len());

    // Missing and corrupt models, and a bad image, fail with a message and a non-zero exit.
    let run = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_woven")).args(args).env("RUST_BACKTRACE", "0").output().unwrap()
    };
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
}
