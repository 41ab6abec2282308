//! Evaluation on real photos (`woven eval --real DIR`, issue 14): fits every photo listed in
//! `DIR/labels.csv` the way a user would (`woven fit PHOTO` with no flags: preparation, the capture
//! estimated from the photo, the fit) and scores what a label can check and what a user sees:
//! - the weave class of the fitted pattern ([`crate::pattern::WeavePattern::weave_class`]: plain, twill, satin,
//!   basket, other — equal up to shift, rotation, transposition and inversion) against the label;
//! - PSNR and SSIM of the fit, registered to the photo ([`registered_render`]), against the whole
//!   photo, beside the PSNR of the fit against the one-repeat crop it matched;
//! - the time of each fit; a photo that fails counts as failed (and as a wrong class), with its
//!   message, which says what to try.
//!
//! `labels.csv`: a header naming the columns `path` (relative to `DIR`) and `weave_label` (a
//! [`WeaveClass`] name), other columns ignored; fields may be double-quoted (`""` inside quotes is
//! a quote).

use super::capture::{estimate_capture, CaptureEstimate};
use super::output::{photo_scores, registered_render, sheet_row, sheet_tile, write_fit_outputs, PhotoScores};
use super::report::quantile;
use super::{fit_prepared, FitOptions};
use crate::image_io::Image;
use crate::pattern::WeaveClass;
use crate::prep::Prepared;
use crate::prep::{diagnostic_overlay, prepare, PrepOptions};
use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Largest `labels.csv` read, bytes (a list of photos, not a data file).
const MAX_LABELS_BYTES: u64 = 4 << 20;

/// Height of a contact-sheet row, pixels.
const SHEET_ROW_H: u32 = 160;

/// One line of `labels.csv`.
#[derive(Clone, Debug, PartialEq)]
pub struct RealLabel {
    /// Photo path relative to the folder.
    pub path: String,
    /// The labelled weave class.
    pub class: WeaveClass,
}

/// Split one CSV line into fields (RFC 4180 quoting within the line).
fn csv_fields(line: &str) -> Result<Vec<String>> {
    let mut fields = Vec::new();
    let mut cur = String::new();
    let mut quoted = false;
    let mut chars = line.chars().peekable();
    while let Some(c) = chars.next() {
        match (c, quoted) {
            ('"', true) if chars.peek() == Some(&'"') => {
                cur.push('"');
                chars.next();
            }
            ('"', true) => quoted = false,
            ('"', false) if cur.is_empty() => quoted = true,
            (',', false) => fields.push(std::mem::take(&mut cur)),
            (c, _) => cur.push(c),
        }
    }
    if quoted {
        bail!("unterminated quoted field");
    }
    fields.push(cur);
    Ok(fields)
}

/// Parse the text of a `labels.csv` (see the module docs).
pub fn parse_labels(text: &str) -> Result<Vec<RealLabel>> {
    let mut lines = text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty());
    let (_, header) = lines.next().context("labels.csv is empty: it needs a header `path,weave_label`")?;
    let names: Vec<String> = csv_fields(header)?.iter().map(|s| s.trim().to_ascii_lowercase()).collect();
    let col = |name: &str| {
        names.iter().position(|n| n == name).with_context(|| {
            format!("labels.csv: the header {header:?} has no `{name}` column (it needs `path,weave_label`)")
        })
    };
    let (pc, lc) = (col("path")?, col("weave_label")?);
    let mut out = Vec::new();
    for (i, line) in lines {
        let f = csv_fields(line).with_context(|| format!("labels.csv line {}", i + 1))?;
        let get = |k: usize| {
            f.get(k)
                .map(|s| s.trim().to_string())
                .filter(|s| !s.is_empty())
                .with_context(|| format!("labels.csv line {}: {line:?} has no {} field", i + 1, names[k]))
        };
        let path = get(pc)?;
        let class = get(lc)?.parse::<WeaveClass>().with_context(|| format!("labels.csv line {}", i + 1))?;
        out.push(RealLabel { path, class });
    }
    if out.is_empty() {
        bail!("labels.csv lists no photo");
    }
    Ok(out)
}

/// Read and parse `dir/labels.csv`.
pub fn read_labels(dir: &Path) -> Result<Vec<RealLabel>> {
    let path = dir.join("labels.csv");
    let text = crate::io::read_text_capped(&path, MAX_LABELS_BYTES).with_context(|| {
        format!("reading {} (a folder for --real needs labels.csv: path,weave_label)", path.display())
    })?;
    parse_labels(&text).with_context(|| format!("in {}", path.display()))
}

