//! Diagnostics of the pre-estimator network on a dataset from `woven generate` (session 9).
//!
//! ```text
//! cargo run --release --example net_diag -- views DATA MODEL OUTDIR
//!     per view: index, split (train / val by the trainer's hash), share of the 8 × 8 grid cells
//!     read right, class, radii, ply count, light rig, blur; then the mean per split, rig and
//!     smaller radius. OUTDIR gets the first 24 views enlarged 6× with the label of every grid
//!     cell drawn as a bar (horizontal: weft on top), green where the model agrees, red where not.
//! cargo run --release --example net_diag -- train DATA CONFIG WORK EPOCHS [resume]
//!     `woven train` (src/pre.rs `train_model`) into WORK only, logging each epoch's summary:
//!     for comparing recipes side by side without touching the shipped model.
//! cargo run --release --example net_diag -- cue DATA
//!     share of grid cells a hand-made orientation cue reads right (mean |∂I/∂y| against mean
//!     |∂I/∂x| over the cell; `CUE_MID=k` restricts each to the middle k rows / columns), per rig.
//! cargo run --release --example net_diag -- cluster DATA MODEL
//!     grid cells right before and after `woven::net::pool_by_colour`, per split.
//! cargo run --release --example net_diag -- colour DATA
//!     how much of each body colour the picture holds (session 14): each family's mean colour
//!     over the middle of the cells it tops (truth labels), against the family's `R^B` —
//!     absolute, exposure-normalised, as chromaticity and as the two families' ratio — as the
//!     MAE of a least-squares line through the views ÷ the MAE of always answering the median
//!     (the trainer's verdict scale), per rig.
//! ```
//!
//! Whether a model under-fits (train and val accuracy both low) or over-fits, and which views
//! fail, decides what to change: see docs/benchmarks.md, "Session 9: the pre-estimator".

use anyhow::{bail, Context, Result};
use std::collections::BTreeMap;
use std::path::Path;
use woven::net::PreEstimator;
use woven::progress::{NoProgress, Progress};

const USAGE: &str =
    "usage: net_diag views DATA MODEL OUTDIR | train DATA CONFIG WORK EPOCHS [resume] | cue DATA | cluster DATA MODEL | colour DATA";

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    match args.get(1).map(String::as_str) {
        Some("views") if args.len() == 5 => views(Path::new(&args[2]), Path::new(&args[3]), Path::new(&args[4])),
        Some("train") if args.len() == 6 || args.len() == 7 => {
            let epochs: usize = args[5].parse().with_context(|| format!("EPOCHS `{}` is not a number", args[5]))?;
            let opts = woven::pre::TrainOptions {
                data: args[2].clone().into(),
                config: args[3].clone().into(),
                work: args[4].clone().into(),
                out: None,
                report_dir: None,
                resume: args.len() == 7,
                epochs: Some(epochs),
                command: args.join(" "),
            };
            let o = woven::pre::train_model(&opts, &EpochLog)?;
            eprintln!("trained on {} views in {:.0} s -> {}", o.images, o.seconds, o.model.display());
            Ok(())
        }
        Some("cue") if args.len() == 3 => cue(Path::new(&args[2])),
        Some("cluster") if args.len() == 4 => cluster(Path::new(&args[2]), Path::new(&args[3])),
        Some("colour") if args.len() == 3 => colour(Path::new(&args[2])),
        _ => bail!("{USAGE}"),
    }
}

/// Prints the trainer's messages (the plan and each epoch's summary) to stderr.
struct EpochLog;

impl Progress for EpochLog {
    fn begin(&self, _stage: &str, _total: u64) {}
    fn advance(&self, _n: u64) {}
    fn message(&self, m: &str) {
        if m.starts_with("epoch") || m.starts_with("training") || m.starts_with("resuming") {
            eprintln!("{m}");
        }
    }
}

