//! Evaluation on renders by another renderer (`woven eval --renders DIR`): a folder of images with
//! their ground truth, made by a renderer that is not woven's forward model (e.g. Mitsuba 3 with
//! its own materials and lights; `datagen/mitsuba/make_set.py` writes such a folder). Each image
//! takes the user's path (preparation, the capture estimated from the prepared image as `woven fit`
//! estimates it, then the fit) and is scored: pattern exact up to shift, the
//! fit's crop PSNR, and the mean colour of each yarn family against the input's.
//!
//! Folder format, per image `NAME`: `NAME.exr` (linear RGB; `NAME.png`, sRGB, when no EXR),
//! `NAME.json` with `pattern` (rows = weft yarns along the image horizontal, top to bottom;
//! columns = warp yarns, left to right; **1 = warp on top**, the opposite of woven's convention)
//! and optionally `NAME_labels.png` (R/G/B = warp/weft/background coverage per pixel).
//!
//! Converting the truth: woven's `P[i][j] = 1` means weft `i` over warp `j`, and woven's row 0 is
//! the bottom weft of the image (its camera looks down with +y up), so the truth is the renderer's
//! matrix inverted with its rows reversed.

use super::capture::estimate_capture;
use super::output::{registered_pair, sheet_row, write_fit_outputs};
use super::report::quantile;
use super::{fit, fit_prepared, FitOptions};
use crate::image_io::Image;
use crate::pattern::WeavePattern;
use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Largest distance (linear RGB, per channel) of a yarn family's mean colour that counts as right.
pub const COLOUR_TOLERANCE: f32 = 0.05;

/// Coverage above which a label pixel belongs to one yarn family only.
const PURE_COVERAGE: f32 = 0.95;

/// One image of the folder.
#[derive(Clone, Debug)]
pub struct RenderCase {
    /// File stem.
    pub name: String,
    /// True pattern in woven's convention.
    pub truth: String,
    /// Fitted pattern (`-` when the fit failed).
    pub fit: String,
    /// Fitted pattern equal to the truth up to a cyclic shift.
    pub exact: bool,
    /// PSNR of the fit against the crop it matched (sRGB, dB).
    pub crop_psnr_db: f32,
    /// PSNR of `fit.png` (the fit registered to the input, with the input's own blur as the fit
    /// measured it) against the whole input (sRGB, dB); `None` where preparation did not run.
    pub photo_psnr_db: Option<f32>,
    /// Largest per-channel distance of the fit's warp and weft mean colours from the input's
    /// (linear), when the folder has label maps ([`FamilyColours::error`]).
    pub colour_err: Option<f32>,
    /// The family colours behind `colour_err`.
    pub colours: Option<FamilyColours>,
    /// Fit seconds.
    pub secs: f64,
    /// Why the fit failed.
    pub error: Option<String>,
    /// Contact-sheet row: the crop the fit matched | the fit as compared (blurred like the crop) |
    /// 4× the sRGB error (as in `compare.png`).
    pub row: Option<Image>,
}

/// Summary of a folder's cases.
#[derive(Clone, Debug)]
pub struct RenderReport {
    /// The cases, in file-name order.
    pub cases: Vec<RenderCase>,
}

impl RenderReport {
    /// The last line `woven eval --renders` prints.
    pub fn summary_line(&self) -> String {
        let n = self.cases.len();
        let frac =
            |f: &dyn Fn(&RenderCase) -> bool| self.cases.iter().filter(|c| f(c)).count() as f32 / n.max(1) as f32;
        let psnr: Vec<f32> = self.cases.iter().map(|c| c.crop_psnr_db).collect();
        let photo: Vec<f32> = self.cases.iter().filter_map(|c| c.photo_psnr_db).collect();
        let secs: Vec<f32> = self.cases.iter().map(|c| c.secs as f32).collect();
        let coloured: Vec<&RenderCase> = self.cases.iter().filter(|c| c.colour_err.is_some()).collect();
        let colour_ok = coloured.iter().filter(|c| c.colour_err.is_some_and(|e| e <= COLOUR_TOLERANCE)).count();
        format!(
            "renders: n={n} pattern_exact={:.2} median_crop_psnr_db={:.1} median_photo_psnr_db={:.1} colour_within_{COLOUR_TOLERANCE}={}/{} failed={} median_fit_s={:.1}",
            frac(&|c| c.exact),
            quantile(&psnr, 0.5),
            quantile(&photo, 0.5),
            colour_ok,
            coloured.len(),
            self.cases.iter().filter(|c| c.error.is_some()).count(),
            quantile(&secs, 0.5),
        )
    }

