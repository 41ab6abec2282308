//! A fast survey of preparation (`woven prep --survey`): the grid that [`super::prepare`] finds on
//! many images, against what each image is known to hold, in seconds instead of fit-hours.
//!
//! Three sources, each optional:
//! - **synthetic**: the photo-path targets of `woven eval` ([`crate::fit::eval::PhotoView`]: the
//!   same random cloths and views for the same seed, multi-repeat renders with rotation, tilt,
//!   phase, exposure, blur and noise); the truth is the pattern's grid `n_e × n_a`;
//! - **renders**: a folder of images by another renderer with a `NAME.json` beside each (its
//!   `pattern` matrix, as `woven eval --renders` reads it); the truth is that pattern's grid;
//! - **real**: a folder with `labels.csv` (`path,weave_label`, as `woven eval --real` reads it);
//!   a label gives only the weave class, so the check is whether the grid *can* hold that class
//!   ([`grid_fits_class`]): plain 2×2, twill square n ≥ 3, satin square n ≥ 4, basket square even
//!   n ≥ 4.
//!
//! Every case records the grid, the angle, the pitch, the number of repeats in the rectified
//! image and the time; a failed preparation records its message. The last line of the report is
//! `prep-survey: …` with the hit count of each source.

use super::{prepare, PrepOptions, Prepared};
use crate::fit::eval::PhotoView;
use crate::image_io::Image;
use crate::pattern::{WeaveClass, WeavePattern};
use anyhow::{Context, Result};
use rand::prelude::*;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Where a survey case comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Source {
    /// A photo-path target of our own renderer.
    Synthetic,
    /// A render by another renderer with its ground-truth pattern.
    Renders,
    /// A real photo with a weave-class label.
    Real,
}

impl Source {
    /// Lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Source::Synthetic => "synthetic",
            Source::Renders => "renders",
            Source::Real => "real",
        }
    }
}

/// What a survey image is known to hold.
#[derive(Clone, Debug, PartialEq)]
pub enum Truth {
    /// The exact minimum pattern (grid `n_e × n_a`).
    Pattern(WeavePattern),
    /// Only the weave class (real photos).
    Class(WeaveClass),
}

/// What preparation found on one image.
#[derive(Clone, Debug, PartialEq)]
pub struct Found {
    /// Weft yarns (rows) of the repeat.
    pub n_e: usize,
    /// Warp yarns (columns) of the repeat.
    pub n_a: usize,
    /// Rotation found, degrees.
    pub angle_deg: f32,
    /// Yarn pitch x / y, pixels.
    pub pitch: [f32; 2],
    /// Repeats of the found period across the rectified image, x / y (1 when not repeated).
    pub repeats: [f32; 2],
    /// Whether a repeat was found along x / y.
    pub repeated: [bool; 2],
}

impl Found {
    fn of(p: &Prepared) -> Found {
        Found {
            n_e: p.n_e,
            n_a: p.n_a,
            angle_deg: p.angle_deg,
            pitch: [p.pitch_x, p.pitch_y],
            repeats: [p.width as f32 / p.period_x.max(1.0), p.height as f32 / p.period_y.max(1.0)],
            repeated: [p.repeated_x, p.repeated_y],
        }
    }
}

/// One surveyed image.
#[derive(Clone, Debug)]
pub struct SurveyCase {
    /// Source of the image.
    pub source: Source,
    /// Name (target index, file stem or photo path).
    pub name: String,
    /// What the image is known to hold.
    pub truth: Truth,
    /// The true rotation, degrees, where known (synthetic views).
    pub true_angle_deg: Option<f32>,
    /// What preparation found, or its error message.
    pub found: std::result::Result<Found, String>,
    /// Preparation time, seconds.
    pub secs: f64,
}

impl SurveyCase {
    /// Whether the grid found is the truth's (exact grid), or can hold the labelled class.
    pub fn right(&self) -> bool {
        let Ok(f) = &self.found else { return false };
        match &self.truth {
            Truth::Pattern(p) => (f.n_e, f.n_a) == (p.n_e(), p.n_a()),
            Truth::Class(c) => grid_fits_class(f.n_e, f.n_a, *c),
        }
    }

