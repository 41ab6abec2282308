//! Area-weighted (box) resampling, the one copy the fit's target crop and the network's input
//! share: every output pixel is the mean of the source area it covers, each source pixel
//! weighted by the fraction of it that falls inside (exact for integer factors; upsampling
//! repeats pixels). Filtering in linear RGB keeps the mean colour of the image.

use crate::image_io::Image;

/// Box-filter weights of `n_src` source samples onto `n_dst` output samples: for each output
/// sample, the `(source index, weight)` pairs of the source samples it covers, weights summing to
/// 1. Output `i` covers `[i·s, (i + 1)·s)` with `s = n_src / n_dst`, in source units.
pub fn box_weights(n_src: u32, n_dst: u32) -> Vec<Vec<(u32, f32)>> {
    let s = n_src as f64 / n_dst as f64;
    (0..n_dst)
        .map(|i| {
            let (a, b) = (i as f64 * s, (i + 1) as f64 * s);
            let mut v = Vec::new();
            let mut j = a.floor() as u32;
            while (j as f64) < b && j < n_src {
                let wgt = (b.min(j as f64 + 1.0) - a.max(j as f64)) / s;
                if wgt > 0.0 {
                    v.push((j, wgt as f32));
                }
                j += 1;
            }
            v
        })
        .collect()
}

/// Box resampling of a `src_w × src_h` source, read through `pixel(x, y)`, to `w × h` linear-RGB
/// pixels (row-major). The source need not be stored as an [`Image`]: a crop or another image
/// type is read in place.
pub fn box_resample(src_w: u32, src_h: u32, pixel: impl Fn(u32, u32) -> [f32; 3], w: u32, h: u32) -> Vec<[f32; 3]> {
    let (wx, wy) = (box_weights(src_w, w), box_weights(src_h, h));
    let mut data = Vec::with_capacity(w as usize * h as usize);
    for ys in &wy {
        for xs in &wx {
            let mut acc = [0.0f32; 3];
            for &(y, a) in ys {
                for &(x, b) in xs {
                    let p = pixel(x, y);
                    (0..3).for_each(|k| acc[k] += a * b * p[k]);
                }
            }
            data.push(acc);
        }
    }
    data
}

/// `img` box-resampled to `w × h` ([`box_resample`]); a copy when the size does not change.
pub fn resample(img: &Image, w: u32, h: u32) -> Image {
    if img.width == w && img.height == h {
        return img.clone();
    }
    Image::new(w, h, box_resample(img.width, img.height, |x, y| img.get(x, y), w, h))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weights_sum_to_one_and_cover_the_right_samples() {
        for (s, d) in [(64, 64), (100, 64), (37, 8), (8, 32), (129, 64), (3, 2)] {
            for w in box_weights(s, d) {
                let sum: f32 = w.iter().map(|x| x.1).sum();
                assert!((sum - 1.0).abs() < 1e-5, "{s}->{d}: {sum}");
            }
        }
        // 3 → 2: output 0 covers [0, 1.5) = all of sample 0 and half of sample 1.
        let w = box_weights(3, 2);
        assert_eq!(w[0], vec![(0, 2.0 / 3.0), (1, 1.0 / 3.0)]);
        assert_eq!(w[1], vec![(1, 1.0 / 3.0), (2, 2.0 / 3.0)]);
        // 2 → 4: each source sample is repeated.
        assert_eq!(box_weights(2, 4), vec![vec![(0, 1.0)], vec![(0, 1.0)], vec![(1, 1.0)], vec![(1, 1.0)]]);
        assert!(box_weights(5, 0).is_empty());
    }

    #[test]
    fn resampling_keeps_constants_and_averages_blocks() {
        let flat = Image::filled(37, 23, [0.25, 0.5, 0.75]);
        for (w, h) in [(8, 5), (50, 40), (37, 23), (1, 1)] {
            let r = resample(&flat, w, h);
            assert_eq!((r.width, r.height), (w, h));
            for p in &r.data {
                // The f32 weights sum to 1 within a few ulps.
                (0..3).for_each(|k| assert!((p[k] - flat.data[0][k]).abs() < 1e-5, "{p:?}"));
            }
        }
        // 4×2 → 2×1: each output is the mean of a 2×2 block.
        let img = Image::new(4, 2, (0..8).map(|i| [i as f32, 0.0, 1.0]).collect());
        let r = resample(&img, 2, 1);
        assert_eq!(r.data, vec![[(0.0 + 1.0 + 4.0 + 5.0) / 4.0, 0.0, 1.0], [(2.0 + 3.0 + 6.0 + 7.0) / 4.0, 0.0, 1.0]]);
        // A crop read in place equals resampling the cropped image.
        let big = Image::new(6, 6, (0..36).map(|i| [i as f32 * 0.1, 1.0, (i % 5) as f32]).collect());
        let crop = big.crop(1, 2, 4, 4);
        assert_eq!(box_resample(4, 4, |x, y| big.get(x + 1, y + 2), 3, 3), resample(&crop, 3, 3).data);
    }
}
