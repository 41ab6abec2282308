//! The evaluation's report: per-target table, run time against error, per-parameter error over
//! all targets and over those whose picture determines the parameter, and the summary line.

use super::demo::param_names;
use super::eval::{Ablation, EvalCase};

/// Summary of `woven eval`.
#[derive(Clone, Debug)]
pub struct EvalReport {
    /// Arguments.
    pub ablation: Ablation,
    /// Cases.
    pub cases: Vec<EvalCase>,
    /// Iterations per fit.
    pub iterations: usize,
    /// Threads.
    pub threads: usize,
}

/// The `q` quantile of `v` (nearest rank; NaN for an empty slice).
pub fn quantile(v: &[f32], q: f32) -> f32 {
    if v.is_empty() {
        return f32::NAN;
    }
    let mut s = v.to_vec();
    s.sort_by(f32::total_cmp);
    s[((s.len() - 1) as f32 * q).round() as usize]
}

impl EvalReport {
    /// Fraction of exact patterns.
    pub fn pattern_exact(&self) -> f32 {
        self.cases.iter().filter(|c| c.exact).count() as f32 / self.cases.len().max(1) as f32
    }
    fn all_errors(&self) -> Vec<f32> {
        self.cases.iter().flat_map(|c| c.errors.iter().copied()).collect()
    }
    /// Errors of the parameters each target determines.
    pub fn identifiable_errors(&self) -> Vec<f32> {
        self.cases
            .iter()
            .flat_map(|c| c.errors.iter().zip(&c.identifiable).filter(|(_, &ok)| ok).map(|(e, _)| *e))
            .collect()
    }
    /// The last line of `woven eval`.
    pub fn summary_line(&self) -> String {
        let e = self.identifiable_errors();
        let all = self.all_errors();
        let psnr = self.cases.iter().map(|c| c.psnr_db).sum::<f32>() / self.cases.len().max(1) as f32;
        let secs = self.cases.iter().map(|c| c.secs).sum::<f64>() / self.cases.len().max(1) as f64;
        format!(
            "eval: pattern_exact={:.2} median_err={:.3} p90_err={:.2} psnr_db={:.1} fit_s={:.1} median_err_all={:.3} identifiable={}/{} relit_db={:.1}",
            self.pattern_exact(),
            quantile(&e, 0.5),
            quantile(&e, 0.9),
            psnr,
            secs,
            quantile(&all, 0.5),
            e.len(),
            all.len(),
            self.cases.iter().map(|c| (c.relit_db[0] + c.relit_db[1]) / 2.0).sum::<f32>() / self.cases.len().max(1) as f32
        )
    }
    /// Markdown section for docs/benchmarks.md.
    pub fn markdown(&self) -> String {
        let mut s = format!(
            "## Fit evaluation (`woven eval --ablation {}`)\n\n{} random synthetic one-repeat targets (half presets, half random \
             patterns without floating yarns; appearance uniform in Table 1), {} iterations, {} threads. Error = |fit − true| as a \
             fraction of the Table-1 range over the 30 appearance scalars, r_e, r_a, n_p, n_f.\n\n",
            self.ablation.name(),
            self.cases.len(),
            self.iterations,
            self.threads
        );
        s += "| # | true pattern | fitted | exact | median err | p90 err | PSNR dB | front-lit PSNR | back-lit PSNR | fit s |\n|---|---|---|---|---|---|---|---|---|---|\n";
        for (i, c) in self.cases.iter().enumerate() {
            s += &format!(
                "| {i} | `{}` | `{}` | {} | {:.3} | {:.3} | {:.1} | {:.1} | {:.1} | {:.1} |\n",
                c.truth,
                c.fit,
                if c.exact { "yes" } else { "no" },
                quantile(&c.errors, 0.5),
                quantile(&c.errors, 0.9),
                c.psnr_db,
                c.relit_db[0],
                c.relit_db[1],
                c.secs
            );
        }
        s += "\nRun time vs error (best state after k iterations; k = 0 is the pre-estimate):\n\n| k | mean s | median err |\n|---|---|---|\n";
        let n_ck = self.cases.iter().map(|c| c.curve.len()).min().unwrap_or(0);
        for i in 0..n_ck {
            let k = self.cases[0].curve[i].0;
            let secs = self.cases.iter().map(|c| c.curve[i].1).sum::<f64>() / self.cases.len() as f64;
            let med: Vec<f32> = self.cases.iter().map(|c| c.curve[i].2).collect();
            s += &format!("| {k} | {secs:.1} | {:.3} |\n", quantile(&med, 0.5));
        }
        s += "\nPer-parameter error, % of the Table-1 range (median / 90th percentile over the targets, the format of \
               Table 2 of Li et al. 2024 [Li24]), and over the targets whose picture determines the parameter \
               (Cramér–Rao bound ≤ 2.5 % of the range, `src/fit/identify.rs`; radii always, n_p and n_f never counted):\n\n\
               | parameter | median % | p90 % | identifiable in | median % there |\n|---|---|---|---|---|\n";
        for (k, name) in param_names().iter().enumerate() {
            let v: Vec<f32> = self.cases.iter().filter_map(|c| c.errors.get(k).copied()).collect();
            let idv: Vec<f32> = self
                .cases
                .iter()
                .filter(|c| c.identifiable.get(k).copied().unwrap_or(false))
                .filter_map(|c| c.errors.get(k).copied())
                .collect();
            let there = if idv.is_empty() { "–".to_string() } else { format!("{:.1}", 100.0 * quantile(&idv, 0.5)) };
            s += &format!(
                "| `{name}` | {:.1} | {:.1} | {}/{} | {there} |\n",
                100.0 * quantile(&v, 0.5),
                100.0 * quantile(&v, 0.9),
                idv.len(),
                self.cases.len()
            );
        }
        let sub = self.subset_errors();
        s += &format!(
            "\nBody colours and radii only (`r_b_e`, `r_b_a`, `r_e`, `r_a`, the parameters every view shows): median {:.1} %, \
             p90 {:.1} %.\n",
            100.0 * quantile(&sub, 0.5),
            100.0 * quantile(&sub, 0.9)
        );
        s += &format!("\n`{}`\n", self.summary_line());
        s
    }

