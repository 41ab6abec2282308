//! The training report: per-epoch history, final metrics, a Markdown summary and a loss plot.
//!
//! Output errors are mean absolute errors of the normalised values, i.e. fractions of each
//! parameter's range. Two reference errors are reported per output:
//!
//! * *chance*: the mean |a − b| over pairs of true values (1/3 for uniform targets), the error
//!   of guessing a random value from the prior;
//! * *baseline*: the mean |t − median(t)| (1/4 for uniform targets), the error of always
//!   answering the median. A network trained with L1 that cannot see a parameter converges to
//!   this, not to chance, so the verdict compares with the baseline: outputs at
//!   ≥ [`NOT_IDENTIFIABLE`] × baseline (0.2 of the range for uniform targets, 0.6 of chance)
//!   are flagged "not identifiable from the image".

use anyhow::Result;
use plotters::prelude::*;
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::path::Path;

/// Error/baseline ratio from which an output counts as not identifiable from the image.
pub const NOT_IDENTIFIABLE: f32 = 0.8;
/// Error/baseline ratio from which an output counts as weakly identifiable.
pub const WEAK: f32 = 0.5;

/// Statistics of one epoch.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpochStats {
    /// 1-based epoch number.
    pub epoch: usize,
    /// Mean training loss over the epoch's batches (weights changing meanwhile).
    pub train_loss: f32,
    /// Validation loss at the end of the epoch (`None` without validation samples).
    pub val_loss: Option<f32>,
    /// Validation pattern accuracy (`None` without validation samples or with < 2 classes).
    pub val_accuracy: Option<f32>,
    /// Learning rate of the epoch's last step.
    pub lr: f64,
    /// Wall time of the epoch including validation, seconds.
    pub seconds: f64,
}

impl EpochStats {
    /// One-line summary, e.g. for logs.
    pub fn summary(&self, epochs: usize) -> String {
        let mut s = format!("epoch {}/{epochs}: train {:.4}", self.epoch, self.train_loss);
        if let Some(v) = self.val_loss {
            let _ = write!(s, "  val {v:.4}");
        }
        if let Some(a) = self.val_accuracy {
            let _ = write!(s, "  acc {:.1}%", 100.0 * a);
        }
        let _ = write!(s, "  lr {:.2e}  {:.1} s", self.lr, self.seconds);
        s
    }
}

/// Error of one output on the evaluation set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OutputError {
    /// Output name.
    pub name: String,
    /// Mean absolute error as a fraction of the output's range.
    pub mae: f32,
    /// The same in the output's units.
    pub mae_units: f64,
    /// Mean pairwise |a − b| of the true normalised values (≈ 1/3 for uniform targets).
    pub chance: f32,
    /// Mean |t − median(t)| of the true normalised values (1/4 for uniform targets).
    pub baseline: f32,
}

impl OutputError {
    /// `mae / baseline` (≈ 1 for an output the network cannot see).
    pub fn ratio(&self) -> f32 {
        self.mae / self.baseline.max(1e-6)
    }

    /// `"not identifiable from the image"`, `"weak"` or `"ok"`.
    pub fn verdict(&self) -> &'static str {
        let r = self.ratio();
        if r >= NOT_IDENTIFIABLE {
            "not identifiable from the image"
        } else if r >= WEAK {
            "weak"
        } else {
            "ok"
        }
    }
}

/// Everything [`super::train()`] measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainReport {
    /// Class names (rows/columns of the confusion matrix).
    pub class_names: Vec<String>,
    /// Per-epoch history (including epochs done before a resume).
    pub epochs: Vec<EpochStats>,
    /// Which set the final metrics were computed on.
    pub eval_set: String,
    /// Number of training samples.
    pub n_train: usize,
    /// Number of validation samples.
    pub n_val: usize,
    /// Pattern accuracy on the evaluation set (`None` with < 2 classes).
    pub accuracy: Option<f32>,
    /// Confusion matrix: `confusion[true][predicted]`.
    pub confusion: Vec<Vec<u32>>,
    /// Per-output error.
    pub output_errors: Vec<OutputError>,
    /// Loss on the evaluation set with the final weights.
    pub eval_loss: f32,
    /// Wall time of the `train` call, seconds (epochs done before a resume are in `epochs`).
    pub wall_seconds: f64,
}

