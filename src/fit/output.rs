//! Files of a fit: `fit.json`, `prep.json`, `fit.png`, `compare.png`, `trace.png`, `log.jsonl`.

use super::FitResult;
use crate::image_io::Image;
use crate::plot::{register_font, write_rgb_png as write_png};
use crate::render::{render, RenderOptions};
use anyhow::{Context, Result};
use plotters::prelude::*;
use std::path::Path;

/// Nearest-neighbour upscale by an integer factor.
fn upscale(img: &Image, f: u32) -> Image {
    let f = f.max(1);
    let (w, h) = (img.width * f, img.height * f);
    let data = (0..h).flat_map(|y| (0..w).map(move |x| (x, y))).map(|(x, y)| img.get(x / f, y / f)).collect();
    Image::new(w, h, data)
}

/// Absolute sRGB error ×4 as a grey image.
pub fn error_map(a: &Image, b: &Image) -> Image {
    use crate::image_io::{linear_to_srgb, srgb_to_linear};
    let data = a
        .data
        .iter()
        .zip(&b.data)
        .map(|(p, q)| {
            let e = (0..3).map(|k| (linear_to_srgb(p[k]) - linear_to_srgb(q[k])).abs()).fold(0.0f32, f32::max);
            [srgb_to_linear((4.0 * e).min(1.0)); 3]
        })
        .collect();
    Image::new(a.width, a.height, data)
}

/// `compare.png`: target | fit | error (×4), upscaled, with the PSNR written on it.
pub fn write_compare(res: &FitResult, path: &Path) -> Result<()> {
    register_font();
    let f = (256 / res.target.height.max(1)).clamp(1, 16);
    let err = error_map(&res.target, &res.render);
    let (t, r, e) = (upscale(&res.target, f), upscale(&res.render, f), upscale(&err, f));
    let strip = Image::hstack(&[&t, &r, &e], 4);
    let label_h = 28u32;
    let (w, h) = (strip.width.max(360), strip.height + label_h);
    let mut buf = vec![255u8; (w * h * 3) as usize];
    let rgb = strip.to_srgb8();
    for y in 0..strip.height {
        for x in 0..strip.width {
            let p = rgb.get_pixel(x, y).0;
            let i = (((y + label_h) * w + x) * 3) as usize;
            buf[i..i + 3].copy_from_slice(&p);
        }
    }
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        let txt = format!("input | fit | error x4     PSNR {:.2} dB", res.psnr_db);
        root.draw(&Text::new(txt, (6, 6), ("sans-serif", 16).into_font().color(&BLACK)))
            .map_err(|e| anyhow::anyhow!("drawing text: {e}"))?;
        root.present().map_err(|e| anyhow::anyhow!("drawing: {e}"))?;
    }
    write_png(path, w, h, buf)
}