/// The light rig of a label line, by the names of its lights (`back`, `front+back`, …).
fn rig_name(label: &serde_json::Value) -> String {
    let mut names: Vec<&str> = label["scene"]["lights"]["lights"]
        .as_array()
        .map(|a| a.iter().filter_map(|l| l["name"].as_str()).collect())
        .unwrap_or_default();
    names.sort_unstable();
    names.join("+")
}

fn views(data: &Path, model: &Path, outdir: &Path) -> Result<()> {
    let model = PreEstimator::load(model)?;
    std::fs::create_dir_all(outdir).with_context(|| format!("creating {}", outdir.display()))?;
    let (_, samples, _) = woven::pre::load_dataset(data, &NoProgress)?;
    let text = std::fs::read_to_string(data.join("labels.jsonl"))?;
    let labels: Vec<serde_json::Value> =
        text.lines().map(serde_json::from_str).collect::<Result<_, _>>().context("parsing labels.jsonl")?;
    if labels.len() != samples.len() {
        bail!("labels.jsonl has {} lines for {} views", labels.len(), samples.len());
    }
    let mut groups = GroupMeans::default();
    for (k, (s, l)) in samples.iter().zip(&labels).enumerate() {
        let p = model.predict(&s.image)?;
        let truth = s.cell_labels();
        if p.cell_logits.len() != truth.len() {
            bail!("view {k}: the model reads {} rows of cells, the labels have {}", p.cell_logits.len(), truth.len());
        }
        let n = truth.iter().map(Vec::len).sum::<usize>();
        let right = truth
            .iter()
            .zip(&p.cell_logits)
            .flat_map(|(t, l)| t.iter().zip(l))
            .filter(|(&t, &l)| (l > 0.0) == t)
            .count();
        let acc = right as f64 / n as f64;
        let split = if woven::net::train::is_validation(s.seed, 0.1) { "val" } else { "train" };
        let c = &l["cloth"];
        let (r_e, r_a) = (c["r_e"].as_f64().unwrap_or(f64::NAN), c["r_a"].as_f64().unwrap_or(f64::NAN));
        let rig = rig_name(l);
        let blur = l["noise"]["blur_px"].as_f64().unwrap_or(f64::NAN);
        println!(
            "{k} {split} {acc:.3} class={} r_e={r_e:.2} r_a={r_a:.2} n_p={} rig={rig} blur={blur:.2}",
            l["class_name"].as_str().unwrap_or("?"),
            c["n_p"]
        );
        for key in [
            format!("split {split}"),
            format!("rig {rig}"),
            format!("smaller radius {}", r_e.min(r_a).floor()),
            format!("class {}", l["class_name"].as_str().unwrap_or("?")),
        ] {
            groups.add(key, acc);
        }
        if k < 24 {
            label_sheet(&s.image, &truth, &p.cell_logits)?.save(outdir.join(format!("v{k:04}.png")))?;
        }
    }
    groups.print("", "grid cells right ");
    Ok(())
}

/// The view enlarged 6× (sRGB), the cell grid in blue, and each cell's label as a bar
/// (horizontal: weft on top), green where the model's sign agrees, red where it does not.
fn label_sheet(img: &image::Rgb32FImage, truth: &[Vec<bool>], logits: &[Vec<f32>]) -> Result<image::RgbImage> {
    const SCALE: u32 = 6;
    let (w, h) = img.dimensions();
    let rows = truth.len() as u32;
    let cols = truth.first().map_or(0, |r| r.len() as u32);
    if rows == 0 || cols == 0 || w % cols != 0 || h % rows != 0 {
        bail!("a {w}×{h} view does not split into {cols}×{rows} cells");
    }
    let cell = w / cols;
    let enc = |v: f32| (woven::net::linear_to_srgb(v.clamp(0.0, 1.0)) * 255.0).round() as u8;
    let mut out = image::RgbImage::from_fn(w * SCALE, h * SCALE, |x, y| {
        let v = img.get_pixel(x / SCALE, y / SCALE).0;
        image::Rgb([enc(v[0]), enc(v[1]), enc(v[2])])
    });
    let side = cell * SCALE;
    for r in 0..rows {
        for c in 0..cols {
            let t = truth[r as usize][c as usize];
            let agree = (logits[r as usize][c as usize] > 0.0) == t;
            let colour = if agree { image::Rgb([0, 255, 0]) } else { image::Rgb([255, 0, 0]) };
            let (cx, cy) = (c * side + side / 2, r * side + side / 2);
            for d in 0..side / 2 {
                let d = d + side / 4;
                let (x, y) = if t { (c * side + d, cy) } else { (cx, r * side + d) };
                out.put_pixel(x, y, colour);
            }
            for q in 0..side {
                out.put_pixel(c * side, r * side + q, image::Rgb([60, 60, 255]));
                out.put_pixel(c * side + q, r * side, image::Rgb([60, 60, 255]));
            }
        }
    }
    Ok(out)
}

