//! Rendering a dataset into a directory: resumable, shardable, byte-for-byte deterministic.
//!
//! Layout of `DIR`:
//! - `images/NNNNNN.png` (sRGB, + `NNNNNN.exr` linear with `exr`), `labels/NNNNNN.json` (one
//!   label line; written last, so it marks the image as finished);
//! - `labels.jsonl`, `manifest.json`, `preview.png`: rebuilt from the per-image files whenever
//!   every image of the set is present, so they do not depend on how the set was produced;
//! - `dataset.json`: the recipe identity (recipe SHA-256 without `count`, seed), refusing a rerun
//!   with another recipe or seed into the same directory;
//! - `runs.jsonl`: one line per run with its timing (the only file that differs between runs).

use super::recipe::{PatternClass, Recipe};
use super::sample::{target_names, Label, Sample};
use super::sheet::contact_sheet;
use crate::io::write_atomic;
use crate::progress::Progress;
use crate::render::{Prepared, RenderOptions};
use anyhow::{anyhow, bail, Context, Result};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// What to generate and how.
#[derive(Clone, Debug)]
pub struct GenerateOptions {
    /// Output directory.
    pub out: PathBuf,
    /// The recipe (before the overrides below).
    pub recipe: Recipe,
    /// Override `recipe.count`.
    pub count: Option<usize>,
    /// Override `recipe.image.size`.
    pub size: Option<u32>,
    /// Override `recipe.seed`.
    pub seed: Option<u64>,
    /// `(i, K)`: render only indices `≡ i (mod K)`. `(0, 1)`: everything.
    pub shard: (usize, usize),
    /// Also write linear EXR images.
    pub exr: bool,
    /// Worker threads (`None`: all cores).
    pub threads: Option<usize>,
    /// Stop dispatching after this many images were rendered (simulates an interruption).
    pub stop_after: Option<usize>,
    /// Set to `true` (e.g. by a Ctrl-C handler) to stop dispatching new images.
    pub cancel: Option<Arc<AtomicBool>>,
}

impl GenerateOptions {
    /// Defaults: whole set, no overrides, all cores.
    pub fn new(out: impl Into<PathBuf>, recipe: Recipe) -> Self {
        GenerateOptions {
            out: out.into(),
            recipe,
            count: None,
            size: None,
            seed: None,
            shard: (0, 1),
            exr: false,
            threads: None,
            stop_after: None,
            cancel: None,
        }
    }

    /// The recipe with `count` and `size` applied.
    pub fn effective_recipe(&self) -> Recipe {
        let mut r = self.recipe.clone();
        if let Some(c) = self.count {
            r.count = c;
        }
        if let Some(s) = self.size {
            r.image.size = s;
        }
        if let Some(s) = self.seed {
            r.seed = s;
        }
        r
    }
}

/// Result of a run.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Summary {
    /// Images in the set.
    pub count: usize,
    /// This run's shard `(i, K)`.
    pub shard: (usize, usize),
    /// Images rendered by this run.
    pub rendered: usize,
    /// Images of this shard found finished and skipped.
    pub skipped: usize,
    /// Images of the whole set present after the run.
    pub present: usize,
    /// Whether the whole set is present (and `labels.jsonl`, `manifest.json`, `preview.png` written).
    pub complete: bool,
    /// Wall time of the run, seconds.
    pub wall_s: f64,
    /// Rendered images per second.
    pub images_per_s: f64,
}

/// The run stopped early (Ctrl-C or `stop_after`); the directory is resumable.
#[derive(Debug, thiserror::Error)]
#[error("interrupted after rendering {rendered} images; {remaining} of this shard remain (rerun the same command to resume)")]
pub struct Interrupted {
    /// Images rendered before stopping.
    pub rendered: usize,
    /// Images of the shard still missing.
    pub remaining: usize,
}

/// `DIR/images/NNNNNN.png`.
pub fn image_path(dir: &Path, index: usize) -> PathBuf {
    dir.join("images").join(format!("{index:06}.png"))
}

/// `DIR/images/NNNNNN.exr`.
pub fn exr_path(dir: &Path, index: usize) -> PathBuf {
    dir.join("images").join(format!("{index:06}.exr"))
}

/// `DIR/labels/NNNNNN.json`.
pub fn label_path(dir: &Path, index: usize) -> PathBuf {
    dir.join("labels").join(format!("{index:06}.json"))
}

/// Hex SHA-256.
pub fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}

