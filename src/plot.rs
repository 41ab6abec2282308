//! Shared plumbing for the plots (training curves, fit traces): the bundled font and writing a
//! plotters RGB buffer as a PNG.

use anyhow::{Context, Result};
use plotters::style::FontStyle;
use std::path::Path;
use std::sync::Once;

/// Register the bundled DejaVu Sans as plotters' "sans-serif" (once per process).
pub fn register_font() {
    static FONT: Once = Once::new();
    FONT.call_once(|| {
        let bytes: &'static [u8] = include_bytes!("../assets/DejaVuSans.ttf");
        // Cannot fail for the bundled font; if it did, text would simply not be drawn.
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, bytes);
    });
}

/// Encode a `w × h` RGB8 buffer as PNG and write it atomically.
pub fn write_rgb_png(path: &Path, w: u32, h: u32, buf: Vec<u8>) -> Result<()> {
    let img = image::RgbImage::from_raw(w, h, buf).context("plot buffer size")?;
    let mut png = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .with_context(|| format!("encoding {}", path.display()))?;
    crate::io::write_atomic(path, &png).with_context(|| format!("writing {}", path.display()))
}