/// Accuracy of the hand-made cue alone: a grid cell is read "weft on top" when the mean |∂I/∂y|
/// over its pixels exceeds the mean |∂I/∂x| (I: the mean of the three log-encoded planes).
fn cue(data: &Path) -> Result<()> {
    let (_, samples, _) = woven::pre::load_dataset(data, &NoProgress)?;
    let text = std::fs::read_to_string(data.join("labels.jsonl"))?;
    let labels: Vec<serde_json::Value> =
        text.lines().map(serde_json::from_str).collect::<Result<_, _>>().context("parsing labels.jsonl")?;
    let mut groups = GroupMeans::default();
    for (s, l) in samples.iter().zip(&labels) {
        let (x, w, h) = woven::net::preprocess(&s.image, 8);
        let n = w * h;
        let lum = |xx: usize, yy: usize| (x[yy * w + xx] + x[n + yy * w + xx] + x[2 * n + yy * w + xx]) / 3.0;
        let truth = s.cell_labels();
        let (mut right, mut total) = (0usize, 0usize);
        for (r, row) in truth.iter().enumerate() {
            for (c, &t) in row.iter().enumerate() {
                let (mut gx, mut gy) = (0.0f32, 0.0f32);
                let mid = std::env::var("CUE_MID").ok().and_then(|v| v.parse::<usize>().ok()).unwrap_or(8);
                let (lo, hi) = (4 - mid / 2, 4 + mid / 2);
                for yy in r * 8..r * 8 + 8 {
                    for xx in c * 8..c * 8 + 8 {
                        let (in_y, in_x) = ((lo..hi).contains(&(yy - r * 8)), (lo..hi).contains(&(xx - c * 8)));
                        if !in_y && !in_x {
                            continue;
                        }
                        let (xl, xr) = (xx.saturating_sub(1), (xx + 1).min(w - 1));
                        let (yu, yd) = (yy.saturating_sub(1), (yy + 1).min(h - 1));
                        if in_y {
                            gx += (lum(xr, yy) - lum(xl, yy)).abs();
                        }
                        if in_x {
                            gy += (lum(xx, yd) - lum(xx, yu)).abs();
                        }
                    }
                }
                right += ((gy > gx) == t) as usize;
                total += 1;
            }
        }
        let acc = right as f64 / total as f64;
        for key in ["all".to_string(), format!("rig {}", rig_name(l))] {
            groups.add(key, acc);
        }
    }
    groups.print("cue alone, ", "grid cells right ");
    Ok(())
}

