//! Synthetic training set generator (docs/design.md §4.3): renders `count` images with
//! parameters drawn from the Table-1 priors of a recipe, writes per-image labels, and assembles
//! `labels.jsonl`, `manifest.json` and a contact sheet. Deterministic (same recipe and seed give
//! the same bytes whatever the threads or sharding), resumable and interruptible (a stop flag,
//! [`GenerateOptions::cancel`], which the `woven` binary sets on Ctrl-C).

pub mod generate;
pub mod merge;
pub mod recipe;
pub mod sample;
pub mod sheet;

pub use generate::{generate, GenerateOptions, Interrupted, Manifest, Summary};
pub use merge::{merge, MergeSummary, ShardManifest};
pub use recipe::{Dist, PatternClass, Prior, Recipe, Span};
pub use sample::{target_names, view_cell_map, Label, NoiseSpec, Sample};
