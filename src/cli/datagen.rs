//! `woven generate`: the synthetic training set, with Ctrl-C handling (finish the images in flight,
//! keep the folder resumable; a second Ctrl-C quits at once).

use super::progress::IndicatifProgress;
use anyhow::{bail, Context, Result};
use clap::Args;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, OnceLock};
use woven::datagen::{generate, GenerateOptions, Interrupted, Recipe};

/// Arguments of `woven generate`.
#[derive(Args, Clone, Debug)]
pub struct GenerateArgs {
    /// Number of images (default: the recipe's `count`).
    #[arg(long)]
    pub count: Option<usize>,
    /// Output directory (created; a rerun resumes, a larger --count extends).
    #[arg(long)]
    pub out: PathBuf,
    /// Recipe file (default: the built-in copy of the repository's `datagen/recipe.toml`).
    #[arg(long)]
    pub recipe: Option<PathBuf>,
    /// Image side in pixels (default: the recipe's `image.size`).
    #[arg(long)]
    pub size: Option<u32>,
    /// Dataset seed (default: the recipe's `seed`).
    #[arg(long, allow_negative_numbers = true, value_parser = super::parse_seed)]
    pub seed: Option<u64>,
    /// Render only indices ≡ i (mod K), e.g. `--shard 0/4`.
    #[arg(long, value_parser = parse_shard)]
    pub shard: Option<(usize, usize)>,
    /// Also write linear EXR images.
    #[arg(long)]
    pub exr: bool,
    /// Worker threads (default: all cores).
    #[arg(long, allow_negative_numbers = true, value_parser = super::parse_threads)]
    pub threads: Option<usize>,
}

/// Arguments of `woven merge`.
#[derive(Args, Clone, Debug)]
pub struct MergeArgs {
    /// Output folder of the merged set (new, one of the shard folders, or an earlier merge).
    #[arg(long)]
    pub out: PathBuf,
    /// The shard folders (each the --out of a finished `woven generate --shard i/K`).
    #[arg(required = true)]
    pub shards: Vec<PathBuf>,
}

/// `woven merge`.
pub fn run_merge(args: &MergeArgs) -> Result<()> {
    let s = woven::datagen::merge(&args.shards, &args.out, &IndicatifProgress::new(true))
        .with_context(|| format!("merging {} shard folders into {}", args.shards.len(), args.out.display()))?;
    eprintln!(
        "merge: {} images from {} shards into {} ({} files copied); labels.jsonl, manifest.json, preview.png written",
        s.count,
        s.shards,
        args.out.display(),
        s.copied
    );
    Ok(())
}

/// Parse `i/K` with `0 <= i < K`.
pub fn parse_shard(s: &str) -> Result<(usize, usize), String> {
    let (a, b) = s.split_once('/').ok_or_else(|| format!("shard `{s}`: expected i/K, e.g. 0/4"))?;
    let i: usize = a.trim().parse().map_err(|_| format!("shard `{s}`: i is not a number"))?;
    let k: usize = b.trim().parse().map_err(|_| format!("shard `{s}`: K is not a number"))?;
    if k == 0 || i >= k {
        return Err(format!("shard `{s}`: need 0 <= i < K"));
    }
    Ok((i, k))
}

/// The stop flag the library polls, set by the first Ctrl-C (installed once per process).
fn cancel_flag() -> Arc<AtomicBool> {
    static FLAG: OnceLock<Arc<AtomicBool>> = OnceLock::new();
    FLAG.get_or_init(|| {
        let flag = Arc::new(AtomicBool::new(false));
        let f = flag.clone();
        let res = ctrlc::set_handler(move || {
            if f.swap(true, Ordering::SeqCst) {
                eprintln!("\ngenerate: second interrupt, exiting now (finished images are kept; rerun to resume)");
                std::process::exit(130);
            }
            eprintln!("\ngenerate: interrupt received; finishing the images in flight (Ctrl-C again to quit now)");
        });
        if let Err(e) = res {
            eprintln!("generate: warning: cannot install the Ctrl-C handler: {e}");
        }
        flag
    })
    .clone()
}

fn resume_command(args: &GenerateArgs) -> String {
    let mut c = format!("woven generate --out {}", args.out.display());
    if let Some(r) = &args.recipe {
        c += &format!(" --recipe {}", r.display());
    }
    if let Some(n) = args.count {
        c += &format!(" --count {n}");
    }
    if let Some(s) = args.size {
        c += &format!(" --size {s}");
    }
    if let Some(s) = args.seed {
        c += &format!(" --seed {s}");
    }
    if let Some((i, k)) = args.shard {
        c += &format!(" --shard {i}/{k}");
    }
    if args.exr {
        c += " --exr";
    }
    c
}

/// `woven generate`.
pub fn run(args: &GenerateArgs) -> Result<()> {
    let recipe = match &args.recipe {
        Some(path) => Recipe::load(path)?,
        None => Recipe::embedded(),
    };
    let mut opts = GenerateOptions::new(&args.out, recipe);
    opts.count = args.count;
    opts.size = args.size;
    opts.seed = args.seed;
    opts.shard = args.shard.unwrap_or((0, 1));
    opts.exr = args.exr;
    opts.threads = args.threads;
    opts.cancel = Some(cancel_flag());
    match generate(&opts, &IndicatifProgress::new(true)) {
        Ok(s) => {
            eprintln!(
                "generate: rendered {}, skipped {} (already done), {} of {} present, wall {:.1} s, {:.2} images/s",
                s.rendered, s.skipped, s.present, s.count, s.wall_s, s.images_per_s
            );
            if s.complete {
                eprintln!("generate: complete: {} (labels.jsonl, manifest.json, preview.png)", args.out.display());
            } else {
                eprintln!(
                    "generate: shard done; labels.jsonl/manifest.json/preview.png are written once all {} images are present (rerun without --shard to finish or check)",
                    s.count
                );
            }
            Ok(())
        }
        Err(e) => {
            if let Some(i) = e.downcast_ref::<Interrupted>() {
                bail!(
                    "interrupted: rendered {} images, {} remain; the directory is consistent. Resume with:\n  {}",
                    i.rendered,
                    i.remaining,
                    resume_command(args)
                );
            }
            Err(e).context("generate failed")
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shards_parse() {
        assert_eq!(parse_shard("1/4"), Ok((1, 4)));
        assert!(parse_shard("4/4").is_err() && parse_shard("0/0").is_err() && parse_shard("x").is_err());
    }
}