/// One photo of the folder.
#[derive(Clone, Debug)]
pub struct RealCase {
    /// Photo path relative to the folder.
    pub path: String,
    /// Labelled class.
    pub label: WeaveClass,
    /// Class of the fitted pattern (`None` when the fit failed).
    pub class: Option<WeaveClass>,
    /// Fitted pattern (`-` when the fit failed).
    pub pattern: String,
    /// The capture the fit assumed, when estimated from the photo.
    pub capture: Option<CaptureEstimate>,
    /// The registered fit against the whole photo.
    pub photo: Option<PhotoScores>,
    /// PSNR of the fit against the crop it matched, dB.
    pub crop_psnr_db: Option<f32>,
    /// [`periodic_ceiling`] of the photo's preparation, dB: the whole-photo PSNR of a fit that
    /// matched its target exactly.
    pub ceiling_db: Option<f32>,
    /// Seconds from loading the photo to the end of the fit (scoring and files excluded).
    pub secs: f64,
    /// Why the photo failed.
    pub error: Option<String>,
    /// Contact-sheet row: photo | registered fit | 4× error (or the preparation overlay when the
    /// photo failed).
    pub row: Option<Image>,
}

impl RealCase {
    /// A case of photo `path` labelled `label`, before anything is found.
    fn new(path: String, label: WeaveClass) -> Self {
        RealCase {
            path,
            label,
            class: None,
            pattern: "-".into(),
            capture: None,
            photo: None,
            crop_psnr_db: None,
            ceiling_db: None,
            secs: 0.0,
            error: None,
            row: None,
        }
    }

    /// Whether the class found is the label's.
    pub fn class_right(&self) -> bool {
        self.class == Some(self.label)
    }
}

/// Options of [`eval_real`].
#[derive(Clone, Debug)]
pub struct RealOptions {
    /// Fit options for every photo (preparation on).
    pub fit: FitOptions,
    /// Estimate the capture of each photo (otherwise `fit.render.lights` is used).
    pub estimate_lights: bool,
    /// Fit only the first `limit` photos of the list.
    pub limit: Option<usize>,
    /// Write each fit's outputs to `save/<photo path without extension>/`.
    pub save: Option<PathBuf>,
}

/// The cases of a folder.
#[derive(Clone, Debug)]
pub struct RealReport {
    /// The cases, in the order of `labels.csv`.
    pub cases: Vec<RealCase>,
}

/// Median of the values, `NaN` when there are none.
fn median(v: impl Iterator<Item = f32>) -> f32 {
    quantile(&v.collect::<Vec<f32>>(), 0.5)
}

impl RealReport {
    /// The last line `woven eval --real` prints. Medians of PSNR and time are over the photos that
    /// were fitted; the class accuracy is over all (a failed photo counts as wrong).
    pub fn summary_line(&self) -> String {
        let n = self.cases.len();
        let ok: Vec<&RealCase> = self.cases.iter().filter(|c| c.error.is_none()).collect();
        format!(
            "real: n={n} class_acc={:.2} median_psnr_db={:.1} median_crop_psnr_db={:.1} failed={} median_fit_s={:.1}",
            self.cases.iter().filter(|c| c.class_right()).count() as f32 / n.max(1) as f32,
            median(ok.iter().filter_map(|c| c.photo.map(|s| s.psnr_db))),
            median(ok.iter().filter_map(|c| c.crop_psnr_db)),
            n - ok.len(),
            median(ok.iter().map(|c| c.secs as f32)),
        )
    }

    /// The line printed before [`RealReport::summary_line`]: the median [`periodic_ceiling`] over
    /// the fitted photos beside their median whole-photo PSNR, so the gap a better fit could still
    /// close is told apart from what no periodic replica can reach (hair, irregular yarns).
    pub fn ceiling_line(&self) -> String {
        let ok: Vec<&RealCase> = self.cases.iter().filter(|c| c.error.is_none()).collect();
        format!(
            "periodic ceiling (the photo's own mean repeat, unblurred, registered to the photo): median {:.1} dB over {} fitted photos; their fits: median {:.1} dB",
            median(ok.iter().filter_map(|c| c.ceiling_db)),
            ok.len(),
            median(ok.iter().filter_map(|c| c.photo.map(|s| s.psnr_db))),
        )
    }