impl TrainReport {
    /// Write a Markdown report: accuracy, confusion matrix, per-output errors with verdicts,
    /// and the loss history.
    pub fn write_markdown(&self, path: &Path) -> Result<()> {
        super::infer::write_atomic(path, self.to_markdown().as_bytes())
    }

    /// The Markdown text of [`Self::write_markdown`].
    pub fn to_markdown(&self) -> String {
        let mut s = String::new();
        let w = &mut s;
        let _ = writeln!(w, "# Pre-estimator training report\n");
        let train_s: f64 = self.epochs.iter().map(|e| e.seconds).sum();
        let _ = writeln!(
            w,
            "{} training / {} validation samples, {} epochs ({:.1} s in epochs, {:.1} s this run). Metrics on the **{}** set, loss {:.4}.\n",
            self.n_train,
            self.n_val,
            self.epochs.len(),
            train_s,
            self.wall_seconds,
            self.eval_set,
            self.eval_loss
        );
        if let Some(a) = self.accuracy {
            let nc = self.class_names.len();
            let _ = writeln!(
                w,
                "## Pattern class\n\nAccuracy **{:.1}%** (chance {:.1}%).\n",
                100.0 * a,
                100.0 / nc.max(1) as f32
            );
            let _ = writeln!(w, "Confusion matrix (rows: true class, columns: predicted):\n");
            let _ = write!(w, "| true \\ predicted |");
            for n in &self.class_names {
                let _ = write!(w, " {n} |");
            }
            let _ = write!(w, "\n|---|");
            for _ in &self.class_names {
                let _ = write!(w, "---:|");
            }
            let _ = writeln!(w);
            for (i, row) in self.confusion.iter().enumerate() {
                let _ = write!(w, "| {} |", self.class_names[i]);
                for c in row {
                    let _ = write!(w, " {c} |");
                }
                let _ = writeln!(w);
            }
            let _ = writeln!(w);
        }
        if !self.output_errors.is_empty() {
            let _ = writeln!(w, "## Outputs\n");
            let _ = writeln!(
                w,
                "Mean absolute error as a fraction of the range. *Chance*: error of a random guess from the target distribution (1/3 for uniform targets). *Baseline*: error of always answering the median (1/4 for uniform targets); a network that cannot see a parameter ends there, so the verdict uses MAE / baseline (not identifiable ≥ {NOT_IDENTIFIABLE}, weak ≥ {WEAK}).\n"
            );
            let _ = writeln!(
                w,
                "| output | MAE (fraction of range) | MAE (units) | chance | baseline | MAE / baseline | verdict |"
            );
            let _ = writeln!(w, "|---|---:|---:|---:|---:|---:|---|");
            for e in &self.output_errors {
                let _ = writeln!(
                    w,
                    "| {} | {:.3} | {:.4} | {:.3} | {:.3} | {:.2} | {} |",
                    e.name,
                    e.mae,
                    e.mae_units,
                    e.chance,
                    e.baseline,
                    e.ratio(),
                    e.verdict()
                );
            }
            let bad: Vec<&str> =
                self.output_errors.iter().filter(|e| e.ratio() >= NOT_IDENTIFIABLE).map(|e| e.name.as_str()).collect();
            if !bad.is_empty() {
                let _ = writeln!(
                    w,
                    "\n**Not identifiable from the image** (error ≥ {:.0}% of the median baseline): {}.",
                    100.0 * NOT_IDENTIFIABLE,
                    bad.join(", ")
                );
            }
            let _ = writeln!(w);
        }
        let _ = writeln!(w, "## History\n\n| epoch | train loss | val loss | val accuracy | lr | s |");
        let _ = writeln!(w, "|---:|---:|---:|---:|---:|---:|");
        for e in &self.epochs {
            let _ = writeln!(
                w,
                "| {} | {:.4} | {} | {} | {:.2e} | {:.1} |",
                e.epoch,
                e.train_loss,
                e.val_loss.map_or("–".into(), |v| format!("{v:.4}")),
                e.val_accuracy.map_or("–".into(), |v| format!("{:.1}%", 100.0 * v)),
                e.lr,
                e.seconds
            );
        }
        s
    }

