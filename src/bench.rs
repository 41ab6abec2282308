//! Forward-model benchmark (filled in below).
use anyhow::Result;
use std::path::Path;
/// Run the benchmark.
pub fn run(_out: &Path, _quick: bool) -> Result<()> {
    anyhow::bail!("not yet")
}