    /// One line of the table.
    pub fn line(&self) -> String {
        let truth = match &self.truth {
            Truth::Pattern(p) => format!("{}×{}", p.n_e(), p.n_a()),
            Truth::Class(c) => c.name().to_string(),
        };
        let found = match &self.found {
            Ok(f) => format!(
                "{}×{} angle {:+.2}°{} pitch {:.1}×{:.1} px repeats {:.1}{}×{:.1}{}",
                f.n_e,
                f.n_a,
                f.angle_deg,
                self.true_angle_deg.map_or(String::new(), |a| format!(" (view {a:+.2}°)")),
                f.pitch[0],
                f.pitch[1],
                f.repeats[0],
                if f.repeated[0] { "" } else { "*" },
                f.repeats[1],
                if f.repeated[1] { "" } else { "*" },
            ),
            Err(e) => format!("failed: {}", e.chars().take(90).collect::<String>()),
        };
        format!(
            "{:<9} {:<40} truth {:<7} {} {} ({:.2} s)",
            self.source.name(),
            self.name,
            truth,
            if self.right() { "RIGHT" } else { "wrong" },
            found,
            self.secs
        )
    }
}

/// Whether a grid of `n_e × n_a` yarns can be the minimum repeat of a weave of class `c`: plain
/// 2×2; twill square with n ≥ 3; satin square with n ≥ 4 (the 4-end crowfoot included); basket
/// square with even n ≥ 4; `Other` any grid.
pub fn grid_fits_class(n_e: usize, n_a: usize, c: WeaveClass) -> bool {
    match c {
        WeaveClass::Plain => (n_e, n_a) == (2, 2),
        WeaveClass::Twill => n_e == n_a && n_e >= 3,
        WeaveClass::Satin => n_e == n_a && n_e >= 4,
        WeaveClass::Basket => n_e == n_a && n_e >= 4 && n_e.is_multiple_of(2),
        WeaveClass::Other => true,
    }
}

/// What to survey.
#[derive(Clone, Debug, Default)]
pub struct SurveyOptions {
    /// Number of synthetic photo-path targets (0: none).
    pub count: usize,
    /// Seed of the synthetic targets (the same targets as `woven eval --seed`).
    pub seed: u64,
    /// Largest random pattern side of the synthetic targets (`woven eval`'s default is 5).
    pub max_side: usize,
    /// A folder of renders by another renderer with `NAME.json` truths.
    pub renders: Option<PathBuf>,
    /// A folder of real photos with `labels.csv`.
    pub real: Option<PathBuf>,
    /// Write each case's grid overlay (or, on failure, the diagnostic overlay) to
    /// `save/<source>_<name>.png`.
    pub save: Option<PathBuf>,
    /// Keep the synthetic renders here (`synthetic_s<seed>_m<max_side>_<i>.exr`, linear) and
    /// read them back on the next survey instead of rendering again: a render takes 20–40 s, the
    /// preparation a quarter of a second. A cache made by another version of the renderer must be
    /// deleted by hand.
    pub cache: Option<PathBuf>,
    /// Render threads of the synthetic targets.
    pub threads: Option<usize>,
    /// Preparation options.
    pub prep: PrepOptions,
}

/// Result of [`survey`].
#[derive(Clone, Debug, Default)]
pub struct SurveyReport {
    /// Every case, in the order surveyed.
    pub cases: Vec<SurveyCase>,
}

