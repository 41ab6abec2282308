//! Linear-RGB images: sRGB PNG/JPEG and linear EXR reading and writing, with input validation.

use std::path::Path;

/// Errors reading or writing images.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// File missing or unreadable / undecodable.
    #[error("cannot read image {path}: {msg}")]
    Read {
        /// File.
        path: String,
        /// Why.
        msg: String,
    },
    /// Too small to hold any yarn structure.
    #[error("image {path} is {w}x{h}; at least {min}x{min} pixels are needed")]
    TooSmall {
        /// File.
        path: String,
        /// Width.
        w: u32,
        /// Height.
        h: u32,
        /// Minimum side.
        min: u32,
    },
    /// NaN or infinite pixel values.
    #[error("image {path} has {count} NaN/Inf pixel values (first at x={x}, y={y})")]
    NotFinite {
        /// File.
        path: String,
        /// How many.
        count: usize,
        /// First x.
        x: u32,
        /// First y.
        y: u32,
    },
    /// The header declares more pixels than [`MAX_IMAGE_PIXELS`] (checked before decoding).
    #[error("image {path} declares {w}x{h} pixels, more than the {max} pixels (512 MiB as linear RGB) accepted; downscale it")]
    TooLarge {
        /// File.
        path: String,
        /// Declared width.
        w: u64,
        /// Declared height.
        h: u64,
        /// The limit.
        max: u64,
    },
    /// Writing failed.
    #[error("cannot write image {path}: {msg}")]
    Write {
        /// File.
        path: String,
        /// Why.
        msg: String,
    },
}

/// Most pixels an input image may declare: 512 MiB as linear `f32` RGB (12 bytes a pixel), the
/// same budget as the `image` crate's default decoding limit for PNG and JPEG, so no header can
/// make a load allocate more than that (about 6900×6900 pixels, far above any close-up photo).
pub const MAX_IMAGE_PIXELS: u64 = (512 << 20) / 12;

/// The message of a decoding error; for a format this build does not read (HEIC from a phone,
/// WebP from a web page, TIFF from a microscope camera), what it reads and what to do.
fn decode_message(e: &image::ImageError) -> String {
    match e {
        image::ImageError::Unsupported(_) => {
            format!("{e}; woven reads PNG, JPEG and OpenEXR (.exr): export or convert the photo to one of them")
        }
        _ => e.to_string(),
    }
}

/// Check that JPEG bytes hold every segment up to the end-of-image marker (JPEG, ITU-T T.81 §B.2):
/// marker segments carry their length, entropy-coded data after a start-of-scan runs to the next
/// marker that is not a stuffed `FF 00` or a restart `FF D0`–`FF D7`. A file that ends before `FF D9`
/// was cut short; decoders fill the missing rows with grey instead of failing.
pub fn check_jpeg_complete(b: &[u8]) -> Result<(), String> {
    let truncated =
        || "truncated JPEG: the file ends before its end-of-image marker (a partial download or copy?)".to_string();
    if b.len() < 2 || b[0] != 0xFF || b[1] != 0xD8 {
        return Err("not a JPEG file (no start-of-image marker)".into());
    }
    let mut i = 2;
    loop {
        // Skip anything up to the next marker (decoders tolerate stray bytes), then fill bytes.
        while i < b.len() && b[i] != 0xFF {
            i += 1;
        }
        while i < b.len() && b[i] == 0xFF {
            i += 1;
        }
        if i >= b.len() {
            return Err(truncated());
        }
        let marker = b[i];
        i += 1;
        match marker {
            0xD9 => return Ok(()),
            0x01 | 0xD0..=0xD8 => continue,
            _ => {}
        }
        if i + 2 > b.len() {
            return Err(truncated());
        }
        let len = u16::from_be_bytes([b[i], b[i + 1]]) as usize;
        if len < 2 {
            return Err(format!("corrupt JPEG: segment {marker:#04x} at byte {} has length {len}", i - 2));
        }
        if i + len > b.len() {
            return Err(truncated());
        }
        i += len;
        if marker == 0xDA {
            // Entropy-coded data: stop at the first real marker.
            loop {
                if i + 1 >= b.len() {
                    return Err(truncated());
                }
                if b[i] == 0xFF && !matches!(b[i + 1], 0x00 | 0xD0..=0xD7 | 0xFF) {
                    break;
                }
                i += 1;
            }
        }
    }
}

/// A linear RGB `f32` image, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
    /// Pixels, row-major.
    pub data: Vec<[f32; 3]>,
}