    /// The contact sheet: one row per fitted image (crop | fit | 4× error), black gaps.
    pub fn sheet(&self) -> Option<Image> {
        let rows: Vec<&Image> = self.cases.iter().filter_map(|c| c.row.as_ref()).collect();
        (!rows.is_empty()).then(|| Image::vstack(&rows, 4))
    }

    /// Markdown table of the cases plus the summary line.
    pub fn markdown(&self) -> String {
        let mut s = String::from(
            "| image | truth | fit | exact | crop PSNR (dB) | fit.png PSNR (dB) | colour error | time (s) |\n|---|---|---|---|---|---|---|---|\n",
        );
        for c in &self.cases {
            s += &format!(
                "| {} | {} | {} | {} | {:.1} | {} | {} | {:.1} |\n",
                c.name,
                c.truth,
                c.error.as_deref().map_or(c.fit.clone(), |e| format!("failed: {e}")),
                if c.exact { "yes" } else { "no" },
                c.crop_psnr_db,
                c.photo_psnr_db.map_or("–".into(), |p| format!("{p:.1}")),
                c.colour_err.map_or("–".into(), |e| format!("{e:.3}")),
                c.secs
            );
        }
        s += &format!("\n`{}`\n", self.summary_line());
        s
    }
}

/// The truth of a renderer's pattern matrix (1 = warp on top, row 0 at the image top) in woven's
/// convention (see the module docs).
pub fn truth_from_renderer(rows: &[Vec<u8>]) -> Result<WeavePattern> {
    if rows.is_empty() || rows.iter().any(|r| r.len() != rows[0].len() || r.is_empty()) {
        bail!("the pattern must be a non-empty rectangular matrix of 0/1");
    }
    let woven: Vec<Vec<bool>> = rows.iter().rev().map(|r| r.iter().map(|&v| v == 0).collect()).collect();
    Ok(WeavePattern::from_rows(&woven)?)
}

/// The images of `dir` that have a `.json` beside them, sorted by name.
fn image_stems(dir: &Path) -> Result<Vec<String>> {
    let mut stems: Vec<String> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(|e| e.ok())
        .filter_map(|e| e.file_name().into_string().ok())
        .filter_map(|n| n.strip_suffix(".json").map(str::to_string))
        .filter(|s| s != "index" && (dir.join(format!("{s}.exr")).is_file() || dir.join(format!("{s}.png")).is_file()))
        .collect();
    stems.sort();
    if stems.is_empty() {
        bail!("{} holds no NAME.json with NAME.exr or NAME.png beside it", dir.display());
    }
    Ok(stems)
}

/// Mean colour (linear RGB) of each yarn family, `[warp, weft]`, in the input and in the fit
/// registered to it, over the same label pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FamilyColours {
    /// The input's `[warp, weft]` means.
    pub input: [[f32; 3]; 2],
    /// The registered fit's `[warp, weft]` means over the same pixels.
    pub fit: [[f32; 3]; 2],
}

impl FamilyColours {
    /// Largest per-channel distance `max_{family, k} |fit − input|`: the colour figure.
    pub fn error(&self) -> f32 {
        (0..2)
            .flat_map(|f| (0..3).map(move |k| (f, k)))
            .map(|(f, k)| (self.fit[f][k] - self.input[f][k]).abs())
            .fold(0.0, f32::max)
    }

    /// `warp in (r g b) fit (r g b) weft in (…) fit (…)`, two decimals.
    pub fn describe(&self) -> String {
        let c = |v: [f32; 3]| format!("({:.2} {:.2} {:.2})", v[0], v[1], v[2]);
        format!(
            "warp in {} fit {} weft in {} fit {}",
            c(self.input[0]),
            c(self.fit[0]),
            c(self.input[1]),
            c(self.fit[1])
        )
    }
}

