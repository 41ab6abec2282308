//! `woven bench` and `woven stress`: forward-model benchmark and numerical stress test, each
//! printed and written as a section of a markdown file (`docs/benchmarks.md`).

use super::progress::IndicatifProgress;
use super::stdout::out;
use anyhow::{bail, Result};
use clap::Args;
use std::path::PathBuf;
use woven::bench::replace_section;

/// Arguments of `woven bench`.
#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Markdown output (appends/replaces the forward-model section).
    #[arg(long, default_value = "docs/benchmarks.md")]
    pub out: PathBuf,
    /// Quick run (fewer repetitions, lower reference spp).
    #[arg(long)]
    pub quick: bool,
    /// Python interpreter with Mitsuba 3 installed, for the side-by-side timing (default: the
    /// `WOVEN_MITSUBA_PYTHON` environment variable, else `python3`); without Mitsuba the section
    /// says so and the bench carries on.
    #[arg(long, value_name = "PATH")]
    pub mitsuba_python: Option<PathBuf>,
    /// Skip the side-by-side timing with Mitsuba 3.
    #[arg(long, conflicts_with = "mitsuba_python")]
    pub no_mitsuba: bool,
}

impl BenchArgs {
    /// The interpreter for Mitsuba: the flag, else `WOVEN_MITSUBA_PYTHON` (when not empty), else
    /// `python3`; `None` with `--no-mitsuba`.
    pub fn mitsuba_python(&self) -> Option<PathBuf> {
        if self.no_mitsuba {
            return None;
        }
        self.mitsuba_python
            .clone()
            .or_else(|| std::env::var_os("WOVEN_MITSUBA_PYTHON").filter(|v| !v.is_empty()).map(PathBuf::from))
            .or_else(|| Some(PathBuf::from("python3")))
    }
}

/// `woven bench`.
pub fn run_bench(a: &BenchArgs) -> Result<()> {
    let mitsuba = woven::bench::MitsubaBench { python: a.mitsuba_python(), woven_exe: std::env::current_exe().ok() };
    let md = woven::bench::run(a.quick, &mitsuba, &IndicatifProgress::new(true))?;
    out!("{md}");
    replace_section(&a.out, "Forward model", &md)?;
    eprintln!("wrote {}", a.out.display());
    Ok(())
}

/// Arguments of `woven stress`.
#[derive(Args, Debug)]
pub struct StressArgs {
    /// Number of random evaluations.
    #[arg(long, default_value_t = 10_000_000)]
    pub count: u64,
    /// Markdown output.
    #[arg(long, default_value = "docs/benchmarks.md")]
    pub out: PathBuf,
    /// Seed.
    #[arg(long, default_value_t = 7, allow_negative_numbers = true, value_parser = super::parse_seed)]
    pub seed: u64,
}

/// `woven stress`: fails (non-zero exit) when any NaN/Inf or negative value was found.
pub fn run_stress(a: &StressArgs) -> Result<()> {
    let rep = woven::stress::stress(a.count, a.seed, &IndicatifProgress::new(true));
    let md = rep.markdown(a.count, a.seed);
    out!("{md}");
    replace_section(&a.out, "Numerical stress", &md)?;
    if !rep.clean() {
        bail!("{} non-finite and {} negative values found", rep.non_finite, rep.negative);
    }
    Ok(())
}
