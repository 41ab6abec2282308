//! The `woven` command line (binary only): argument types, progress bars, Ctrl-C and printing over
//! the library, which has no CLI dependency. One file per command group; each holds the clap
//! argument struct(s) of its commands and a `run` function that parses the rest, calls the library
//! and prints.

pub mod bench;
pub mod datagen;
pub mod export;
pub mod fit;
pub mod net;
pub mod prep;
pub mod progress;
pub mod render;
pub mod stdout;

use anyhow::{Context, Result};
use std::path::Path;
use woven::params::{ParamError, ParamFile};

/// Read, parse and validate a parameter file given on the command line: a regular file of at most
/// [`woven::io::MAX_PARAM_FILE_BYTES`] (a FIFO would block, `/dev/zero` would fill memory), whose
/// weave pattern is woven (no yarn floating over the whole fabric).
pub fn load_params(path: &Path) -> Result<ParamFile> {
    let text = woven::io::read_text_capped(path, woven::io::MAX_PARAM_FILE_BYTES)
        .map_err(|source| ParamError::Io { path: path.display().to_string(), source })?;
    let p = ParamFile::from_json(&text).with_context(|| format!("in {}", path.display()))?;
    p.cloth.pattern.check_woven().with_context(|| format!("in {}", path.display()))?;
    Ok(p)
}

/// Clap value parser of `--seed`: a non-negative integer, with a hint instead of clap's bare
/// "unexpected argument" (the argument must also allow a leading `-`, or clap takes `-1` for a flag).
pub fn parse_seed(s: &str) -> Result<u64, String> {
    s.trim().parse::<u64>().map_err(|_| format!("seed must be a non-negative integer (0 to {}), got `{s}`", u64::MAX))
}

/// Clap value parser of `--threads`: `1..=`[`woven::render::MAX_THREADS`].
pub fn parse_threads(s: &str) -> Result<usize, String> {
    let max = woven::render::MAX_THREADS;
    match s.trim().parse::<usize>() {
        Ok(n) if (1..=max).contains(&n) => Ok(n),
        _ => Err(format!("threads must be a whole number from 1 to {max}, got `{s}`")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seeds_and_threads_parse_with_hints() {
        assert_eq!(parse_seed("7"), Ok(7));
        assert!(parse_seed("-1").unwrap_err().contains("non-negative integer"));
        assert!(parse_seed("x").is_err());
        assert_eq!(parse_threads("2"), Ok(2));
        for bad in ["0", "5000", "-3", "two"] {
            assert!(parse_threads(bad).unwrap_err().contains("from 1 to"), "{bad}");
        }
    }
}