/// `manifest.json`. Deterministic: the same for the same recipe and seed, however produced
/// (timing lives in `runs.jsonl`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// `woven`.
    pub program: String,
    /// Crate version.
    pub version: String,
    /// Dataset seed.
    pub seed: u64,
    /// Images.
    pub count: usize,
    /// Image side, pixels.
    pub image_size: u32,
    /// Samples per pixel.
    pub spp: u32,
    /// Whether every image also has an EXR.
    pub exr: bool,
    /// Effective recipe.
    pub recipe: Recipe,
    /// SHA-256 of the canonical TOML of the effective recipe ([`Recipe::to_toml`]).
    pub recipe_sha256: String,
    /// Pattern classes.
    pub classes: Vec<PatternClass>,
    /// Images per class, by class id.
    pub class_counts: Vec<usize>,
    /// Names of the normalised `targets` of each label.
    pub target_names: Vec<String>,
    /// SHA-256 of `labels.jsonl`.
    pub labels_sha256: String,
    /// Where the timing of each run is recorded.
    pub timing: String,
}

/// `dataset.json`: what makes two runs the same dataset (`image_size` is informative: it is part
/// of the recipe hash, and kept apart so a mismatch can be explained; absent in older sets).
#[derive(Serialize, Deserialize)]
pub(crate) struct Identity {
    seed: u64,
    recipe_sha256_without_count: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    image_size: Option<u32>,
}

impl Identity {
    pub(crate) fn same_dataset(&self, other: &Identity) -> bool {
        self.seed == other.seed && self.recipe_sha256_without_count == other.recipe_sha256_without_count
    }
}

pub(crate) fn identity(recipe: &Recipe) -> Identity {
    let mut r = recipe.clone();
    r.count = 0;
    Identity {
        seed: recipe.seed,
        recipe_sha256_without_count: sha256_hex(r.to_toml().as_bytes()),
        image_size: Some(recipe.image.size),
    }
}

/// Why a run does not match the dataset already in `dir` (identity `old`): the seed, the image
/// size (from `dataset.json` or, for older sets, `manifest.json`), or else the recipe itself.
fn mismatch(dir: &Path, old: &Identity, recipe: &Recipe) -> String {
    let mut why = Vec::new();
    if old.seed != recipe.seed {
        why.push(format!("its seed is {} (this run: {}; --seed)", old.seed, recipe.seed));
    }
    let old_size = old.image_size.or_else(|| {
        let text = std::fs::read_to_string(dir.join("manifest.json")).ok()?;
        serde_json::from_str::<serde_json::Value>(&text).ok()?["image_size"].as_u64().map(|s| s as u32)
    });
    if let Some(s) = old_size.filter(|&s| s != recipe.image.size) {
        why.push(format!("its images are {s} px (this run: {} px; --size)", recipe.image.size));
    }
    if why.is_empty() {
        why.push("it was made from another recipe (a different recipe file, or one edited since)".into());
    }
    format!(
        "{} holds a dataset from another recipe or seed: {}; use another --out, or the same recipe, size and seed",
        dir.display(),
        why.join(", and ")
    )
}

/// Remove temporary files left by a crashed run (those of live processes are kept).
fn remove_stale_temps(dir: &Path) -> Result<usize> {
    let mut n = 0;
    let me = std::process::id().to_string();
    let have_proc = Path::new("/proc/self").exists();
    for sub in [dir.to_path_buf(), dir.join("images"), dir.join("labels")] {
        let Ok(rd) = std::fs::read_dir(&sub) else { continue };
        for e in rd.flatten() {
            let name = e.file_name().to_string_lossy().to_string();
            let Some(pos) = name.find(".tmp") else { continue };
            if !name.starts_with('.') {
                continue;
            }
            let pid = name[..pos].rsplit_once('.').map(|(_, p)| p.to_string()).unwrap_or_default();
            let stale = if pid == me {
                true
            } else if have_proc && pid.chars().all(|c| c.is_ascii_digit()) && !pid.is_empty() {
                !Path::new("/proc").join(&pid).exists()
            } else {
                let age = e.metadata().and_then(|m| m.modified()).ok().and_then(|t| t.elapsed().ok());
                age.is_some_and(|a| a.as_secs() > 3600)
            };
            if stale {
                std::fs::remove_file(e.path()).with_context(|| format!("cannot remove {}", e.path().display()))?;
                n += 1;
            }
        }
    }
    Ok(n)
}