    /// Markdown table of the cases plus the summary line.
    pub fn markdown(&self) -> String {
        let mut s = String::from(
            "| photo | label | class found | pattern | capture | photo PSNR (dB) | ceiling (dB) | photo SSIM | crop PSNR (dB) | time (s) |\n|---|---|---|---|---|---|---|---|---|---|\n",
        );
        for c in &self.cases {
            let found = match (&c.error, c.class) {
                (Some(e), _) => format!("failed: {}", e.replace('|', "/")),
                (None, Some(k)) => format!("{k}{}", if c.class_right() { "" } else { " ✗" }),
                (None, None) => "-".into(),
            };
            s += &format!(
                "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {:.1} |\n",
                c.path,
                c.label,
                found,
                c.pattern,
                c.capture.map_or("-".into(), |k| k.capture.name().to_string()),
                c.photo.map_or("-".into(), |p| format!("{:.1}", p.psnr_db)),
                c.ceiling_db.map_or("-".into(), |p| format!("{p:.1}")),
                c.photo.map_or("-".into(), |p| format!("{:.3}", p.ssim)),
                c.crop_psnr_db.map_or("-".into(), |p| format!("{p:.1}")),
                c.secs
            );
        }
        s += &format!("\n{}\n\n`{}`\n", self.ceiling_line(), self.summary_line());
        s
    }

    /// The contact sheet: one row per photo (photo | fit | 4× error, or photo | preparation
    /// overlay for a failed one), black gaps; `None` for no rows.
    pub fn sheet(&self) -> Option<Image> {
        let rows: Vec<&Image> = self.cases.iter().filter_map(|c| c.row.as_ref()).collect();
        if rows.is_empty() {
            return None;
        }
        // Rows differ in width (photos differ in aspect); `vstack` pads each to the widest.
        Some(Image::vstack(&rows, 4))
    }
}

/// PSNR (sRGB) against `photo` of the photo's own periodic picture — the mean of the aligned
/// repeats of the rectified photo *without* the blur preparation gives the fit's target
/// (`prep::regularize::mean_of_repeats` on `Prepared::rectified`), each repeat moved back by its
/// drift — mapped back to the photo through `H⁻¹` as `fit.png` is: Keys cubic, and beyond the
/// rectified image (the photo's corners that the rotation cropped away) continued by whole
/// periods, as `fit.png` continues its repeat. A periodic replica that matched every repeat's
/// mean exactly would score this against the whole photo: the ceiling of the whole-photo PSNR
/// for any periodic replica of this preparation. What the photo holds beyond one repeated tile
/// (flyaway fibres, yarns that wander, uneven lighting) lies above it.
///
/// Why not the blurred `Prepared::regularized`: `fit.png` carries the photo's own blur only
/// (`output::registered_render`), so the blurred mean understated the ceiling by the σ = pitch/16
/// blur (a twill 2/2 rendered by woven at 16 px a yarn: 22.9 dB, while its fit.png scored
/// 31.7 dB and the sharp mean 37 dB).
pub fn periodic_ceiling(prepared: &Prepared, photo: &Image) -> f32 {
    let p = prepared;
    let (mean, drift) = crate::prep::regularize::mean_of_repeats(
        &p.rectified,
        [p.pitch_x, p.pitch_y],
        p.period_x,
        p.period_y,
        &crate::prep::regularize::RepeatParams::default(),
    );
    let inv = crate::math::linalg::mat3_inv(&p.homography).unwrap_or(crate::math::linalg::IDENTITY);
    let (rw, rh) = (mean.width() as usize, mean.height() as usize);
    let (w, h) = (rw as f64, rh as f64);
    // A coordinate outside [0, n − 1] moved by whole periods to inside (clamped on an axis without
    // a repeat, or one too short for it).
    let wrap = |a: f64, n: f64, period: f32, repeated: bool| -> f64 {
        let period = period as f64;
        if repeated && period >= 1.0 && period < n - 1.0 && !(0.0..=n - 1.0).contains(&a) {
            let k = if a < 0.0 { (-a / period).ceil() } else { -((a - (n - 1.0)) / period).ceil() };
            (a + k * period).clamp(0.0, n - 1.0)
        } else {
            a.clamp(0.0, n - 1.0)
        }
    };
    let mut data = Vec::with_capacity((photo.width * photo.height) as usize);
    for y in 0..photo.height {
        for x in 0..photo.width {
            let (u, v) = crate::math::linalg::apply(&inv, x as f64, y as f64);
            let s = drift.shift_at(u, v);
            let a = wrap(u - s[0], w, p.period_x, p.repeated_x);
            let b = wrap(v - s[1], h, p.period_y, p.repeated_y);
            let mut px = [0.0f32; 3];
            crate::prep::image_ops::sample_cubic_into(mean.as_raw(), rw, rh, 3, a, b, &mut px);
            data.push(px);
        }
    }
    Image::new(photo.width, photo.height, data).psnr_srgb(photo)
}

