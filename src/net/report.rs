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

/// One panel of the curves: area, title, y label, and the series (points, colour, name).
type Panel<'a, DB> = (&'a DrawingArea<DB, plotters::coord::Shift>, &'a str, &'a str, Vec<Series<'a>>);
/// One series of a panel: points, colour, legend name.
type Series<'a> = (Vec<(f64, f64)>, RGBColor, &'a str);

/// Statistics of one epoch.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpochStats {
    /// 1-based epoch number.
    pub epoch: usize,
    /// Mean training loss over the epoch's batches (weights changing meanwhile).
    pub train_loss: f32,
    /// Mean training cross-entropy of the cells.
    pub train_cell_loss: f32,
    /// Validation loss at the end of the epoch (`None` without validation samples).
    pub val_loss: Option<f32>,
    /// Validation cross-entropy of the cells.
    pub val_cell_loss: Option<f32>,
    /// Validation share of pattern cells read right.
    pub val_cell_accuracy: Option<f32>,
    /// Validation share of views whose whole pattern is read right.
    pub val_pattern_exact: Option<f32>,
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
        if let Some(a) = self.val_cell_accuracy {
            let _ = write!(s, "  cells {:.1}%", 100.0 * a);
        }
        if let Some(a) = self.val_pattern_exact {
            let _ = write!(s, "  exact {:.1}%", 100.0 * a);
        }
        let _ = write!(s, "  lr {:.2e}  {:.1} s", self.lr, self.seconds);
        s
    }
}

/// Error of one output on the evaluation set (normalised units: fractions of the range).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OutputError {
    /// Output name.
    pub name: String,
    /// Mean absolute error as a fraction of the output's range.
    pub mae: f32,
    /// Median absolute error as a fraction of the range.
    pub median_error: f32,
    /// The mean absolute error in the output's units.
    pub mae_units: f64,
    /// Mean pairwise |a − b| of the true normalised values (≈ 1/3 for uniform targets).
    pub chance: f32,
    /// Mean |t − median(t)| of the true normalised values (1/4 for uniform targets).
    pub baseline: f32,
    /// Root mean square error (fraction of the range).
    pub rmse: f32,
    /// Median of the predicted standard deviations (fraction of the range).
    pub median_sigma: f32,
    /// Share of views whose error is within two predicted standard deviations (≈ 0.95 when the
    /// confidences are calibrated).
    pub within_2_sigma: f32,
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

/// How well the views of one dataset class were read.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClassStats {
    /// Class name.
    pub name: String,
    /// Views of the class in the evaluation set.
    pub views: usize,
    /// Pattern cells of those views.
    pub cells: usize,
    /// Pattern cells read right.
    pub cells_right: usize,
    /// Views whose whole pattern was read right.
    pub exact: usize,
}

/// Everything [`super::train()`] measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainReport {
    /// Per-epoch history (including epochs done before a resume).
    pub epochs: Vec<EpochStats>,
    /// Which set the final metrics were computed on.
    pub eval_set: String,
    /// Number of training samples.
    pub n_train: usize,
    /// Number of validation samples.
    pub n_val: usize,
    /// Share of the views' grid cells read right, each grid cell on its own.
    pub grid_cell_accuracy: f32,
    /// Share of pattern cells read right, from the logits averaged over the grid cells that
    /// show the same pattern cell (what the fit uses).
    pub cell_accuracy: f32,
    /// Share of views whose whole pattern was read right.
    pub pattern_exact: f32,
    /// Pattern cells: `cell_confusion[true][read]`, 0 = warp on top, 1 = weft on top.
    pub cell_confusion: [[u32; 2]; 2],
    /// Per dataset class.
    pub per_class: Vec<ClassStats>,
    /// Per-output error.
    pub output_errors: Vec<OutputError>,
    /// Share of views whose ply count `n_p` is exact after rounding (`None` without that output).
    pub ply_exact: Option<f32>,
    /// Loss on the evaluation set with the final weights.
    pub eval_loss: f32,
    /// Wall time of the `train` call, seconds (epochs done before a resume are in `epochs`).
    pub wall_seconds: f64,
}

