//! `woven export`: yarn geometry for other renderers (PLY curves and tubes, Mitsuba 3 scene).

use super::stdout::outln;
use anyhow::Result;
use clap::Args;
use std::path::PathBuf;
use woven::export::{export, ExportOptions, MAX_REPEATS};

/// Arguments of `woven export`.
#[derive(Args, Clone, Debug)]
pub struct ExportArgs {
    /// Parameter file (JSON) of a fit or of `woven params`.
    pub params: PathBuf,
    /// Output directory (created if missing).
    #[arg(long, default_value = "export")]
    pub out: PathBuf,
    /// Pattern repeats: `N` (N×N) or `NxM` (N along x, M along y). Default: enough to cover the
    /// scene's view (at least 1×1).
    #[arg(long, value_parser = parse_repeats)]
    pub repeats: Option<[u32; 2]>,
    /// Also export the plies as separate thinner tubes following their helices (`plies.ply`).
    #[arg(long)]
    pub plies: bool,
    /// Curve samples per pattern cell for the polylines and tube meshes.
    #[arg(long, default_value_t = 16)]
    pub samples_per_cell: u32,
    /// Vertices around each tube.
    #[arg(long, default_value_t = 12)]
    pub ring: u32,
    /// Write the tube meshes as ASCII PLY instead of binary.
    #[arg(long)]
    pub ascii: bool,
}

/// Parse `N` or `NxM` (each in 1..=[`MAX_REPEATS`]).
pub fn parse_repeats(s: &str) -> Result<[u32; 2], String> {
    let parts: Vec<&str> = s.trim().split(['x', 'X']).collect();
    let num = |t: &str| -> Result<u32, String> {
        let n: u32 = t.trim().parse().map_err(|_| format!("`{s}`: expected N or NxM with whole numbers"))?;
        if n == 0 || n > MAX_REPEATS {
            return Err(format!("`{s}`: repeats must be in 1..={MAX_REPEATS}"));
        }
        Ok(n)
    };
    match parts.as_slice() {
        [n] => num(n).map(|n| [n, n]),
        [a, b] => Ok([num(a)?, num(b)?]),
        _ => Err(format!("`{s}`: expected N or NxM")),
    }
}

/// `woven export`.
pub fn run(args: &ExportArgs) -> Result<()> {
    let params = super::load_params(&args.params)?;
    let opts = ExportOptions {
        repeats: args.repeats,
        plies: args.plies,
        samples_per_cell: args.samples_per_cell,
        ring: args.ring,
        ascii: args.ascii,
    };
    let s = export(&params, &args.out, &opts)?;
    outln!(
        "exported {}x{} repeats ({} weft + {} warp curves) to {}{}",
        s.repeats[0],
        s.repeats[1],
        s.weft_curves,
        s.warp_curves,
        s.dir.display(),
        if s.clamped { " (view clamped)" } else { "" }
    );
    outln!("  files: {}", s.files.join(", "));
    outln!("  units: pitch = {} (renderer units); open scene.xml with mitsuba.load_file", s.pitch);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn repeats_parse() {
        assert_eq!(parse_repeats("3").unwrap(), [3, 3]);
        assert_eq!(parse_repeats("2x5").unwrap(), [2, 5]);
        assert!(parse_repeats("0").is_err() && parse_repeats("a").is_err() && parse_repeats("1x2x3").is_err());
        assert!(parse_repeats("65").is_err() && parse_repeats("2x").is_err());
    }
}