/// Path of a photo's outputs under `save`: its path in the folder without the extension.
fn save_dir(save: &Path, rel: &str) -> PathBuf {
    save.join(Path::new(rel).with_extension(""))
}

/// Fit and score one photo.
fn eval_photo(dir: &Path, label: &RealLabel, opts: &RealOptions) -> RealCase {
    let mut case = RealCase::new(label.path.clone(), label.class);
    let t = Instant::now();
    let input = match Image::load(&dir.join(&label.path), super::MIN_INPUT_SIDE)
        .map_err(anyhow::Error::from)
        .and_then(|img| super::check_input(&img).map(|_| img))
    {
        Ok(img) => img,
        Err(e) => {
            case.error = Some(format!("{e:#}"));
            return case;
        }
    };
    let mut fopts = opts.fit.clone();
    // Preparation runs here first (about a second at most) to estimate the capture before the fit,
    // and so that a photo whose repeat cannot be found fails in seconds with the overlay to look at.
    let rgb = input.to_rgb32f();
    let prepared = match prepare(&rgb, &PrepOptions::default()) {
        Ok(p) => {
            if opts.estimate_lights {
                case.capture = estimate_capture(&p);
                if let Some(k) = &case.capture {
                    k.apply(&mut fopts.render);
                }
            }
            p
        }
        Err(e) => {
            case.secs = t.elapsed().as_secs_f64();
            case.error = Some(e.to_string());
            if let Some(ov) = diagnostic_overlay(&rgb, &PrepOptions::default()) {
                let ov = Image::from_rgb32f(&ov);
                case.row = Some(Image::hstack(&[&sheet_tile(&input, SHEET_ROW_H), &sheet_tile(&ov, SHEET_ROW_H)], 2));
                if let Some(s) = &opts.save {
                    let d = save_dir(s, &label.path);
                    if std::fs::create_dir_all(&d).is_ok() {
                        // The overlay is a help to look at; failing to write it is not the photo's failure.
                        let _ = ov.save_png(&d.join("prep_grid.png"));
                    }
                }
            }
            return case;
        }
    };
    case.ceiling_db = Some(periodic_ceiling(&prepared, &input));
    // The fit takes this preparation rather than running it again.
    match fit_prepared(&input, Some(prepared), &fopts) {
        Ok(res) => {
            case.secs = t.elapsed().as_secs_f64();
            case.class = Some(res.params.cloth.pattern.weave_class());
            case.pattern = res.params.cloth.pattern.to_string();
            case.crop_psnr_db = Some(res.psnr_db);
            let threads = fopts.control.threads;
            // Saved, fit.png's registered render is the one scored.
            let mut registered = None;
            if let Some(s) = &opts.save {
                let d = save_dir(s, &label.path);
                let written = write_fit_outputs(&res, &d, true, threads).and_then(|w| {
                    registered = w.registered.map(|r| r.blurred);
                    let json = serde_json::to_string_pretty(&case.capture)?;
                    crate::io::write_atomic(&d.join("capture.json"), json.as_bytes())?;
                    Ok(())
                });
                if let Err(e) = written {
                    case.error = Some(format!("fitted, but writing {} failed: {e:#}", d.display()));
                }
            }
            if let Some(reg) = registered.or_else(|| registered_render(&res, (input.width, input.height), threads)) {
                case.photo = Some(photo_scores(&reg, &input));
                case.row = Some(sheet_row(&input, &reg, SHEET_ROW_H));
            }
        }
        Err(e) => {
            case.secs = t.elapsed().as_secs_f64();
            case.error = Some(format!("{e:#}"));
        }
    }
    case
}

