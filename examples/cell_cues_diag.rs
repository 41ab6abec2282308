//! Diagnostic of the picture's cell cues (`woven::fit::cell_cues`) on photos or renders:
//!
//! `cargo run --release --example cell_cues_diag -- IMAGE [TRUTH_PATTERN]...`
//!
//! prepares each image as `woven fit` does (default preparation), reads the cues of the repeat
//! found, and prints per image: the grid, the pattern the cues read and its weave class, the
//! unary labelling alone (sign of the orientation cue), the mean margin, and with a truth
//! pattern (`0011/0110/…`, rows by weft as `woven params` prints them) whether the reading is
//! the truth up to a shift. With `CUE_TABLES=1`, the per-cell tables (orientation t, weft and
//! warp links); `CUE_ORIGIN=x,y` anchors the cell grid at another crop corner.

use anyhow::{Context, Result};
use woven::fit::cell_cues;
use woven::image_io::Image;
use woven::pattern::WeavePattern;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.is_empty() {
        anyhow::bail!("usage: cell_cues_diag IMAGE [TRUTH] [IMAGE [TRUTH]]...");
    }
    let mut k = 0;
    while k < args.len() {
        let path = std::path::Path::new(&args[k]);
        let truth = args.get(k + 1).and_then(|t| WeavePattern::parse(t).ok());
        k += if truth.is_some() { 2 } else { 1 };
        let img = Image::load(path, woven::prep::MIN_SIZE)?;
        let p = match woven::prep::prepare(&img.to_rgb32f(), &woven::prep::PrepOptions::default()) {
            Ok(p) => p,
            Err(e) => {
                println!("{}: not prepared ({e})", path.display());
                continue;
            }
        };
        let (n_e, n_a) = (p.n_e, p.n_a);
        // `CUE_ORIGIN=x,y` anchors the cell grid elsewhere (e.g. the crop corner a fit's
        // `prep.json` records after its phase alignment).
        let mut p = p;
        if let Ok(o) = std::env::var("CUE_ORIGIN") {
            let v: Vec<u32> = o.split(',').filter_map(|t| t.trim().parse().ok()).collect();
            if let [x, y] = v[..] {
                (p.crop.x, p.crop.y) = (x, y);
            }
        }
        let Some(cues) = cell_cues::read_prepared(&p, n_e, n_a) else {
            println!("{}: {n_e}×{n_a}, no cues", path.display());
            continue;
        };
        let r = cues.read().context("no woven reading")?;
        let unary: Vec<Vec<bool>> =
            (0..n_e).map(|i| (0..n_a).map(|j| cues.orient[i * n_a + j] > 0.0).collect()).collect();
        let unary = WeavePattern::from_rows_unreduced(&unary)
            .map(|u| format!("{u} ({:?})", u.weave_class()))
            .unwrap_or_else(|e| e.to_string());
        let finite: Vec<f64> = r.margin.iter().copied().filter(|m| m.is_finite()).collect();
        let mean_margin = finite.iter().sum::<f64>() / finite.len().max(1) as f64;
        let min_margin = r.margin.iter().copied().fold(f64::INFINITY, f64::min);
        let verdict = truth.as_ref().map_or(String::new(), |t| {
            let t = WeavePattern::from_rows_unreduced(&t.rows()).expect("valid");
            // Exact: the truth up to a shift (the crop's origin is arbitrary).
            let ok = r.pattern.equivalent(&t) || r.pattern.reduced().equivalent(&t.reduced());
            format!(" truth {t}: {}", if ok { "RIGHT" } else { "wrong" })
        });
        // The face: the truth against its inverted twin, each at its best cyclic shift on the
        // cue grid (the truth tiled to the grid), split into the orientation and link terms.
        let face = truth.as_ref().map_or(String::new(), |t| {
            let t = WeavePattern::from_rows_unreduced(&t.rows()).expect("valid");
            if n_e % t.n_e() != 0 || n_a % t.n_a() != 0 {
                return " face: grid mismatch".into();
            }
            let best = |p: &WeavePattern| -> (f64, f64) {
                let mut b = (f64::INFINITY, 0.0);
                for di in 0..n_e {
                    for dj in 0..n_a {
                        let lab: Vec<bool> = (0..n_e * n_a)
                            .map(|k| p.get((k / n_a + di) % p.n_e(), (k % n_a + dj) % p.n_a()))
                            .collect();
                        let e = cues.energy(&lab);
                        let u: f64 = lab
                            .iter()
                            .zip(&cues.orient)
                            .map(|(&v, &o)| if v { -o } else { o })
                            .sum();
                        if e < b.0 {
                            b = (e, u);
                        }
                    }
                }
                b
            };
            let (et, ut) = best(&t);
            let (ei, ui) = best(&t.inverted());
            // The mirror (S against Z twill): every row read right to left.
            let rows: Vec<Vec<bool>> = t.rows().into_iter().map(|r| r.into_iter().rev().collect()).collect();
            let mirror = WeavePattern::from_rows_unreduced(&rows).expect("valid");
            let (em, _) = best(&mirror);
            let own_mirror = mirror.equivalent(&t);
            format!(
                " face: E truth {et:.1} (orient {ut:.1}) twin {ei:.1} (orient {ui:.1}) d {:.1} (orient {:.1} links {:.1}) mirror {} d_per_cell {:.2}",
                ei - et,
                ui - ut,
                (ei - ui) - (et - ut),
                if own_mirror { "self" } else { "other" },
                (em - et) / (n_e * n_a) as f64
            )
        });
        println!(
            "{}: {n_e}×{n_a} pitch {:.1}×{:.1} copies {} -> {} ({:?}) E {:.1} margin mean {:.1} min {:.1}; unary {}{}{}",
            path.display(),
            p.pitch_x,
            p.pitch_y,
            cues.copies,
            r.pattern,
            r.pattern.reduced().weave_class(),
            r.energy,
            mean_margin,
            min_margin,
            unary,
            verdict,
            face
        );
        if std::env::var("CUE_TABLES").is_ok() {
            for (name, v) in [("orient", &cues.orient), ("weft link", &cues.weft_link), ("warp link", &cues.warp_link)]
            {
                println!("  {name} (rows = wefts, top row = weft {}):", n_e - 1);
                for i in (0..n_e).rev() {
                    let row: Vec<String> = (0..n_a).map(|j| format!("{:7.1}", v[i * n_a + j])).collect();
                    println!("   {}", row.join(" "));
                }
            }
        }
    }
    Ok(())
}