/// The model's grid logits against the same logits pooled within the two colour groups of the
/// view's cells by `woven::net::pool_by_colour` (the 8 × 8 grid taken as one repeat of 8 × 8
/// cells), per split, on all views and on the views whose colours separate.
fn cluster(data: &Path, model: &Path) -> Result<()> {
    let model = PreEstimator::load(model)?;
    let (_, samples, _) = woven::pre::load_dataset(data, &NoProgress)?;
    let mut groups = GroupMeans::default();
    for s in &samples {
        let p = model.predict(&s.image)?;
        let truth = s.cell_labels();
        let g = truth.len();
        // `pool_by_colour` indexes cells by weft: grid row r from the top is weft g − 1 − r.
        let view = woven::net::ViewPrediction {
            cell_logits: (0..g).map(|i| p.cell_logits[g - 1 - i].clone()).collect(),
            outputs: Vec::new(),
        };
        let pooled = woven::net::pool_by_colour(&view, &woven::Image::from_rgb32f(&s.image), g, g);
        let acc = |l: &[Vec<f32>]| {
            let right = (0..g)
                .flat_map(|i| (0..g).map(move |j| (i, j)))
                .filter(|&(i, j)| (l[i][j] > 0.0) == truth[g - 1 - i][j]);
            right.count() as f64 / (g * g) as f64
        };
        let split = if woven::net::train::is_validation(s.seed, 0.1) { "val" } else { "train" };
        let own = acc(&view.cell_logits);
        let after = pooled.as_ref().map_or(own, |v| acc(&v.cell_logits));
        let mut rows = vec![
            (format!("{split} network"), own),
            (format!("{split} colour-pooled"), after),
            (format!("{split} separated views"), pooled.is_some() as u8 as f64),
        ];
        if pooled.is_some() {
            rows.push((format!("{split} separated: network"), own));
            rows.push((format!("{split} separated: pooled"), after));
        }
        for (key, a) in rows {
            groups.add(key, a);
        }
    }
    groups.print("", "");
    Ok(())
}

/// MAE of the least-squares line `y ≈ a + b x` through the pairs, ÷ the MAE of the median of `y`:
/// 1 when `x` says nothing about `y` (linearly), 0 when it determines it.
fn line_mae_ratio(pairs: &[(f64, f64)]) -> f64 {
    let n = pairs.len() as f64;
    let (mx, my) = (pairs.iter().map(|p| p.0).sum::<f64>() / n, pairs.iter().map(|p| p.1).sum::<f64>() / n);
    let sxy: f64 = pairs.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let sxx: f64 = pairs.iter().map(|p| (p.0 - mx).powi(2)).sum();
    let b = if sxx > 0.0 { sxy / sxx } else { 0.0 };
    let mae = pairs.iter().map(|p| (p.1 - my - b * (p.0 - mx)).abs()).sum::<f64>() / n;
    let mut ys: Vec<f64> = pairs.iter().map(|p| p.1).collect();
    ys.sort_by(f64::total_cmp);
    let med = ys[ys.len() / 2];
    let base = ys.iter().map(|y| (y - med).abs()).sum::<f64>() / n;
    mae / base.max(1e-12)
}