impl SurveyReport {
    /// `prep-survey: synthetic r/n renders r/n real r/n prepared p/n median_s t`.
    pub fn summary_line(&self) -> String {
        let mut s = String::from("prep-survey:");
        for src in [Source::Synthetic, Source::Renders, Source::Real] {
            let c: Vec<&SurveyCase> = self.cases.iter().filter(|c| c.source == src).collect();
            if !c.is_empty() {
                let right = c.iter().filter(|c| c.right()).count();
                let ok = c.iter().filter(|c| c.found.is_ok()).count();
                s += &format!(" {}={}/{} (prepared {})", src.name(), right, c.len(), ok);
            }
        }
        let mut t: Vec<f64> = self.cases.iter().map(|c| c.secs).collect();
        t.sort_by(f64::total_cmp);
        if !t.is_empty() {
            s += &format!(" median_s={:.2}", t[t.len() / 2]);
        }
        s
    }
}

/// Prepare one image and record the case; with `save`, write its overlay.
fn survey_one(
    img: &image::Rgb32FImage,
    source: Source,
    name: String,
    truth: Truth,
    true_angle_deg: Option<f32>,
    opts: &SurveyOptions,
) -> Result<SurveyCase> {
    let t = Instant::now();
    let res = prepare(img, &opts.prep);
    let secs = t.elapsed().as_secs_f64();
    if let Some(dir) = &opts.save {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let overlay = match &res {
            Ok(p) => Some(p.grid_overlay()),
            Err(_) => super::diagnostic_overlay(img, &opts.prep),
        };
        if let Some(ov) = overlay {
            let file = format!("{}_{}.png", source.name(), name.replace(['/', '\\'], "_"));
            Image::from_rgb32f(&ov).save_png(&dir.join(file))?;
        }
    }
    Ok(SurveyCase {
        source,
        name,
        truth,
        true_angle_deg,
        found: res.as_ref().map(Found::of).map_err(|e| e.to_string()),
        secs,
    })
}

/// Run the survey; `on_case` is called as each image is done (the command line prints its line).
///
/// Errors: nothing to survey, an unreadable folder or `labels.csv`, a render's truth that is not a
/// pattern, or failing to write `save`. An image that preparation refuses is a case, not an error.
pub fn survey(opts: &SurveyOptions, on_case: &mut dyn FnMut(&SurveyCase)) -> Result<SurveyReport> {
    if opts.count == 0 && opts.renders.is_none() && opts.real.is_none() {
        anyhow::bail!("nothing to survey: give --count N (synthetic targets), --renders DIR or --real DIR");
    }
    let mut report = SurveyReport::default();
    let mut push = |c: SurveyCase, report: &mut SurveyReport| {
        on_case(&c);
        report.cases.push(c);
    };
    // The same cloths as `woven eval --seed S`: one generator drawn in target order.
    let mut rng = StdRng::seed_from_u64(opts.seed);
    for i in 0..opts.count {
        let truth = crate::fit::demo::random_cloth(&mut rng, opts.max_side.max(2));
        let view = PhotoView::draw(opts.seed, i, &truth);
        let cached =
            opts.cache.as_ref().map(|d| d.join(format!("synthetic_s{}_m{}_{i}.exr", opts.seed, opts.max_side)));
        let img = match cached.as_ref().filter(|p| p.is_file()) {
            Some(p) => Image::load(p, 1)?,
            None => {
                let img = view.render(&truth, 50_000 + i as u64, opts.threads);
                if let Some(p) = &cached {
                    if let Some(d) = p.parent() {
                        std::fs::create_dir_all(d).with_context(|| format!("creating {}", d.display()))?;
                    }
                    img.save_exr(p)?;
                }
                img
            }
        }
        .to_rgb32f();
        let name = format!("target_{i}");
        let c =
            survey_one(&img, Source::Synthetic, name, Truth::Pattern(truth.pattern), Some(view.rotation_deg), opts)?;
        push(c, &mut report);
    }
    if let Some(dir) = &opts.renders {
        for (name, pattern, path) in render_truths(dir)? {
            let img = Image::load(&path, 1)?.to_rgb32f();
            let c = survey_one(&img, Source::Renders, name, Truth::Pattern(pattern), None, opts)?;
            push(c, &mut report);
        }
    }
    if let Some(dir) = &opts.real {
        for label in crate::fit::real::read_labels(dir)? {
            let path = dir.join(&label.path);
            let c = match Image::load(&path, 1) {
                Ok(img) => {
                    survey_one(&img.to_rgb32f(), Source::Real, label.path, Truth::Class(label.class), None, opts)?
                }
                Err(e) => SurveyCase {
                    source: Source::Real,
                    name: label.path,
                    truth: Truth::Class(label.class),
                    true_angle_deg: None,
                    found: Err(format!("reading {}: {e}", path.display())),
                    secs: 0.0,
                },
            };
            push(c, &mut report);
        }
    }
    Ok(report)
}