    /// Plot train and validation loss per epoch into a PNG (800×500).
    pub fn write_curves_png(&self, path: &Path) -> Result<()> {
        crate::plot::register_font();
        let (w, h) = (800u32, 500u32);
        let mut buf = vec![0u8; (w * h * 3) as usize];
        let err = |e: &dyn std::fmt::Display| anyhow::anyhow!("plotting the loss curves: {e}");
        {
            let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
            root.fill(&WHITE).map_err(|e| err(&e))?;
            let train: Vec<(f64, f64)> = self.epochs.iter().map(|e| (e.epoch as f64, e.train_loss as f64)).collect();
            let val: Vec<(f64, f64)> =
                self.epochs.iter().filter_map(|e| e.val_loss.map(|v| (e.epoch as f64, v as f64))).collect();
            let ymax =
                train.iter().chain(&val).map(|p| p.1).filter(|v| v.is_finite()).fold(0.0f64, f64::max).max(1e-3) * 1.05;
            let xmax = (self.epochs.len() as f64).max(2.0);
            let mut chart = ChartBuilder::on(&root)
                .caption("pre-estimator loss", ("sans-serif", 24))
                .margin(15)
                .x_label_area_size(45)
                .y_label_area_size(60)
                .build_cartesian_2d(1.0..xmax, 0.0..ymax)
                .map_err(|e| err(&e))?;
            chart
                .configure_mesh()
                .x_desc("epoch")
                .x_label_formatter(&|x| format!("{x:.0}"))
                .y_desc("loss (CE + L1)")
                .label_style(("sans-serif", 14))
                .draw()
                .map_err(|e| err(&e))?;
            for (pts, colour, name) in [(&train, BLUE, "train"), (&val, RED, "validation")] {
                if pts.is_empty() {
                    continue;
                }
                chart
                    .draw_series(LineSeries::new(pts.iter().copied(), colour.stroke_width(2)))
                    .map_err(|e| err(&e))?
                    .label(name)
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2)));
                chart
                    .draw_series(PointSeries::of_element(pts.iter().copied(), 3, colour.filled(), &|c, s, st| {
                        EmptyElement::at(c) + Circle::new((0, 0), s, st)
                    }))
                    .map_err(|e| err(&e))?;
            }
            chart
                .configure_series_labels()
                .label_font(("sans-serif", 16))
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .draw()
                .map_err(|e| err(&e))?;
            root.present().map_err(|e| err(&e))?;
        }
        crate::plot::write_rgb_png(path, w, h, buf)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn report() -> TrainReport {
        TrainReport {
            class_names: vec!["plain".into(), "twill".into()],
            epochs: (1..=4)
                .map(|e| EpochStats {
                    epoch: e,
                    train_loss: 1.0 / e as f32,
                    val_loss: Some(1.2 / e as f32),
                    val_accuracy: Some(0.5 + 0.1 * e as f32),
                    lr: 1e-3,
                    seconds: 1.0,
                })
                .collect(),
            eval_set: "validation".into(),
            n_train: 90,
            n_val: 10,
            accuracy: Some(0.9),
            confusion: vec![vec![5, 0], vec![1, 4]],
            output_errors: vec![
                OutputError { name: "m_r".into(), mae: 0.05, mae_units: 0.03, chance: 0.33, baseline: 0.25 },
                OutputError { name: "G_f".into(), mae: 0.24, mae_units: 0.24, chance: 0.33, baseline: 0.25 },
            ],
            eval_loss: 0.3,
            wall_seconds: 4.2,
        }
    }

    #[test]
    fn markdown_has_tables_and_flags() {
        let md = report().to_markdown();
        assert!(md.contains("Accuracy **90.0%**"), "{md}");
        assert!(md.contains("| twill | 1 | 4 |"), "{md}");
        assert!(md.contains("| m_r | 0.050 |"), "{md}");
        assert!(md.contains("| ok |"));
        assert!(md.contains("**Not identifiable from the image** (error ≥ 80% of the median baseline): G_f."), "{md}");
        assert!(!md.contains("m_r, G_f"));
    }

    #[test]
    fn curves_png_is_written_with_lines() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("loss.png");
        report().write_curves_png(&p).unwrap();
        let img = image::open(&p).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (800, 500));
        let blue = img.pixels().filter(|p| p[2] > 200 && p[0] < 60 && p[1] < 60).count();
        let red = img.pixels().filter(|p| p[0] > 200 && p[1] < 60 && p[2] < 60).count();
        let dark = img.pixels().filter(|p| p[0] < 60 && p[1] < 60 && p[2] < 60).count();
        assert!(blue > 500 && red > 500, "blue {blue} red {red}");
        assert!(dark > 500, "no text/axes drawn ({dark})");
    }
}