impl TrainReport {
    /// Write a Markdown report: cell and pattern accuracy, the cell confusion, per-class
    /// results, per-output errors with confidences and verdicts, and the history.
    pub fn write_markdown(&self, path: &Path) -> Result<()> {
        super::infer::write_atomic(path, self.to_markdown().as_bytes())
    }

    /// The Markdown text of [`Self::write_markdown`].
    pub fn to_markdown(&self) -> String {
        let mut s = String::new();
        let w = &mut s;
        let pct = |x: f32| format!("{:.1}%", 100.0 * x);
        let _ = writeln!(w, "# Pre-estimator training report\n");
        let train_s: f64 = self.epochs.iter().map(|e| e.seconds).sum();
        let _ = writeln!(
            w,
            "{} training / {} validation views, {} epochs ({:.1} s in epochs, {:.1} s this run). Metrics on the **{}** set, loss {:.4}.\n",
            self.n_train,
            self.n_val,
            self.epochs.len(),
            train_s,
            self.wall_seconds,
            self.eval_set,
            self.eval_loss
        );
        let _ = writeln!(w, "## Pattern\n");
        let _ = writeln!(
            w,
            "Pattern cells read right: **{}** (logits averaged over the grid cells showing the same pattern cell; each grid cell alone: {}). Whole pattern exact: **{}** of the views.\n",
            pct(self.cell_accuracy),
            pct(self.grid_cell_accuracy),
            pct(self.pattern_exact)
        );
        let c = &self.cell_confusion;
        let _ = writeln!(w, "| true \\ read | warp on top | weft on top |\n|---|---:|---:|");
        let _ =
            writeln!(w, "| warp on top | {} | {} |\n| weft on top | {} | {} |\n", c[0][0], c[0][1], c[1][0], c[1][1]);
        if !self.per_class.is_empty() {
            let _ = writeln!(w, "| dataset class | views | cells right | pattern exact |\n|---|---:|---:|---:|");
            for k in self.per_class.iter().filter(|k| k.views > 0) {
                let _ = writeln!(
                    w,
                    "| {} | {} | {} | {} |",
                    k.name,
                    k.views,
                    pct(k.cells_right as f32 / k.cells.max(1) as f32),
                    pct(k.exact as f32 / k.views as f32)
                );
            }
            let _ = writeln!(w);
        }
        if !self.output_errors.is_empty() {
            let _ = writeln!(w, "## Outputs\n");
            let _ = writeln!(
                w,
                "Errors as fractions of each output's range. *Baseline*: the error of always answering the median (1/4 for uniform targets); a network that cannot see a parameter ends there, so the verdict uses MAE / baseline (not identifiable ≥ {NOT_IDENTIFIABLE}, weak ≥ {WEAK}). *σ*: the median predicted standard deviation; *within 2σ*: the share of views whose error is inside twice their own predicted σ (0.95 if calibrated).\n"
            );
            let _ = writeln!(
                w,
                "| output | median error | MAE | MAE (units) | baseline | MAE / baseline | σ | within 2σ | verdict |"
            );
            let _ = writeln!(w, "|---|---:|---:|---:|---:|---:|---:|---:|---|");
            for e in &self.output_errors {
                let _ = writeln!(
                    w,
                    "| {} | {:.3} | {:.3} | {:.4} | {:.3} | {:.2} | {:.3} | {} | {} |",
                    e.name,
                    e.median_error,
                    e.mae,
                    e.mae_units,
                    e.baseline,
                    e.ratio(),
                    e.median_sigma,
                    pct(e.within_2_sigma),
                    e.verdict()
                );
            }
            if let Some(p) = self.ply_exact {
                let _ = writeln!(w, "\nPly count `n_p` exact after rounding: **{}** of the views.", pct(p));
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
        let _ = writeln!(
            w,
            "## History\n\n| epoch | train loss | train cell loss | val loss | val cell loss | val cells right | val pattern exact | lr | s |"
        );
        let _ = writeln!(w, "|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
        let opt = |v: Option<f32>, f: &dyn Fn(f32) -> String| v.map_or("–".into(), f);
        for e in &self.epochs {
            let _ = writeln!(
                w,
                "| {} | {:.4} | {:.4} | {} | {} | {} | {} | {:.2e} | {:.1} |",
                e.epoch,
                e.train_loss,
                e.train_cell_loss,
                opt(e.val_loss, &|v| format!("{v:.4}")),
                opt(e.val_cell_loss, &|v| format!("{v:.4}")),
                opt(e.val_cell_accuracy, &|v| pct(v)),
                opt(e.val_pattern_exact, &|v| pct(v)),
                e.lr,
                e.seconds
            );
        }
        s
    }

    /// Learning curves as a PNG (1000×450): the cells' cross-entropy (train, validation) per
    /// epoch on the left, the validation share of cells read right and of whole patterns exact
    /// on the right.
    pub fn write_curves_png(&self, path: &Path) -> Result<()> {
        crate::plot::register_font();
        let (w, h) = (1000u32, 450u32);
        let mut buf = vec![0u8; (w * h * 3) as usize];
        let err = |e: &dyn std::fmt::Display| anyhow::anyhow!("plotting the learning curves: {e}");
        {
            let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
            root.fill(&WHITE).map_err(|e| err(&e))?;
            let (left, right) = root.split_horizontally(w / 2);
            let xmax = (self.epochs.len() as f64).max(2.0);
            let ep = |f: &dyn Fn(&EpochStats) -> Option<f32>| -> Vec<(f64, f64)> {
                self.epochs.iter().filter_map(|e| f(e).map(|v| (e.epoch as f64, v as f64))).collect()
            };
            let panels: [Panel<'_, _>; 2] = [
                (
                    &left,
                    "cell cross-entropy",
                    "BCE",
                    vec![
                        (ep(&|e| Some(e.train_cell_loss)), BLUE, "train"),
                        (ep(&|e| e.val_cell_loss), RED, "validation"),
                    ],
                ),
                (
                    &right,
                    "validation reading",
                    "share",
                    vec![
                        (ep(&|e| e.val_cell_accuracy), RGBColor(0, 150, 0), "cells right"),
                        (ep(&|e| e.val_pattern_exact), RGBColor(200, 0, 200), "pattern exact"),
                    ],
                ),
            ];
            for (area, title, ylab, series) in panels {
                let ymax = series
                    .iter()
                    .flat_map(|s| s.0.iter().map(|p| p.1))
                    .filter(|v| v.is_finite())
                    .fold(0.0f64, f64::max)
                    .max(1e-3)
                    * 1.05;
                let ymax = if ylab == "share" { 1.0 } else { ymax };
                let mut chart = ChartBuilder::on(area)
                    .caption(title, ("sans-serif", 22))
                    .margin(15)
                    .x_label_area_size(40)
                    .y_label_area_size(55)
                    .build_cartesian_2d(1.0..xmax, 0.0..ymax)
                    .map_err(|e| err(&e))?;
                chart
                    .configure_mesh()
                    .x_desc("epoch")
                    .x_label_formatter(&|x| format!("{x:.0}"))
                    .y_desc(ylab)
                    .label_style(("sans-serif", 14))
                    .draw()
                    .map_err(|e| err(&e))?;
                for (pts, colour, name) in series {
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
                    .position(SeriesLabelPosition::LowerRight)
                    .label_font(("sans-serif", 15))
                    .background_style(WHITE.mix(0.8))
                    .border_style(BLACK)
                    .draw()
                    .map_err(|e| err(&e))?;
            }
            root.present().map_err(|e| err(&e))?;
        }
        crate::plot::write_rgb_png(path, w, h, buf)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn report() -> TrainReport {
        let err = |name: &str, mae: f32| OutputError {
            name: name.into(),
            mae,
            median_error: mae * 0.8,
            mae_units: mae as f64 * 4.0,
            chance: 0.33,
            baseline: 0.25,
            rmse: mae * 1.2,
            median_sigma: 0.05,
            within_2_sigma: 0.93,
        };
        TrainReport {
            epochs: (1..=4)
                .map(|e| EpochStats {
                    epoch: e,
                    train_loss: 1.0 / e as f32,
                    train_cell_loss: 0.7 / e as f32,
                    val_loss: Some(1.2 / e as f32),
                    val_cell_loss: Some(0.8 / e as f32),
                    val_cell_accuracy: Some(0.5 + 0.1 * e as f32),
                    val_pattern_exact: Some(0.1 * e as f32),
                    lr: 1e-3,
                    seconds: 1.0,
                })
                .collect(),
            eval_set: "validation".into(),
            n_train: 90,
            n_val: 10,
            grid_cell_accuracy: 0.95,
            cell_accuracy: 0.97,
            pattern_exact: 0.8,
            cell_confusion: [[40, 2], [1, 37]],
            per_class: vec![
                ClassStats { name: "plain".into(), views: 4, cells: 16, cells_right: 16, exact: 4 },
                ClassStats { name: "satin8".into(), views: 0, cells: 0, cells_right: 0, exact: 0 },
                ClassStats { name: "twill".into(), views: 6, cells: 64, cells_right: 60, exact: 4 },
            ],
            output_errors: vec![err("r_e", 0.05), err("alpha_s", 0.24)],
            ply_exact: Some(0.6),
            eval_loss: 0.3,
            wall_seconds: 4.2,
        }
    }

    #[test]
    fn markdown_has_tables_and_flags() {
        let md = report().to_markdown();
        assert!(md.contains("Pattern cells read right: **97.0%**"), "{md}");
        assert!(md.contains("Whole pattern exact: **80.0%**"), "{md}");
        assert!(md.contains("| weft on top | 1 | 37 |"), "{md}");
        assert!(md.contains("| twill | 6 | 93.8% | 66.7% |"), "{md}");
        assert!(!md.contains("| satin8 |"), "classes without views are left out");
        assert!(md.contains("| r_e | 0.040 | 0.050 | 0.2000 |"), "{md}");
        assert!(md.contains("| ok |"));
        assert!(md.contains("Ply count `n_p` exact after rounding: **60.0%**"), "{md}");
        assert!(
            md.contains("**Not identifiable from the image** (error ≥ 80% of the median baseline): alpha_s."),
            "{md}"
        );
        assert!(md.contains("| 4 | 0.2500 | 0.1750 | 0.3000 | 0.2000 | 90.0% | 40.0% |"), "{md}");
    }

    #[test]
    fn curves_png_is_written_with_lines() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("curves.png");
        report().write_curves_png(&p).unwrap();
        let img = image::open(&p).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (1000, 450));
        let count = |f: &dyn Fn(&image::Rgb<u8>) -> bool| img.pixels().filter(|p| f(p)).count();
        let blue = count(&|p| p[2] > 200 && p[0] < 60 && p[1] < 60);
        let red = count(&|p| p[0] > 200 && p[1] < 60 && p[2] < 60);
        let green = count(&|p| p[1] > 120 && p[0] < 60 && p[2] < 60);
        let magenta = count(&|p| p[0] > 170 && p[2] > 170 && p[1] < 60);
        let dark = count(&|p| p[0] < 60 && p[1] < 60 && p[2] < 60);
        assert!(blue > 300 && red > 300 && green > 300 && magenta > 300, "{blue} {red} {green} {magenta}");
        assert!(dark > 500, "no text/axes drawn ({dark})");
    }
}
