//! Shards made on several machines, merged into one dataset.
//!
//! `woven generate --shard i/K` renders the indices `≡ i (mod K)`. On one machine (or a shared
//! file system) the shards can write into one folder. On a cluster without one — a Slurm array job,
//! a Kubernetes Indexed Job (`datagen/cluster/`) — each task writes its own folder, and
//! [`merge`] assembles them:
//!
//! 1. every finished shard leaves a **shard manifest** `shards/shard-i-of-K.json` in its folder
//!    ([`write_shard_manifest`]): the effective recipe, its hash, and the SHA-256 of every file it
//!    rendered;
//! 2. [`merge`] reads the manifests of all given folders, checks that they describe the same
//!    dataset (recipe hash, seed, count, K), that every shard `0..K` is there exactly once (an
//!    identical duplicate, e.g. a retried task, is accepted) and that every file still has the
//!    hash its manifest recorded (a truncated copy is caught before it is used);
//! 3. the files are copied into the output folder (each to a temporary name, then renamed) and the
//!    dataset is finalised exactly as a single run finalises it ([`super::generate::finalize`]):
//!    `labels.jsonl`, `manifest.json` and `preview.png` are byte-identical to a one-machine run.

use super::generate::{exr_path, finalize, identity, image_path, label_path, sha256_hex, Identity};
use super::recipe::Recipe;
use crate::io::write_atomic;
use crate::progress::Progress;
use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Folder (inside a shard's output folder) that holds the shard manifests.
pub const SHARD_DIR: &str = "shards";

/// Largest shard manifest read (a manifest lists three hashes per image: about 250 bytes).
const MAX_MANIFEST_BYTES: u64 = 256 << 20;

/// Hashes of one rendered image's files.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ShardFile {
    /// Image index in the dataset.
    pub index: usize,
    /// SHA-256 of `images/NNNNNN.png`.
    pub png_sha256: String,
    /// SHA-256 of `images/NNNNNN.exr` (when EXR was written).
    pub exr_sha256: Option<String>,
    /// SHA-256 of `labels/NNNNNN.json`.
    pub label_sha256: String,
}

/// `shards/shard-i-of-K.json`: what one finished shard holds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ShardManifest {
    /// `woven`.
    pub program: String,
    /// Crate version that rendered the shard.
    pub version: String,
    /// `[i, K]`.
    pub shard: [usize; 2],
    /// Effective recipe (count, size and seed applied).
    pub recipe: Recipe,
    /// SHA-256 of the recipe's canonical TOML ([`Recipe::to_toml`]).
    pub recipe_sha256: String,
    /// Whether EXR files were written.
    pub exr: bool,
    /// Every image of the shard, by index.
    pub files: Vec<ShardFile>,
}

/// Path of the manifest of shard `(i, K)` in `dir`.
pub fn shard_manifest_path(dir: &Path, (i, k): (usize, usize)) -> PathBuf {
    dir.join(SHARD_DIR).join(format!("shard-{i}-of-{k}.json"))
}

fn file_sha(path: &Path) -> Result<String> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    Ok(sha256_hex(&bytes))
}

/// Write the manifest of a finished shard `(i, K)` of `recipe` in `dir` (hashing its files).
pub fn write_shard_manifest(dir: &Path, recipe: &Recipe, shard: (usize, usize), exr: bool) -> Result<PathBuf> {
    let files = (shard.0..recipe.count)
        .step_by(shard.1)
        .map(|i| {
            Ok(ShardFile {
                index: i,
                png_sha256: file_sha(&image_path(dir, i))?,
                exr_sha256: if exr { Some(file_sha(&exr_path(dir, i))?) } else { None },
                label_sha256: file_sha(&label_path(dir, i))?,
            })
        })
        .collect::<Result<Vec<_>>>()?;
    let m = ShardManifest {
        program: "woven".into(),
        version: env!("CARGO_PKG_VERSION").into(),
        shard: [shard.0, shard.1],
        recipe: recipe.clone(),
        recipe_sha256: sha256_hex(recipe.to_toml().as_bytes()),
        exr,
        files,
    };
    let path = shard_manifest_path(dir, shard);
    write_atomic(&path, (serde_json::to_string_pretty(&m)? + "\n").as_bytes())
        .with_context(|| format!("cannot write {}", path.display()))?;
    Ok(path)
}

/// Every shard manifest found in `dir/shards/`, with its path.
fn read_manifests(dir: &Path) -> Result<Vec<(PathBuf, ShardManifest)>> {
    let sub = dir.join(SHARD_DIR);
    let rd = std::fs::read_dir(&sub).with_context(|| {
        format!(
            "{} holds no shard manifest ({SHARD_DIR}/shard-i-of-K.json): is it the --out of a `woven generate --shard i/K` run that finished?",
            dir.display()
        )
    })?;
    let mut out = Vec::new();
    for e in rd.flatten() {
        let p = e.path();
        let name = e.file_name().to_string_lossy().to_string();
        if !(name.starts_with("shard-") && name.ends_with(".json")) {
            continue;
        }
        let text = crate::io::read_text_capped(&p, MAX_MANIFEST_BYTES)
            .with_context(|| format!("cannot read {}", p.display()))?;
        let m: ShardManifest =
            serde_json::from_str(&text).with_context(|| format!("{} is not a shard manifest", p.display()))?;
        out.push((p, m));
    }
    if out.is_empty() {
        bail!("{} holds no shard manifest in {SHARD_DIR}/", dir.display());
    }
    Ok(out)
}