/// Whether image `s.index` is finished: its label file equals `line` and its PNG (and EXR when
/// asked) decodes at the right size.
fn is_finished(dir: &Path, s: &Sample, line: &str, exr: bool, decode: bool) -> bool {
    match std::fs::read(label_path(dir, s.index)) {
        Ok(b) if b == line.as_bytes() => {}
        _ => return false,
    }
    let png = image_path(dir, s.index);
    if !decode {
        return png.is_file() && (!exr || exr_path(dir, s.index).is_file());
    }
    let ok_png = image::open(&png).is_ok_and(|i| i.width() == s.scene.width && i.height() == s.scene.height);
    let ok_exr = !exr || crate::Image::load(&exr_path(dir, s.index), 1).is_ok_and(|i| i.width == s.scene.width);
    ok_png && ok_exr
}

/// Render one sample to its files (PNG, EXR, then the label last).
fn render_one(dir: &Path, s: &Sample, line: &str, exr: bool) -> Result<()> {
    let prepared = Prepared::new(&s.cloth, &s.scene, &RenderOptions::default());
    let mut img = prepared.render(&s.cloth.appearance);
    s.noise.apply(&mut img);
    img.save_png(&image_path(dir, s.index))?;
    if exr {
        img.save_exr(&exr_path(dir, s.index))?;
    }
    write_atomic(&label_path(dir, s.index), line.as_bytes())
        .with_context(|| format!("cannot write {}", label_path(dir, s.index).display()))
}

/// Rebuild `labels.jsonl`, `manifest.json` and `preview.png` when every image is present.
/// Returns the number of images present.
pub fn finalize(dir: &Path, recipe: &Recipe) -> Result<(usize, bool)> {
    let results: Vec<Result<Option<(Label, String, bool)>>> = (0..recipe.count)
        .into_par_iter()
        .map(|i| {
            let s = recipe.sample(i, recipe.seed)?;
            let label = Label::from_sample(&s);
            let line = label.to_line();
            if !is_finished(dir, &s, &line, false, false) {
                return Ok(None);
            }
            let has_exr = exr_path(dir, i).is_file();
            Ok(Some((label, line, has_exr)))
        })
        .collect();
    let mut done = Vec::with_capacity(recipe.count);
    for r in results {
        if let Some(x) = r? {
            done.push(x);
        }
    }
    let present = done.len();
    if present < recipe.count {
        return Ok((present, false));
    }
    let jsonl: String = done.iter().map(|(_, l, _)| l.as_str()).collect();
    write_atomic(&dir.join("labels.jsonl"), jsonl.as_bytes())?;
    let classes = recipe.classes();
    let mut class_counts = vec![0; classes.len()];
    done.iter().for_each(|(l, _, _)| class_counts[l.class_id] += 1);
    let manifest = Manifest {
        program: "woven".into(),
        version: env!("CARGO_PKG_VERSION").into(),
        seed: recipe.seed,
        count: recipe.count,
        image_size: recipe.image.size,
        spp: recipe.image.spp,
        exr: done.iter().all(|d| d.2),
        recipe: recipe.clone(),
        recipe_sha256: sha256_hex(recipe.to_toml().as_bytes()),
        classes,
        class_counts,
        target_names: target_names(),
        labels_sha256: sha256_hex(jsonl.as_bytes()),
        timing: "runs.jsonl (one line per run; timing is kept out of the manifest so it stays deterministic)".into(),
    };
    let mut text = serde_json::to_string_pretty(&manifest)?;
    text.push('\n');
    write_atomic(&dir.join("manifest.json"), text.as_bytes())?;
    let labels: Vec<Label> = done.into_iter().map(|d| d.0).collect();
    let sheet = contact_sheet(dir, &labels)?;
    let mut bytes = Vec::new();
    sheet.write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)?;
    write_atomic(&dir.join("preview.png"), &bytes)?;
    Ok((present, true))
}