/// sRGB encoding of a linear value (IEC 61966-2-1).
///
/// The loss encodes every rendered pixel at every evaluation, so the power law `c^(1/2.4)` is read
/// from a table over `sqrt(c)` instead of `powf` (a profile of a fit put `powf` at 5.7 % of its CPU):
/// within 6e-7 of the exact curve, a thousandth of an 8-bit step. A NaN stays NaN.
pub fn linear_to_srgb(c: f32) -> f32 {
    if c.is_nan() {
        return c;
    }
    let c = c.clamp(0.0, 1.0);
    if c <= 0.003_130_8 {
        12.92 * c
    } else {
        1.055 * srgb_power(c) - 0.055
    }
}

/// Derivative of [`linear_to_srgb`] (zero outside [0, 1], where the encoding clamps):
/// `d/dc (1.055 c^(1/2.4)) = 1.055 / 2.4 · c^(1/2.4) / c`, from the same table.
pub fn linear_to_srgb_slope(c: f32) -> f32 {
    if !(0.0..=1.0).contains(&c) {
        0.0
    } else if c <= 0.003_130_8 {
        12.92
    } else {
        1.055 / 2.4 * srgb_power(c) / c
    }
}

/// Entries of [`SRGB_POWER`] over `u = sqrt(c)` in [0, 1].
const SRGB_POWER_STEPS: usize = 1024;

/// `c^(1/2.4) = u^(5/6)` tabulated over `u = sqrt(c)`: in `u` the curve is smooth enough that
/// linear interpolation between 1025 entries is within 6e-7 where the power law applies
/// (`c > 0.0031308`, `u > 0.056`; the second derivative is at most 4 there).
static SRGB_POWER: std::sync::LazyLock<Vec<f32>> = std::sync::LazyLock::new(|| {
    (0..=SRGB_POWER_STEPS + 1).map(|i| (i as f64 / SRGB_POWER_STEPS as f64).powf(5.0 / 6.0) as f32).collect()
});

/// `c^(1/2.4)` for `c` in (0, 1], from [`SRGB_POWER`].
fn srgb_power(c: f32) -> f32 {
    let u = c.sqrt() * SRGB_POWER_STEPS as f32;
    let i = (u as usize).min(SRGB_POWER_STEPS);
    let f = u - i as f32;
    let (a, b) = (SRGB_POWER[i], SRGB_POWER[i + 1]);
    a + f * (b - a)
}

/// sRGB decoding.
pub fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.040_45 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

impl Image {
    /// Wrap pixel data.
    pub fn new(width: u32, height: u32, data: Vec<[f32; 3]>) -> Self {
        assert_eq!(data.len(), (width * height) as usize);
        Image { width, height, data }
    }

    /// Constant image.
    pub fn filled(width: u32, height: u32, v: [f32; 3]) -> Self {
        Image::new(width, height, vec![v; (width * height) as usize])
    }

    /// Pixel at (x, y).
    pub fn get(&self, x: u32, y: u32) -> [f32; 3] {
        self.data[(y * self.width + x) as usize]
    }

    /// Bilinear sample at pixel position `(x, y)` (pixel centres at integers), the image repeated
    /// periodically in both directions (a repeat of periodic cloth, a noise field made by an inverse
    /// FFT); a non-finite position reads pixel (0, 0).
    pub fn sample_wrapped(&self, x: f64, y: f64) -> [f32; 3] {
        let (w, h) = (self.width as i64, self.height as i64);
        if !(x.is_finite() && y.is_finite()) {
            return self.get(0, 0);
        }
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = ((x - x0) as f32, (y - y0) as f32);
        let at = |i: i64, j: i64| self.get(i.rem_euclid(w) as u32, j.rem_euclid(h) as u32);
        let (i, j) = (x0 as i64, y0 as i64);
        let (p00, p10, p01, p11) = (at(i, j), at(i + 1, j), at(i, j + 1), at(i + 1, j + 1));
        [0, 1, 2].map(|k| (1.0 - fy) * ((1.0 - fx) * p00[k] + fx * p10[k]) + fy * ((1.0 - fx) * p01[k] + fx * p11[k]))
    }

    /// 8-bit sRGB encoding.
    pub fn to_srgb8(&self) -> image::RgbImage {
        image::RgbImage::from_fn(self.width, self.height, |x, y| {
            let p = self.get(x, y);
            image::Rgb(p.map(|c| (linear_to_srgb(c) * 255.0 + 0.5) as u8))
        })
    }