/// Fit every photo of `dir/labels.csv` (the first `opts.limit`) and score it; `on_case` is called
/// as each photo is done. Errors only for a folder without a readable `labels.csv`; a photo that
/// cannot be read or fitted is a failed case.
pub fn eval_real(dir: &Path, opts: &RealOptions, on_case: &mut dyn FnMut(&RealCase)) -> Result<RealReport> {
    let mut labels = read_labels(dir)?;
    if let Some(n) = opts.limit {
        if n == 0 {
            bail!("--limit 0 fits no photo; give at least 1");
        }
        labels.truncate(n);
    }
    let mut cases = Vec::new();
    for l in &labels {
        let case = eval_photo(dir, l, opts);
        on_case(&case);
        cases.push(case);
    }
    Ok(RealReport { cases })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn labels_parse_with_quotes_and_extra_columns() {
        let text =
            "path,weave_label,note\na/W1.jpg,twill,FabricNET label\n\n\"b,c.png\",Satin,\"4-end, \"\"crowfoot\"\"\"\n";
        let l = parse_labels(text).unwrap();
        assert_eq!(l.len(), 2);
        assert_eq!(l[0], RealLabel { path: "a/W1.jpg".into(), class: WeaveClass::Twill });
        assert_eq!(l[1].path, "b,c.png");
        assert_eq!(l[1].class, WeaveClass::Satin);
        assert_eq!(csv_fields("\"x \"\"y\"\"\",z").unwrap(), ["x \"y\"", "z"]);
        // Columns may come in any order.
        assert_eq!(parse_labels("weave_label,path\nplain,p.png").unwrap()[0].path, "p.png");
    }

    #[test]
    fn bad_labels_are_refused_with_the_line() {
        let e = |t: &str| format!("{:#}", parse_labels(t).unwrap_err());
        assert!(e("").contains("empty"));
        assert!(e("file,class\na,plain").contains("no `path` column"));
        assert!(e("path,weave_label\n").contains("no photo"));
        assert!(
            e("path,weave_label\na.png,jacquard").contains("line 2")
                && e("path,weave_label\na.png,jacquard").contains("jacquard")
        );
        assert!(e("path,weave_label\na.png").contains("line 2: \"a.png\" has no weave_label field"));
        assert!(e("path,weave_label\n\"a.png,plain").contains("unterminated"));
    }

    #[test]
    fn the_summary_counts_failures_as_wrong_and_medians_over_fits() {
        let case = |label, class, psnr: Option<f32>, err: Option<&str>, secs| RealCase {
            path: "p".into(),
            label,
            class,
            pattern: "-".into(),
            capture: None,
            photo: psnr.map(|p| PhotoScores { psnr_db: p, ssim: 0.5 }),
            crop_psnr_db: psnr.map(|p| p + 5.0),
            ceiling_db: None,
            secs,
            error: err.map(str::to_string),
            row: None,
        };
        use WeaveClass::*;
        let rep = RealReport {
            cases: vec![
                case(Plain, Some(Plain), Some(20.0), None, 30.0),
                case(Twill, Some(Satin), Some(24.0), None, 50.0),
                case(Satin, None, None, Some("no repeat"), 1.0),
                case(Twill, Some(Twill), Some(22.0), None, 40.0),
            ],
        };
        assert_eq!(
            rep.summary_line(),
            "real: n=4 class_acc=0.50 median_psnr_db=22.0 median_crop_psnr_db=27.0 failed=1 median_fit_s=40.0"
        );
        let md = rep.markdown();
        assert!(md.contains("failed: no repeat") && md.contains("satin ✗"), "{md}");
        assert!(rep.sheet().is_none());
        assert_eq!(save_dir(Path::new("out"), "fabricnet/W1.jpg"), Path::new("out/fabricnet/W1"));
    }

    #[test]
    fn sheet_rows_of_different_widths_are_padded() {
        let mut rep = RealReport { cases: Vec::new() };
        for w in [40, 90] {
            let photo = Image::filled(w, 30, [0.5; 3]);
            let row = sheet_row(&photo, &photo, SHEET_ROW_H);
            assert_eq!(row.height, SHEET_ROW_H);
            rep.cases.push(RealCase { row: Some(row), ..RealCase::new("p".into(), WeaveClass::Plain) });
        }
        let sheet = rep.sheet().unwrap();
        assert_eq!(sheet.height, 2 * SHEET_ROW_H + 4);
        assert_eq!(sheet.width, rep.cases[1].row.as_ref().unwrap().width);
    }
}