/// See the module docs, `colour`.
fn colour(data: &Path) -> Result<()> {
    let (_, samples, _) = woven::pre::load_dataset(data, &NoProgress)?;
    let text = std::fs::read_to_string(data.join("labels.jsonl"))?;
    let labels: Vec<serde_json::Value> =
        text.lines().map(serde_json::from_str).collect::<Result<_, _>>().context("parsing labels.jsonl")?;
    // (group, feature name) -> (x, y) pairs over the views.
    let mut pairs: BTreeMap<(String, String), Vec<(f64, f64)>> = BTreeMap::new();
    for (s, l) in samples.iter().zip(&labels) {
        let truth = s.cell_labels();
        let img = &s.image;
        let (w, h) = img.dimensions();
        let mean_img = img.as_raw().iter().map(|&v| v as f64).sum::<f64>() / (3 * w * h) as f64;
        // Family sums over the middle 4 × 4 px of every cell it tops (label true: weft on top).
        let mut fam = [[0f64; 3]; 2];
        let mut cnt = [0usize; 2];
        for (r, row) in truth.iter().enumerate() {
            for (c, &t) in row.iter().enumerate() {
                let f = if t { 0 } else { 1 };
                for y in r * 8 + 2..r * 8 + 6 {
                    for x in c * 8 + 2..c * 8 + 6 {
                        let p = img.get_pixel(x as u32, y as u32);
                        for k in 0..3 {
                            fam[f][k] += p[k].max(0.0) as f64;
                        }
                        cnt[f] += 1;
                    }
                }
            }
        }
        if cnt.contains(&0) {
            continue;
        }
        let fam: Vec<[f64; 3]> = (0..2).map(|f| fam[f].map(|v| v / cnt[f] as f64)).collect();
        let ap = &l["cloth"]["appearance"];
        let rb = |key: &str| -> [f64; 3] {
            let a = ap[key].as_array();
            [0, 1, 2].map(|k| a.and_then(|a| a[k].as_f64()).unwrap_or(f64::NAN))
        };
        let truth_rb = [rb("r_b_e"), rb("r_b_a")];
        let rig = rig_name(l);
        for group in ["all".to_string(), format!("rig {rig}")] {
            let mut add = |feat: &str, x: f64, y: f64| {
                pairs.entry((group.clone(), feat.to_string())).or_default().push((x, y));
            };
            for (f, name) in [(0, "e"), (1, "a")] {
                let sum_c: f64 = fam[f].iter().sum::<f64>() + 1e-6;
                let sum_t: f64 = truth_rb[f].iter().sum::<f64>() + 1e-6;
                let other = [rb(&format!("s_b_{name}")), rb("r_s"), rb("t_s")];
                // The body lobes' weight at a front vertex (src/shading/bysdf.rs `VertexTerms`):
                // m_r · (1 − T^S_k) · R^B_k, the colour the picture shows up to the light level.
                let m_r = ap["m_r"].as_f64().unwrap_or(f64::NAN);
                let eff = [0, 1, 2].map(|k| m_r * (1.0 - other[2][k]) * truth_rb[f][k]);
                let sum_eff: f64 = eff.iter().sum::<f64>() + 1e-6;
                for k in 0..3 {
                    for (o, oname) in other.iter().zip(["s_b", "r_s", "t_s"]) {
                        add(&format!("{oname}({name})[k] ~ colour / mean"), fam[f][k] / mean_img, o[k]);
                    }
                    add(&format!("r_b_{name}[k] ~ colour"), fam[f][k], truth_rb[f][k]);
                    add(&format!("m_r (1 - t_s) r_b_{name}[k] ~ colour / mean"), fam[f][k] / mean_img, eff[k]);
                    add(&format!("m_r (1 - t_s) r_b_{name}[k] ~ colour"), fam[f][k], eff[k]);
                    add(&format!("chroma (1 - t_s) r_b_{name}[k] ~ chroma"), fam[f][k] / sum_c, eff[k] / sum_eff);
                    add(&format!("r_b_{name}[k] ~ colour / mean"), fam[f][k] / mean_img, truth_rb[f][k]);
                    add(&format!("chroma r_b_{name}[k] ~ chroma"), fam[f][k] / sum_c, truth_rb[f][k] / sum_t);
                }
            }
            for k in 0..3 {
                let x = fam[0][k] / (fam[0][k] + fam[1][k] + 1e-6);
                let y = truth_rb[0][k] / (truth_rb[0][k] + truth_rb[1][k] + 1e-6);
                add("ratio r_b_e/(r_b_e+r_b_a)[k] ~ same of colour", x, y);
            }
        }
    }
    for ((group, feat), p) in &pairs {
        eprintln!("{group}: {feat}: {} pairs, line MAE / median MAE {:.2}", p.len(), line_mae_ratio(p));
    }
    Ok(())
}

/// Per-key means of per-view accuracies, printed in key order.
#[derive(Default)]
struct GroupMeans(BTreeMap<String, (f64, usize)>);

impl GroupMeans {
    fn add(&mut self, key: String, value: f64) {
        let e = self.0.entry(key).or_default();
        e.0 += value;
        e.1 += 1;
    }

    /// One line per key: `{prefix}{key}: {n} views, {what}{mean}%`.
    fn print(&self, prefix: &str, what: &str) {
        for (key, (sum, n)) in &self.0 {
            eprintln!("{prefix}{key}: {n} views, {what}{:.1}%", 100.0 * sum / *n as f64);
        }
    }
}
