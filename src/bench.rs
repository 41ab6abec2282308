//! Forward-model benchmark (`woven bench`): time vs error, thread scaling, re-shading, and what
//! each skip saves. Results are written into a section of `docs/benchmarks.md`.

use anyhow::{Context, Result};
use std::path::Path;

/// Replace (or append) the `## {title}` section of a markdown file with `body`.
pub fn replace_section(path: &Path, title: &str, body: &str) -> Result<()> {
    let old = std::fs::read_to_string(path)
        .unwrap_or_else(|_| "# Benchmarks\n\nMachine: 2 cores, 24 GiB (the project's standard machine).\n".into());
    let head = format!("## {title}\n");
    let section = format!("{head}\n{body}\n");
    let new = match old.find(&head) {
        Some(start) => {
            let rest = &old[start + head.len()..];
            let end = rest.find("\n## ").map(|e| start + head.len() + e + 1).unwrap_or(old.len());
            format!("{}{}{}", &old[..start], section, &old[end..])
        }
        None => format!("{}\n{}", old.trim_end(), format!("\n{section}")),
    };
    crate::io::write_atomic(path, new.as_bytes()).with_context(|| format!("writing {}", path.display()))
}

/// Run the benchmark.
pub fn run(_out: &Path, _quick: bool) -> Result<()> {
    anyhow::bail!("not yet")
}