/// What [`merge`] did.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct MergeSummary {
    /// Images in the merged set.
    pub count: usize,
    /// Number of shards `K`.
    pub shards: usize,
    /// Files copied into the output (the others were already there with the right hash).
    pub copied: usize,
}

/// One shard of the set: where its files are and what they should hash to.
struct Source {
    dir: PathBuf,
    manifest: ShardManifest,
}

/// Check the manifests against each other: one dataset, one K, every shard once.
fn check_sources(found: Vec<(PathBuf, PathBuf, ShardManifest)>) -> Result<(Recipe, Vec<Source>)> {
    let (first_path, first) = (&found[0].1, &found[0].2);
    let (sha, k) = (first.recipe_sha256.clone(), first.shard[1]);
    let mut by_shard: BTreeMap<usize, Source> = BTreeMap::new();
    for (dir, path, m) in &found {
        if m.recipe_sha256 != sha {
            bail!(
                "{} and {} are shards of different datasets (recipe, size, count or seed differ); merge shards of one `woven generate` command only",
                first_path.display(),
                path.display()
            );
        }
        if m.shard[1] != k || m.shard[0] >= k {
            bail!(
                "{} is shard {}/{}, but {} is from a split into {k}",
                path.display(),
                m.shard[0],
                m.shard[1],
                first_path.display()
            );
        }
        if m.exr != first.exr {
            bail!(
                "{} and {} differ in --exr; render every shard with the same flags",
                first_path.display(),
                path.display()
            );
        }
        let expected: Vec<usize> = (m.shard[0]..m.recipe.count).step_by(k).collect();
        if m.files.iter().map(|f| f.index).collect::<Vec<_>>() != expected {
            bail!("{} does not list exactly the images of shard {}/{k}", path.display(), m.shard[0]);
        }
        if let Some(prev) = by_shard.get(&m.shard[0]) {
            if prev.manifest.files != m.files {
                bail!(
                    "shard {}/{k} is given twice with different files ({} and {}); keep one",
                    m.shard[0],
                    prev.dir.display(),
                    dir.display()
                );
            }
            continue;
        }
        by_shard.insert(m.shard[0], Source { dir: dir.clone(), manifest: m.clone() });
    }
    let missing: Vec<String> = (0..k).filter(|i| !by_shard.contains_key(i)).map(|i| format!("{i}/{k}")).collect();
    if !missing.is_empty() {
        bail!(
            "shards missing: {} (of {k}); run `woven generate --shard I/{k}` with the same recipe for each and pass its folder",
            missing.join(", ")
        );
    }
    let recipe = first.recipe.clone();
    Ok((recipe, by_shard.into_values().collect()))
}

/// Copy `src` to `dst` (temporary name, then rename) unless `dst` already has hash `sha`; the
/// source must have hash `sha`. Returns whether a copy was made.
fn copy_checked(src: &Path, dst: &Path, sha: &str) -> Result<bool> {
    let bytes = std::fs::read(src).with_context(|| format!("cannot read {}", src.display()))?;
    if sha256_hex(&bytes) != sha {
        bail!(
            "{} does not match its shard manifest (changed or truncated since the shard finished); re-render that shard",
            src.display()
        );
    }
    if src == dst || std::fs::read(dst).is_ok_and(|b| sha256_hex(&b) == sha) {
        return Ok(false);
    }
    write_atomic(dst, &bytes).with_context(|| format!("cannot write {}", dst.display()))?;
    Ok(true)
}

/// Merge the shard folders `dirs` into `out` (see the module docs). `out` may be new, one of the
/// shard folders, or an earlier merge of the same dataset; a folder holding another dataset is
/// refused. Progress: the stage `merge`, one step per image.
pub fn merge(dirs: &[PathBuf], out: &Path, progress: &dyn Progress) -> Result<MergeSummary> {
    if dirs.is_empty() {
        bail!("no shard folders given");
    }
    let mut found = Vec::new();
    for d in dirs {
        for (p, m) in read_manifests(d)? {
            found.push((d.clone(), p, m));
        }
    }
    let (recipe, sources) = check_sources(found)?;
    recipe.validate().context("the shards' recipe")?;
    let id = identity(&recipe);
    let id_path = out.join("dataset.json");
    if let Ok(text) = std::fs::read_to_string(&id_path) {
        let old: Identity = serde_json::from_str(&text).with_context(|| format!("corrupt {}", id_path.display()))?;
        if !old.same_dataset(&id) {
            bail!(
                "{} holds another dataset (its dataset.json differs from the shards'); merge into a new folder",
                out.display()
            );
        }
    }
    progress.begin("merge", recipe.count as u64);
    let mut copied = 0;
    for s in &sources {
        for f in &s.manifest.files {
            let mut pairs = vec![
                (image_path(&s.dir, f.index), image_path(out, f.index), &f.png_sha256),
                (label_path(&s.dir, f.index), label_path(out, f.index), &f.label_sha256),
            ];
            if let Some(h) = &f.exr_sha256 {
                pairs.insert(1, (exr_path(&s.dir, f.index), exr_path(out, f.index), h));
            }
            // The label goes last: it marks the image finished (as in a single run).
            for (src, dst, sha) in pairs {
                copied += copy_checked(&src, &dst, sha)? as usize;
            }
            progress.advance(1);
        }
    }
    progress.finish();
    write_atomic(&id_path, (serde_json::to_string_pretty(&id)? + "\n").as_bytes())?;
    let (present, complete) = finalize(out, &recipe)?;
    if !complete {
        bail!(
            "after merging, {present} of {} images are present in {}; the shards do not cover the set",
            recipe.count,
            out.display()
        );
    }
    Ok(MergeSummary { count: recipe.count, shards: sources.len(), copied })
}