    /// Errors of the body colours and radii over all cases.
    pub fn subset_errors(&self) -> Vec<f32> {
        let names = param_names();
        let keep: Vec<usize> = names
            .iter()
            .enumerate()
            .filter(|(_, n)| n.starts_with("r_b_") || *n == "r_e" || *n == "r_a")
            .map(|(k, _)| k)
            .collect();
        self.cases.iter().flat_map(|c| keep.iter().filter_map(|&k| c.errors.get(k).copied())).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn case(exact: bool, err: f32, identifiable: bool) -> EvalCase {
        let n = param_names().len();
        EvalCase {
            truth: "10/01".into(),
            fit: if exact { "10/01".into() } else { "1100/0110/0011/1001".into() },
            exact,
            errors: vec![err; n],
            psnr_db: 30.0,
            secs: 2.0,
            curve: vec![(0, 0.5, 2.0 * err), (10, 1.0, err)],
            grid_ok: true,
            relit_db: [28.0, 26.0],
            identifiable: vec![identifiable; n],
            error: None,
        }
    }

    #[test]
    fn quantiles_take_the_nearest_rank() {
        assert_eq!(quantile(&[3.0, 1.0, 2.0], 0.5), 2.0);
        assert_eq!(quantile(&[4.0, 1.0, 3.0, 2.0], 0.9), 4.0);
        assert_eq!(quantile(&[4.0, 1.0, 3.0, 2.0], 0.0), 1.0);
        assert!(quantile(&[], 0.5).is_nan());
    }

    #[test]
    fn report_counts_exact_patterns_and_identifiable_errors() {
        let rep = EvalReport {
            ablation: Ablation::NoPre,
            cases: vec![case(true, 0.02, true), case(false, 0.2, false)],
            iterations: 10,
            threads: 2,
        };
        assert_eq!(rep.pattern_exact(), 0.5);
        assert!(rep.identifiable_errors().iter().all(|e| *e == 0.02));
        assert_eq!(rep.subset_errors().len(), 2 * 8);
        let line = rep.summary_line();
        assert!(line.starts_with("eval: pattern_exact=0.50 median_err=0.020"), "{line}");
        assert!(line.contains("relit_db=27.0"), "{line}");
        let md = rep.markdown();
        assert!(
            md.contains("`woven eval --ablation no-pre`")
                && md.contains("| 1 | `10/01` | `1100/0110/0011/1001` | no |"),
            "{md}"
        );
        assert!(md.contains("| 10 | 1.0 |"), "{md}");
    }
}