/// `trace.png`: loss (log) with accepted discrete changes marked, and parameter traces.
pub fn write_trace(res: &FitResult, path: &Path) -> Result<()> {
    register_font();
    let (w, h) = (900u32, 700u32);
    let mut buf = vec![255u8; (w * h * 3) as usize];
    let err = |e: &dyn std::fmt::Display| anyhow::anyhow!("plotting the trace: {e}");
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| err(&e))?;
        let (top, bottom) = root.split_vertically(350);
        let hist = &res.history;
        let n = hist.len().max(2) as f64;
        let loss: Vec<(f64, f64)> = hist.iter().map(|l| (l.iter as f64, (l.loss as f64).max(1e-9))).collect();
        let best: Vec<(f64, f64)> = hist.iter().map(|l| (l.iter as f64, (l.best_loss as f64).max(1e-9))).collect();
        let (lo, hi) = loss.iter().chain(&best).fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.1), b.max(p.1)));
        let (lo, hi) = if lo < hi { (lo * 0.8, hi * 1.25) } else { (1e-6, 1.0) };
        let mut chart = ChartBuilder::on(&top)
            .caption(format!("fit loss (MSE + barrier), PSNR {:.2} dB", res.psnr_db), ("sans-serif", 20))
            .margin(12)
            .x_label_area_size(35)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..n, (lo..hi).log_scale())
            .map_err(|e| err(&e))?;
        chart
            .configure_mesh()
            .x_desc("iteration")
            .y_desc("loss")
            .y_label_formatter(&|v| format!("{v:.1e}"))
            .label_style(("sans-serif", 12))
            .draw()
            .map_err(|e| err(&e))?;
        chart
            .draw_series(LineSeries::new(loss.iter().copied(), BLUE.stroke_width(2)))
            .map_err(|e| err(&e))?
            .label("current")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLUE.stroke_width(2)));
        chart
            .draw_series(LineSeries::new(best.iter().copied(), BLACK.stroke_width(1)))
            .map_err(|e| err(&e))?
            .label("best")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK.stroke_width(1)));
        let acc: Vec<(f64, f64)> = hist
            .iter()
            .filter(|l| l.accepted && l.proposal.starts_with("cell"))
            .map(|l| (l.iter as f64, (l.loss as f64).max(1e-9)))
            .collect();
        chart
            .draw_series(PointSeries::of_element(acc, 4, RED.filled(), &|c, s, st| {
                EmptyElement::at(c) + Circle::new((0, 0), s, st)
            }))
            .map_err(|e| err(&e))?
            .label("accepted pattern change")
            .legend(|(x, y)| Circle::new((x + 10, y), 4, RED.filled()));
        chart
            .configure_series_labels()
            .label_font(("sans-serif", 13))
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| err(&e))?;

        let mut chart = ChartBuilder::on(&bottom)
            .caption("parameters (normalised to their range)", ("sans-serif", 18))
            .margin(12)
            .x_label_area_size(35)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..n, 0.0..1.0f64)
            .map_err(|e| err(&e))?;
        chart.configure_mesh().x_desc("iteration").label_style(("sans-serif", 12)).draw().map_err(|e| err(&e))?;
        type Getter = Box<dyn Fn(&super::IterLog) -> f64>;
        let series: Vec<(&str, RGBColor, Getter)> = vec![
            ("r_e", RGBColor(200, 0, 0), Box::new(|l| (l.r_e as f64 - 1.0) / 4.0)),
            ("r_a", RGBColor(0, 120, 0), Box::new(|l| (l.r_a as f64 - 1.0) / 4.0)),
            ("n_p", RGBColor(120, 0, 160), Box::new(|l| (l.n_p as f64 - 1.0) / 6.0)),
            ("n_f", RGBColor(160, 100, 0), Box::new(|l| (l.n_f as f64 - 20.0) / 30.0)),
            ("m_r", RGBColor(0, 0, 200), Box::new(|l| (l.appearance[0] as f64 - 0.2) / 0.6)),
            ("r_b_e[0]", RGBColor(255, 80, 80), Box::new(|l| l.appearance[16] as f64)),
            ("r_b_a[0]", RGBColor(80, 160, 255), Box::new(|l| l.appearance[19] as f64)),
            ("T/T0", RGBColor(120, 120, 120), Box::new(|l| (l.temperature / super::anneal::T0).min(1.0))),
        ];
        for (name, col, get) in series {
            let pts: Vec<(f64, f64)> = hist.iter().map(|l| (l.iter as f64, get(l).clamp(0.0, 1.0))).collect();
            chart
                .draw_series(LineSeries::new(pts, col.stroke_width(2)))
                .map_err(|e| err(&e))?
                .label(name)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], col.stroke_width(2)));
        }
        chart
            .configure_series_labels()
            .label_font(("sans-serif", 12))
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| err(&e))?;
        root.present().map_err(|e| err(&e))?;
    }
    write_png(path, w, h, buf)
}

/// Write every output of a fit into `dir` (created). `input` is the image the fit was given.
pub fn write_outputs(
    res: &FitResult,
    dir: &Path,
    threads: Option<usize>,
    noise: Option<&crate::noise::NoiseModel>,
) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    res.params.save(&dir.join("fit.json")).with_context(|| format!("writing {}", dir.join("fit.json").display()))?;
    if let Some(p) = &res.prep {
        crate::io::write_atomic(&dir.join("prep.json"), p.to_json().as_bytes())?;
    }
    let mut log = String::new();
    for l in &res.history {
        log.push_str(&serde_json::to_string(l)?);
        log.push('\n');
    }
    crate::io::write_atomic(&dir.join("log.jsonl"), log.as_bytes())?;
    let mut full = render(&res.params.cloth, &res.params.scene, &RenderOptions { threads, ..Default::default() });
    if let Some(m) = noise {
        m.add_to(&mut full, res.params.scene.seed);
    }
    full.save_png(&dir.join("fit.png"))?;
    write_compare(res, &dir.join("compare.png"))?;
    write_trace(res, &dir.join("trace.png"))?;
    Ok(())
}