/// The input's mean colour of the pixels that belong to the warp (`warp = true`) or the weft
/// only, from the label map (R = warp, G = weft coverage).
fn family_mean(img: &Image, labels: &Image, warp: bool) -> Option<[f32; 3]> {
    if (img.width, img.height) != (labels.width, labels.height) {
        return None;
    }
    let mut sum = [0.0f64; 3];
    let mut n = 0usize;
    for (p, l) in img.data.iter().zip(&labels.data) {
        // Labels are stored as sRGB PNG: coverage 1 decodes to 1, 0 to 0.
        let cov = if warp { l[0] } else { l[1] };
        if cov >= PURE_COVERAGE {
            (0..3).for_each(|k| sum[k] += p[k] as f64);
            n += 1;
        }
    }
    (n > 0).then(|| sum.map(|v| (v / n as f64) as f32))
}

/// The family colours of the input and of `fit`, the fit registered to the input (same size,
/// [`registered_render_sharp`](super::output::registered_render_sharp)), each averaged over the SAME pure-label pixels: the visible part of
/// each family where it lies on top, as the issue defines the figure. Averaging both over one set
/// of pixels compares like with like — a shading gradient across a yarn (brighter crown, darker
/// flanks) is in both means alike, and a fit registered to the wrong cells or coloured wrongly
/// shows. `None` when the sizes differ or a family has no pure pixel.
fn family_colours(input: &Image, labels: &Image, fit: &Image) -> Option<FamilyColours> {
    if (fit.width, fit.height) != (input.width, input.height) {
        return None;
    }
    let input_means = [family_mean(input, labels, true)?, family_mean(input, labels, false)?];
    let fit_means = [family_mean(fit, labels, true)?, family_mean(fit, labels, false)?];
    Some(FamilyColours { input: input_means, fit: fit_means })
}

/// Height of a contact-sheet row, pixels.
const SHEET_ROW_H: u32 = 128;

/// Fit and score one image of the folder.
fn eval_image(
    dir: &Path,
    name: &str,
    opts: &FitOptions,
    estimate_lights: bool,
    save: Option<&Path>,
) -> Result<RenderCase> {
    let meta: serde_json::Value = serde_json::from_str(&crate::io::read_text_capped(
        &dir.join(format!("{name}.json")),
        crate::io::MAX_PARAM_FILE_BYTES,
    )?)
    .with_context(|| format!("parsing {name}.json"))?;
    let rows: Vec<Vec<u8>> = serde_json::from_value(meta["pattern"].clone())
        .with_context(|| format!("{name}.json: `pattern` must be a matrix of 0/1"))?;
    let truth = truth_from_renderer(&rows).with_context(|| format!("{name}.json"))?;
    let exr = dir.join(format!("{name}.exr"));
    let path = if exr.is_file() { exr } else { dir.join(format!("{name}.png")) };
    let input = Image::load(&path, super::MIN_INPUT_SIDE)?;
    let labels = Image::load(&dir.join(format!("{name}_labels.png")), 1).ok();
    let t = Instant::now();
    let mut case = RenderCase {
        name: name.to_string(),
        truth: truth.to_string(),
        fit: "-".into(),
        exact: false,
        crop_psnr_db: 0.0,
        photo_psnr_db: None,
        colour_err: None,
        colours: None,
        secs: 0.0,
        error: None,
        row: None,
    };
    match fit_as_user(&input, opts, estimate_lights) {
        Ok(res) => {
            case.secs = t.elapsed().as_secs_f64();
            case.fit = res.params.cloth.pattern.reduced().to_string();
            case.exact = res.params.cloth.pattern.reduced().equivalent(&truth.reduced());
            case.crop_psnr_db = res.psnr_db;
            case.row = Some(sheet_row(&res.target, &res.observed_render(), SHEET_ROW_H));
            // Saved, the outputs' registration (one render of the repeat) serves the scores too.
            let mut registered = None;
            if let Some(s) = save {
                let written = write_fit_outputs(&res, &s.join(name), true, opts.control.threads)?;
                registered = written.registered;
            }
            let size = (input.width, input.height);
            let registered = registered.or_else(|| registered_pair(&res, size, opts.control.threads));
            case.photo_psnr_db = registered.as_ref().map(|r| r.blurred.psnr_srgb(&input));
            if let Some(l) = &labels {
                case.colours = registered.as_ref().and_then(|r| family_colours(&input, l, &r.sharp));
                case.colour_err = case.colours.map(|c| c.error());
            }
        }
        Err(e) => {
            case.secs = t.elapsed().as_secs_f64();
            case.error = Some(format!("{e:#}"));
        }
    }
    Ok(case)
}