/// `(stem, truth pattern, image path)` of every image of a renders folder with a `NAME.json`
/// holding a `pattern` (EXR preferred over PNG), sorted by name.
fn render_truths(dir: &Path) -> Result<Vec<(String, WeavePattern, PathBuf)>> {
    let mut out = Vec::new();
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(|e| e.ok())
        .filter_map(|e| e.file_name().into_string().ok())
        .filter_map(|n| n.strip_suffix(".json").map(str::to_string))
        .collect();
    names.sort();
    for name in names {
        let exr = dir.join(format!("{name}.exr"));
        let png = dir.join(format!("{name}.png"));
        let path = if exr.is_file() {
            exr
        } else if png.is_file() {
            png
        } else {
            continue;
        };
        let text = crate::io::read_text_capped(&dir.join(format!("{name}.json")), crate::io::MAX_PARAM_FILE_BYTES)?;
        let meta: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("parsing {name}.json"))?;
        let rows: Vec<Vec<u8>> = serde_json::from_value(meta["pattern"].clone())
            .with_context(|| format!("{name}.json: `pattern` must be a matrix of 0/1"))?;
        let pattern = crate::fit::renders::truth_from_renderer(&rows).with_context(|| format!("{name}.json"))?;
        out.push((name, pattern, path));
    }
    if out.is_empty() {
        anyhow::bail!("{} holds no NAME.json with NAME.exr or NAME.png beside it", dir.display());
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn class_plausibility_of_grids() {
        assert!(grid_fits_class(2, 2, WeaveClass::Plain));
        assert!(!grid_fits_class(2, 3, WeaveClass::Plain));
        assert!(!grid_fits_class(2, 2, WeaveClass::Twill));
        assert!(grid_fits_class(3, 3, WeaveClass::Twill));
        assert!(!grid_fits_class(3, 4, WeaveClass::Twill));
        assert!(!grid_fits_class(3, 3, WeaveClass::Satin));
        assert!(grid_fits_class(5, 5, WeaveClass::Satin));
        assert!(grid_fits_class(6, 6, WeaveClass::Basket));
        assert!(grid_fits_class(4, 4, WeaveClass::Basket));
        assert!(!grid_fits_class(3, 3, WeaveClass::Basket));
        assert!(grid_fits_class(7, 2, WeaveClass::Other));
    }

    #[test]
    fn nothing_to_survey_is_an_error() {
        let e = survey(&SurveyOptions::default(), &mut |_| {}).unwrap_err();
        assert!(e.to_string().starts_with("nothing to survey"), "{e}");
    }

    #[test]
    fn a_synthetic_case_is_scored_against_its_pattern() {
        let opts = SurveyOptions { count: 1, seed: 1, max_side: 5, threads: Some(2), ..Default::default() };
        let mut seen = 0;
        let r = survey(&opts, &mut |_| seen += 1).unwrap();
        assert_eq!((seen, r.cases.len()), (1, 1));
        let c = &r.cases[0];
        assert!(matches!(c.truth, Truth::Pattern(_)) && c.true_angle_deg.is_some());
        assert!(r.summary_line().starts_with("prep-survey: synthetic="), "{}", r.summary_line());
        // A case is right exactly when the grid equals the truth's.
        if let (Ok(f), Truth::Pattern(p)) = (&c.found, &c.truth) {
            assert_eq!(c.right(), (f.n_e, f.n_a) == (p.n_e(), p.n_a()));
        } else {
            assert!(!c.right());
        }
    }
}