/// Generate (or resume, or extend) the dataset described by `opts`. Progress: a message with the
/// plan (images, already done, to render, threads), then the stage `generate` with one step per
/// rendered image.
pub fn generate(opts: &GenerateOptions, progress: &dyn Progress) -> Result<Summary> {
    let start = Instant::now();
    let (shard_i, shard_k) = opts.shard;
    if shard_k == 0 || shard_i >= shard_k {
        bail!("--shard {shard_i}/{shard_k}: need 0 <= i < K");
    }
    let recipe = opts.effective_recipe();
    recipe.validate()?;
    let dir = &opts.out;
    for sub in ["images", "labels"] {
        std::fs::create_dir_all(dir.join(sub)).with_context(|| format!("cannot create {}", dir.join(sub).display()))?;
    }
    // Refuse to mix two datasets in one directory.
    let id = identity(&recipe);
    let id_path = dir.join("dataset.json");
    match std::fs::read_to_string(&id_path) {
        Ok(text) => {
            let old: Identity =
                serde_json::from_str(&text).with_context(|| format!("corrupt {}", id_path.display()))?;
            if !old.same_dataset(&id) {
                bail!("{}", mismatch(dir, &old, &recipe));
            }
        }
        Err(_) => write_atomic(&id_path, (serde_json::to_string_pretty(&id)? + "\n").as_bytes())?,
    }
    let stale = remove_stale_temps(dir)?;

    let threads = opts
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1))
        .clamp(1, crate::render::MAX_THREADS);
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
    let indices: Vec<usize> = (shard_i..recipe.count).step_by(shard_k).collect();

    // Check what is already finished (label matches the sample, image decodes).
    let checked: Vec<Result<(Sample, String, bool)>> = pool.install(|| {
        indices
            .par_iter()
            .map(|&i| {
                let s = recipe.sample(i, recipe.seed)?;
                let line = Label::from_sample(&s).to_line();
                let done = is_finished(dir, &s, &line, opts.exr, true);
                Ok((s, line, done))
            })
            .collect()
    });
    let mut todo = Vec::new();
    let mut skipped = 0;
    for c in checked {
        let (s, line, done) = c?;
        if done {
            skipped += 1;
        } else {
            todo.push((s, line));
        }
    }
    progress.message(&format!(
        "generate: {} images (shard {shard_i}/{shard_k}: {}) into {}; {skipped} already done, {} to render, {threads} threads{}",
        recipe.count,
        indices.len(),
        dir.display(),
        todo.len(),
        if stale > 0 { format!("; removed {stale} stale temporary files") } else { String::new() }
    ));
    progress.begin("generate", todo.len() as u64);
    let stop = AtomicBool::new(false);
    let rendered = AtomicUsize::new(0);
    let first_err: Mutex<Option<anyhow::Error>> = Mutex::new(None);
    let n_todo = todo.len();
    let render_start = Instant::now();
    pool.install(|| {
        todo.par_iter().for_each(|(s, line)| {
            let cancelled = opts.cancel.as_ref().is_some_and(|c| c.load(Ordering::SeqCst));
            if cancelled || stop.load(Ordering::SeqCst) {
                stop.store(true, Ordering::SeqCst);
                return;
            }
            if let Err(e) = render_one(dir, s, line, opts.exr) {
                stop.store(true, Ordering::SeqCst);
                let mut slot = first_err.lock().expect("error slot");
                slot.get_or_insert(e.context(format!("image {}", s.index)));
                return;
            }
            let n = rendered.fetch_add(1, Ordering::SeqCst) + 1;
            progress.advance(1);
            if opts.stop_after.is_some_and(|k| n >= k) {
                stop.store(true, Ordering::SeqCst);
            }
        })
    });
    progress.finish();
    if let Some(e) = first_err.into_inner().expect("error slot") {
        return Err(e);
    }
    let rendered = rendered.into_inner();
    let wall_s = start.elapsed().as_secs_f64();
    let render_s = render_start.elapsed().as_secs_f64();
    let images_per_s = if rendered > 0 { rendered as f64 / render_s.max(1e-9) } else { 0.0 };
    let run_line = serde_json::json!({
        "shard": format!("{shard_i}/{shard_k}"),
        "count": recipe.count,
        "threads": threads,
        "rendered": rendered,
        "skipped": skipped,
        "wall_s": wall_s,
        "render_s": render_s,
        "images_per_s": images_per_s,
        "interrupted": rendered < n_todo,
        "unix_time": std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0),
    });
    append_line(&dir.join("runs.jsonl"), &run_line.to_string())?;
    if rendered < n_todo {
        return Err(anyhow!(Interrupted { rendered, remaining: n_todo - rendered }));
    }
    if shard_k > 1 {
        // For `woven merge` of shards rendered on machines without a shared folder.
        super::merge::write_shard_manifest(dir, &recipe, opts.shard, opts.exr)?;
    }
    let (present, complete) = finalize(dir, &recipe)?;
    Ok(Summary { count: recipe.count, shard: opts.shard, rendered, skipped, present, complete, wall_s, images_per_s })
}

fn append_line(path: &Path, line: &str) -> Result<()> {
    use std::io::Write;
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .with_context(|| format!("cannot open {}", path.display()))?;
    f.write_all(format!("{line}\n").as_bytes())?;
    Ok(())
}