/// The fit of `input` as `woven fit` makes it: prepared first, and with `estimate_lights` the
/// light rig of the capture estimated from the preparation (`capture::estimate_capture`) in place
/// of `opts.render.lights` where one is estimated; a preparation that fails leaves the fit to
/// report it.
fn fit_as_user(input: &Image, opts: &FitOptions, estimate_lights: bool) -> Result<super::FitResult> {
    if !opts.input.prep {
        return fit(input, opts);
    }
    match crate::prep::prepare(&input.to_rgb32f(), &crate::prep::PrepOptions::default()) {
        Ok(p) => {
            let mut o = opts.clone();
            if let Some(c) = estimate_capture(&p).filter(|_| estimate_lights) {
                c.apply(&mut o.render);
            }
            fit_prepared(input, Some(p), &o)
        }
        Err(_) => fit(input, opts),
    }
}

/// Fit every image of `dir` with `opts` (preparation on) and score it; `on_case` is called as
/// each image is done. With `estimate_lights`, each image's light rig is the capture estimated
/// from it (as `woven fit` does without `--lights`), else `opts.render.lights`. With `save`, each
/// fit's outputs go to `save/NAME/`.
pub fn eval_renders(
    dir: &Path,
    opts: &FitOptions,
    estimate_lights: bool,
    save: Option<&PathBuf>,
    on_case: &mut dyn FnMut(&RenderCase),
) -> Result<RenderReport> {
    let mut cases = Vec::new();
    for name in image_stems(dir)? {
        let case = eval_image(dir, &name, opts, estimate_lights, save.map(|p| p.as_path()))?;
        on_case(&case);
        cases.push(case);
    }
    Ok(RenderReport { cases })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn renderer_truth_is_inverted_and_flipped_top_to_bottom() {
        // A 3/1 twill in the renderer's convention (1 = warp on top, row 0 at the top).
        let rows = vec![vec![1, 1, 1, 0], vec![0, 1, 1, 1], vec![1, 0, 1, 1], vec![1, 1, 0, 1]];
        let p = truth_from_renderer(&rows).unwrap();
        // Rows reversed (woven's row 0 is the bottom weft) and inverted (1 = weft over warp).
        let b = |r: &[u8]| r.iter().map(|&v| v == 1).collect::<Vec<bool>>();
        let want =
            WeavePattern::from_rows(&[b(&[0, 0, 1, 0]), b(&[0, 1, 0, 0]), b(&[1, 0, 0, 0]), b(&[0, 0, 0, 1])]).unwrap();
        assert!(p.equivalent(&want), "{p}");
        // Inverted only (rows kept) is the twill running the other way: not the same cloth.
        let mirrored =
            WeavePattern::from_rows(&[b(&[0, 0, 0, 1]), b(&[1, 0, 0, 0]), b(&[0, 1, 0, 0]), b(&[0, 0, 1, 0])]).unwrap();
        assert!(!p.equivalent(&mirrored));
        assert!(truth_from_renderer(&[vec![1, 0], vec![1]]).is_err());
        assert!(truth_from_renderer(&[]).is_err());
    }

    #[test]
    fn family_colours_come_from_pure_label_pixels() {
        let img = Image::new(2, 2, vec![[0.2, 0.1, 0.0], [0.6, 0.5, 0.4], [0.9; 3], [0.4, 0.3, 0.2]]);
        let labels = Image::new(2, 2, vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.5, 0.5, 0.0], [1.0, 0.0, 0.0]]);
        let warp = family_mean(&img, &labels, true).unwrap();
        assert!((warp[0] - 0.3).abs() < 1e-6 && (warp[2] - 0.1).abs() < 1e-6);
        assert_eq!(family_mean(&img, &labels, false).unwrap(), [0.6, 0.5, 0.4]);
        assert!(family_mean(&img, &Image::new(1, 1, vec![[1.0; 3]]), true).is_none());
    }

    #[test]
    fn the_colour_error_compares_the_same_pixels_and_catches_a_misregistered_or_miscoloured_fit() {
        // Vertical stripes 4 px wide: warp (red) in columns 0–3, weft (blue) in 4–7, repeated; a
        // shading gradient across each stripe (bright centre, dark flanks), as a yarn's has.
        let (w, h) = (32u32, 8u32);
        let shade = |x: u32| 0.6 + 0.4 * (1.0 - ((x % 4) as f32 - 1.5).abs() / 1.5);
        let warp_col = [0.5, 0.1, 0.1];
        let weft_col = [0.1, 0.1, 0.5];
        let paint = |offset: u32, warp: [f32; 3], weft: [f32; 3]| {
            let data = (0..w * h)
                .map(|i| {
                    let x = (i % w + offset) % w;
                    let c = if (x / 4).is_multiple_of(2) { warp } else { weft };
                    c.map(|v| v * shade(x))
                })
                .collect();
            Image::new(w, h, data)
        };
        let labels = Image::new(
            w,
            h,
            (0..w * h).map(|i| if (i % w / 4).is_multiple_of(2) { [1.0, 0.0, 0.0] } else { [0.0, 1.0, 0.0] }).collect(),
        );
        let input = paint(0, warp_col, weft_col);
        // The same cloth, registered: no error, shading and all.
        let same = family_colours(&input, &labels, &input).unwrap();
        assert!(same.error() < 1e-6, "{same:?}");
        // Registered one stripe off: each family's pixels show the other family.
        let shifted = family_colours(&input, &labels, &paint(4, warp_col, weft_col)).unwrap();
        // Red 0.5 against 0.1, times the mean shade 0.733: 0.293.
        assert!((shifted.error() - 0.2933).abs() < 1e-3, "{shifted:?}");
        // Registered, but the weft's blue too bright by 0.1 before shading (mean shade 0.733).
        let bright = family_colours(&input, &labels, &paint(0, warp_col, [0.1, 0.1, 0.6])).unwrap();
        assert!((bright.error() - 0.0733).abs() < 1e-3, "{bright:?}");
        assert_eq!(bright.fit[0], bright.input[0]);
        // A fit of another size cannot be compared pixel for pixel.
        assert!(family_colours(&input, &labels, &Image::filled(8, 8, [0.5; 3])).is_none());
    }

    #[test]
    fn the_summary_gives_the_median_fit_png_psnr_over_the_prepared_fits() {
        let case = |photo: Option<f32>| RenderCase {
            name: "m".into(),
            truth: "10/01".into(),
            fit: "10/01".into(),
            exact: true,
            crop_psnr_db: 30.0,
            photo_psnr_db: photo,
            colour_err: Some(0.01),
            colours: None,
            secs: 10.0,
            error: None,
            row: None,
        };
        let rep = RenderReport { cases: vec![case(Some(20.0)), case(None), case(Some(24.0)), case(Some(22.0))] };
        let line = rep.summary_line();
        assert!(line.contains("median_crop_psnr_db=30.0 median_photo_psnr_db=22.0 "), "{line}");
        assert!(rep.markdown().contains("| 30.0 | – | 0.010 |"), "{}", rep.markdown());
    }

    #[test]
    fn a_folder_without_images_is_an_error() {
        let dir = std::env::temp_dir().join(format!("woven_renders_empty_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let e = eval_renders(&dir, &FitOptions::fast(), true, None, &mut |_| {}).unwrap_err();
        assert!(e.to_string().contains("holds no NAME.json"), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }
}