    /// From an 8-bit sRGB image.
    pub fn from_srgb8(img: &image::RgbImage) -> Self {
        let lut: Vec<f32> = (0..256).map(|i| srgb_to_linear(i as f32 / 255.0)).collect();
        let data = img.pixels().map(|p| p.0.map(|c| lut[c as usize])).collect();
        Image::new(img.width(), img.height(), data)
    }

    /// As an `image` crate linear f32 buffer.
    pub fn to_rgb32f(&self) -> image::Rgb32FImage {
        image::Rgb32FImage::from_fn(self.width, self.height, |x, y| image::Rgb(self.get(x, y)))
    }

    /// From an `image` crate linear f32 buffer.
    pub fn from_rgb32f(img: &image::Rgb32FImage) -> Self {
        Image::new(img.width(), img.height(), img.pixels().map(|p| p.0).collect())
    }

    /// The image as sRGB PNG bytes (what [`Image::save_png`] writes).
    pub fn encode_png(&self) -> Result<Vec<u8>, ImageError> {
        let mut bytes = Vec::new();
        self.to_srgb8()
            .write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)
            .map_err(|e| ImageError::Write { path: "(PNG encoder)".into(), msg: e.to_string() })?;
        Ok(bytes)
    }

    /// The image as linear EXR bytes (what [`Image::save_exr`] writes). Blocks are compressed
    /// one after the other: the parallel writer stores them in the order its threads finish, so
    /// the same image could give different files.
    pub fn encode_exr(&self) -> Result<Vec<u8>, ImageError> {
        use exr::prelude::{Image as ExrImage, SpecificChannels, Vec2, WritableImage};
        let w = self.width as usize;
        let channels = SpecificChannels::rgb(|Vec2(x, y): Vec2<usize>| {
            let p = self.data[y * w + x];
            (p[0], p[1], p[2])
        });
        let mut bytes = Vec::new();
        ExrImage::from_channels((w, self.height as usize), channels)
            .write()
            .non_parallel()
            .to_buffered(std::io::Cursor::new(&mut bytes))
            .map_err(|e| ImageError::Write { path: "(EXR encoder)".into(), msg: e.to_string() })?;
        Ok(bytes)
    }

    /// Write an sRGB PNG atomically.
    pub fn save_png(&self, path: &Path) -> Result<(), ImageError> {
        let bytes = self.encode_png()?;
        crate::io::write_atomic(path, &bytes)
            .map_err(|e| ImageError::Write { path: path.display().to_string(), msg: e.to_string() })
    }

    /// Write a linear EXR atomically (deterministic bytes, see [`Image::encode_exr`]).
    pub fn save_exr(&self, path: &Path) -> Result<(), ImageError> {
        let bytes = self.encode_exr()?;
        crate::io::write_atomic(path, &bytes)
            .map_err(|e| ImageError::Write { path: path.display().to_string(), msg: e.to_string() })
    }

    /// Read PNG/JPEG (sRGB-decoded; 8/16-bit, grey or RGB(A)) or EXR (linear); rejects tiny
    /// images and NaN/Inf values.
    ///
    /// Checked before decoding: the path is a regular file (a FIFO would block forever), the size
    /// the header declares fits [`MAX_IMAGE_PIXELS`] (a few bytes of EXR can declare 10¹⁰ pixels),
    /// and a JPEG holds every segment up to its end-of-image marker (the decoder fills a truncated
    /// file with grey without a word, which prep would then read as yarns).
    pub fn load(path: &Path, min_side: u32) -> Result<Self, ImageError> {
        let p = path.display().to_string();
        let read_err = |msg: String| ImageError::Read { path: p.clone(), msg };
        match crate::io::check_regular_file(path) {
            Ok(_) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Err(read_err("file not found".into())),
            Err(e) => return Err(read_err(e.to_string())),
        }
        let check_size = |w: u64, h: u64| -> Result<(), ImageError> {
            if w.saturating_mul(h) > MAX_IMAGE_PIXELS {
                return Err(ImageError::TooLarge { path: p.clone(), w, h, max: MAX_IMAGE_PIXELS });
            }
            Ok(())
        };
        let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_lowercase();
        let img = if ext == "exr" {
            let meta = exr::meta::MetaData::read_from_file(path, false).map_err(|e| read_err(e.to_string()))?;
            for h in meta.headers.iter() {
                check_size(h.layer_size.width() as u64, h.layer_size.height() as u64)?;
            }
            let r = exr::prelude::read_first_rgba_layer_from_file(
                path,
                |res, _| (res.width(), vec![[0f32; 3]; res.width() * res.height()]),
                |(w, buf): &mut (usize, Vec<[f32; 3]>), pos, (r, g, b, _a): (f32, f32, f32, f32)| {
                    buf[pos.y() * *w + pos.x()] = [r, g, b]
                },
            )
            .map_err(|e| read_err(e.to_string()))?;
            let size = r.layer_data.size;
            let (_, data) = r.layer_data.channel_data.pixels;
            Image::new(size.width() as u32, size.height() as u32, data)
        } else {
            let reader = || -> Result<_, ImageError> {
                image::ImageReader::open(path)
                    .map_err(|e| read_err(e.to_string()))?
                    .with_guessed_format()
                    .map_err(|e| read_err(e.to_string()))
            };
            let (w, h) = reader()?.into_dimensions().map_err(|e| read_err(decode_message(&e)))?;
            check_size(w as u64, h as u64)?;
            let r = reader()?;
            if r.format() == Some(image::ImageFormat::Jpeg) {
                let bytes = std::fs::read(path).map_err(|e| read_err(e.to_string()))?;
                check_jpeg_complete(&bytes).map_err(read_err)?;
            }
            // A phone stores a portrait photo as landscape pixels plus an EXIF orientation that
            // every viewer applies; applied here too, so that preparation, the weave's warp and
            // weft and the registered fit.png follow the photo as the user sees it.
            use image::ImageDecoder;
            let mut decoder = r.into_decoder().map_err(|e| read_err(e.to_string()))?;
            let orientation = decoder.orientation().unwrap_or(image::metadata::Orientation::NoTransforms);
            let mut dynimg = image::DynamicImage::from_decoder(decoder).map_err(|e| read_err(e.to_string()))?;
            dynimg.apply_orientation(orientation);
            use image::DynamicImage as D;
            match &dynimg {
                D::ImageRgb32F(_) | D::ImageRgba32F(_) => Image::from_rgb32f(&dynimg.to_rgb32f()),
                D::ImageLuma16(_) | D::ImageLumaA16(_) | D::ImageRgb16(_) | D::ImageRgba16(_) => {
                    let img = dynimg.to_rgb16();
                    let data = img.pixels().map(|p| p.0.map(|c| srgb_to_linear(c as f32 / 65535.0))).collect();
                    Image::new(img.width(), img.height(), data)
                }
                _ => Image::from_srgb8(&dynimg.to_rgb8()),
            }
        };
        if img.width < min_side || img.height < min_side {
            return Err(ImageError::TooSmall { path: p, w: img.width, h: img.height, min: min_side });
        }
        img.check_finite(&p)?;
        Ok(img)
    }

    /// Error if any value is NaN/Inf.
    pub fn check_finite(&self, name: &str) -> Result<(), ImageError> {
        let bad: Vec<usize> =
            self.data.iter().enumerate().filter(|(_, p)| p.iter().any(|c| !c.is_finite())).map(|(i, _)| i).collect();
        if let Some(&i) = bad.first() {
            return Err(ImageError::NotFinite {
                path: name.to_string(),
                count: bad.len(),
                x: i as u32 % self.width,
                y: i as u32 / self.width,
            });
        }
        Ok(())
    }

    /// Root-mean-square difference.
    pub fn rmse(&self, other: &Image) -> f32 {
        assert_eq!((self.width, self.height), (other.width, other.height));
        let s: f64 = self
            .data
            .iter()
            .zip(&other.data)
            .map(|(a, b)| (0..3).map(|k| ((a[k] - b[k]) as f64).powi(2)).sum::<f64>())
            .sum();
        (s / (self.data.len() * 3) as f64).sqrt() as f32
    }

    /// PSNR in dB of sRGB-encoded values (peak 1).
    pub fn psnr_srgb(&self, other: &Image) -> f32 {
        let s: f64 = self
            .data
            .iter()
            .zip(&other.data)
            .map(|(a, b)| (0..3).map(|k| ((linear_to_srgb(a[k]) - linear_to_srgb(b[k])) as f64).powi(2)).sum::<f64>())
            .sum();
        let mse = s / (self.data.len() * 3) as f64;
        (10.0 * (1.0 / mse.max(1e-12)).log10()) as f32
    }

    /// Mean value per channel.
    pub fn mean(&self) -> [f32; 3] {
        let n = self.data.len() as f32;
        let mut m = [0.0; 3];
        for p in &self.data {
            (0..3).for_each(|k| m[k] += p[k]);
        }
        m.map(|v| v / n)
    }

    /// Place images side by side (same height), separated by `gap` black pixels.
    pub fn hstack(images: &[&Image], gap: u32) -> Image {
        let h = images.iter().map(|i| i.height).max().unwrap_or(1);
        let w: u32 = images.iter().map(|i| i.width).sum::<u32>() + gap * (images.len() as u32).saturating_sub(1);
        let mut out = Image::filled(w, h, [0.0; 3]);
        let mut x0 = 0;
        for img in images {
            for y in 0..img.height {
                for x in 0..img.width {
                    out.data[(y * w + x0 + x) as usize] = img.get(x, y);
                }
            }
            x0 += img.width + gap;
        }
        out
    }
    /// Stack images vertically (width of the widest), separated by `gap` black rows.
    pub fn vstack(images: &[&Image], gap: u32) -> Image {
        let w = images.iter().map(|i| i.width).max().unwrap_or(1);
        let h: u32 = images.iter().map(|i| i.height).sum::<u32>() + gap * (images.len() as u32).saturating_sub(1);
        let mut data = Vec::with_capacity((w * h) as usize);
        for (k, img) in images.iter().enumerate() {
            for y in 0..img.height {
                for x in 0..w {
                    data.push(if x < img.width { img.get(x, y) } else { [0.0; 3] });
                }
            }
            if k + 1 < images.len() {
                data.extend(std::iter::repeat_n([0.0; 3], (gap * w) as usize));
            }
        }
        Image::new(w, h, data)
    }

    /// Cut a `w`×`h` window at `(x, y)` out of the image (clamped to its bounds, at least 1×1).
    pub fn crop(&self, x: u32, y: u32, w: u32, h: u32) -> Image {
        let w = w.min(self.width.saturating_sub(x)).max(1);
        let h = h.min(self.height.saturating_sub(y)).max(1);
        let data = (0..h)
            .flat_map(|j| (0..w).map(move |i| (i, j)))
            .map(|(i, j)| self.get((x + i).min(self.width - 1), (y + j).min(self.height - 1)))
            .collect();
        Image::new(w, h, data)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The tabulated encoding against IEC 61966-2-1's power law on a dense sweep of [0, 1] (and
    /// past it, where it clamps), its slope against central differences of the exact curve, and
    /// NaN in, NaN out.
    #[test]
    fn the_tabulated_srgb_curve_matches_the_power_law() {
        let exact = |c: f64| {
            let c = c.clamp(0.0, 1.0);
            if c <= 0.003_130_8 {
                12.92 * c
            } else {
                1.055 * c.powf(1.0 / 2.4) - 0.055
            }
        };
        let mut worst = 0.0f64;
        for i in 0..=200_000 {
            let c = i as f64 / 190_000.0 - 0.01;
            worst = worst.max((linear_to_srgb(c as f32) as f64 - exact(c)).abs());
        }
        assert!(worst < 1e-6, "worst encoding error {worst:e}");
        for &c in &[0.004f64, 0.01, 0.05, 0.2, 0.5, 0.9, 0.999] {
            let h = 1e-6 * c;
            let fd = (exact(c + h) - exact(c - h)) / (2.0 * h);
            let s = linear_to_srgb_slope(c as f32) as f64;
            assert!((s - fd).abs() < 1e-4 * fd, "slope at {c}: {s} vs {fd}");
        }
        assert_eq!(linear_to_srgb_slope(1.5), 0.0);
        assert!(linear_to_srgb(f32::NAN).is_nan());
    }

    fn jpeg_bytes() -> Vec<u8> {
        let img =
            image::RgbImage::from_fn(64, 48, |x, y| image::Rgb([(x * 4) as u8, (y * 5) as u8, ((x ^ y) * 3) as u8]));
        let mut bytes = Vec::new();
        img.write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Jpeg).unwrap();
        bytes
    }

    /// A JPEG of a 64 × 48 picture stored with EXIF orientation 6 ("rotate 90° clockwise to
    /// view", what a phone writes for a portrait photo) loads as the 48 × 64 picture a viewer shows.
    #[test]
    fn the_exif_orientation_of_a_jpeg_is_applied() {
        use image::ImageEncoder;
        // Left half black, right half white: after the turn, top half black, bottom half white.
        let img =
            image::RgbImage::from_fn(64, 48, |x, _| if x < 32 { image::Rgb([0; 3]) } else { image::Rgb([255; 3]) });
        // A TIFF-structured EXIF block: little-endian header, one IFD of one entry,
        // tag 0x0112 (orientation), type SHORT, count 1, value 6.
        let mut exif = b"II*\0\x08\0\0\0\x01\0".to_vec();
        exif.extend_from_slice(&[0x12, 0x01, 3, 0, 1, 0, 0, 0, 6, 0, 0, 0, 0, 0, 0, 0]);
        let mut bytes = Vec::new();
        let mut enc = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, 95);
        enc.set_exif_metadata(exif).unwrap();
        enc.write_image(img.as_raw(), 64, 48, image::ExtendedColorType::Rgb8).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("portrait.jpg");
        std::fs::write(&path, &bytes).unwrap();
        let loaded = Image::load(&path, 8).unwrap();
        assert_eq!((loaded.width, loaded.height), (48, 64));
        assert!(
            loaded.get(24, 8)[0] < 0.05 && loaded.get(24, 56)[0] > 0.9,
            "{:?} {:?}",
            loaded.get(24, 8),
            loaded.get(24, 56)
        );
    }

    /// Formats this build does not decode (a phone's HEIC, a web page's WebP) are refused with
    /// what it reads.
    #[test]
    fn an_unsupported_format_is_refused_with_the_formats_read() {
        let dir = tempfile::tempdir().unwrap();
        let heic = dir.path().join("photo.heic");
        std::fs::write(&heic, b"\0\0\0\x18ftypheic\0\0\0\0mif1heic").unwrap();
        let webp = dir.path().join("photo.webp");
        std::fs::write(&webp, b"RIFF\x24\0\0\0WEBPVP8 \x18\0\0\0").unwrap();
        for f in [heic, webp] {
            let e = Image::load(&f, 8).unwrap_err().to_string();
            assert!(e.contains("woven reads PNG, JPEG and OpenEXR"), "{e}");
        }
    }

    #[test]
    fn jpeg_completeness() {
        let b = jpeg_bytes();
        assert_eq!(check_jpeg_complete(&b), Ok(()));
        // Trailing bytes after the end-of-image marker are harmless.
        let mut t = b.clone();
        t.extend_from_slice(b"trailer");
        assert_eq!(check_jpeg_complete(&t), Ok(()));
        // Every cut, in the headers or in the scan data, is caught.
        for cut in [3, 20, b.len() / 2, b.len() - 2] {
            let e = check_jpeg_complete(&b[..cut]).unwrap_err();
            assert!(e.contains("truncated"), "cut {cut}: {e}");
        }
        assert!(check_jpeg_complete(b"\x89PNG").is_err());
    }

    #[test]
    fn encoders_match_the_savers_and_are_deterministic() {
        let img = Image::new(90, 170, (0..90 * 170).map(|i| [i as f32 / 9e3, 0.5, (i % 7) as f32]).collect());
        let dir = tempfile::tempdir().unwrap();
        let (png, exr) = (dir.path().join("a.png"), dir.path().join("a.exr"));
        img.save_png(&png).unwrap();
        img.save_exr(&exr).unwrap();
        assert_eq!(std::fs::read(&png).unwrap(), img.encode_png().unwrap());
        assert_eq!(std::fs::read(&exr).unwrap(), img.encode_exr().unwrap());
        for _ in 0..3 {
            assert_eq!(img.encode_exr().unwrap(), img.encode_exr().unwrap());
        }
        assert_eq!(Image::load(&exr, 8).unwrap(), img);
    }

    #[test]
    fn truncated_jpeg_and_oversized_exr_are_refused_before_decoding() {
        let dir = tempfile::tempdir().unwrap();
        let b = jpeg_bytes();
        let cut = dir.path().join("cut.jpg");
        std::fs::write(&cut, &b[..b.len() * 2 / 3]).unwrap();
        let e = Image::load(&cut, 8).unwrap_err().to_string();
        assert!(e.contains("truncated JPEG"), "{e}");
        let whole = dir.path().join("whole.jpg");
        std::fs::write(&whole, &b).unwrap();
        assert_eq!(Image::load(&whole, 8).unwrap().width, 64);
        let folder = Image::load(dir.path(), 8).unwrap_err().to_string();
        assert!(folder.contains("a folder"), "{folder}");
    }
}
