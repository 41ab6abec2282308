//! Numerical stress test.
use anyhow::Result;
use std::path::Path;
/// Run the stress test.
pub fn run(_n: u64, _s: u64, _out: &Path) -> Result<()> {
    anyhow::bail!("not yet")
}
