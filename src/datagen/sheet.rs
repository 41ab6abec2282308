//! The contact sheet `preview.png`: the first images of the dataset in a grid, each with its
//! index and pattern-class name underneath.

use super::sample::Label;
use anyhow::{anyhow, Context, Result};
use image::RgbImage;
use plotters::prelude::*;
use plotters::style::FontStyle;
use std::path::Path;
use std::sync::Once;

/// Images shown on the sheet.
pub const SHEET_IMAGES: usize = 64;
/// Thumbnails per row.
pub const SHEET_COLUMNS: usize = 8;
const LABEL_H: u32 = 14;
const GAP: u32 = 2;

fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        let bytes: &'static [u8] = include_bytes!("../../assets/DejaVuSans.ttf");
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, bytes);
    });
}

/// Resample to `side × side`: box average over each target pixel's footprint (nearest when enlarging).
fn rescale(img: &RgbImage, side: u32) -> RgbImage {
    let (w, h) = img.dimensions();
    if w == side && h == side {
        return img.clone();
    }
    RgbImage::from_fn(side, side, |x, y| {
        // Box filter over the source footprint of the target pixel.
        let (x0, x1) = (x * w / side, ((x + 1) * w).div_ceil(side).max(x * w / side + 1));
        let (y0, y1) = (y * h / side, ((y + 1) * h).div_ceil(side).max(y * h / side + 1));
        let mut acc = [0u32; 3];
        let mut n = 0;
        for yy in y0..y1.min(h) {
            for xx in x0..x1.min(w) {
                let p = img.get_pixel(xx, yy).0;
                (0..3).for_each(|k| acc[k] += p[k] as u32);
                n += 1;
            }
        }
        image::Rgb(acc.map(|a| ((a + n / 2) / n.max(1)) as u8))
    })
}

/// Thumbnail side for images of side `size`: the size itself clamped to [64, 128].
pub fn thumb_side(size: u32) -> u32 {
    size.clamp(64, 128)
}

/// Build the sheet from the dataset directory and the labels (in index order; the first
/// [`SHEET_IMAGES`] are shown).
pub fn contact_sheet(dir: &Path, labels: &[Label]) -> Result<RgbImage> {
    let shown = &labels[..labels.len().min(SHEET_IMAGES)];
    let cols = SHEET_COLUMNS.min(shown.len().max(1)) as u32;
    let rows = shown.len().div_ceil(SHEET_COLUMNS).max(1) as u32;
    let t = shown.first().map(|l| thumb_side(l.scene.width)).unwrap_or(64);
    let (cw, ch) = (t + GAP, t + LABEL_H + GAP);
    let (w, h) = (cols * cw + GAP, rows * ch + GAP);
    let mut sheet = RgbImage::from_pixel(w, h, image::Rgb([24, 24, 24]));
    for (k, l) in shown.iter().enumerate() {
        let path = dir.join(&l.image);
        let img = image::open(&path).with_context(|| format!("preview: cannot read {}", path.display()))?.to_rgb8();
        let thumb = rescale(&img, t);
        let (ox, oy) = (GAP + (k as u32 % cols) * cw, GAP + (k as u32 / cols) * ch);
        image::imageops::replace(&mut sheet, &thumb, ox as i64, oy as i64);
    }
    register_font();
    let mut buf = sheet.into_raw();
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        let style = TextStyle::from(("sans-serif", 11).into_font()).color(&RGBColor(235, 235, 235));
        let max_chars = (t / 6) as usize;
        for (k, l) in shown.iter().enumerate() {
            let (ox, oy) = (GAP + (k as u32 % cols) * cw, GAP + (k as u32 / cols) * ch);
            let text: String = format!("{} {}", l.index, l.class_name).chars().take(max_chars).collect();
            root.draw_text(&text, &style, (ox as i32 + 1, (oy + t + 1) as i32))
                .map_err(|e| anyhow!("preview: cannot draw text: {e:?}"))?;
        }
        root.present().map_err(|e| anyhow!("preview: {e:?}"))?;
    }
    RgbImage::from_raw(w, h, buf).ok_or_else(|| anyhow!("preview: buffer size"))
}
