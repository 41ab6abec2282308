//! Flyaway fibres ("hairiness"): an optional layer of short fibres rooted on the yarn surfaces
//! and leaving them (docs/forward-model.md, "Flyaway fibres").
//!
//! The model is the hair type of the procedural yarn of Zhao et al. 2016 (*Fitting procedural
//! yarn models for realistic cloth rendering*), as used by the fiber-level cloth of Li et al.
//! 2024 (seed 002): a flyaway fibre whose distance from the yarn centre grows along its length,
//! from the yarn surface at its root to `R + rise` at its tip, while it travels along the yarn and
//! turns around it. In the yarn's frame at length coordinate `s`, with `u ∈ [0, 1]` along the fibre,
//!
//! `p(u) = c(s₀ + u·Δs) + (R + u·rise)·(cos(θ₀ + u·Δθ)·e_x + sin(θ₀ + u·Δθ)·e_y)`,
//!
//! which is Zhao et al.'s hair fibre (radius from `r_min` to `r_max`, angle and axial position
//! each spanning an interval) with its root on the yarn surface. Hairs are counted per yarn per
//! pitch of length ([`Hair::density`], Zhao et al.'s density per unit length), each drawn from a
//! hash of its yarn, its cell along the yarn and its number in that cell, so the same cloth always
//! grows the same hairs (and a fit's scan compares densities on the same random hairs).
//!
//! Each hair is a chain of [`HAIR_SEGMENTS`] thin capsules. They are built in the stretched space
//! of flattened yarns ([`crate::geometry::yarn::YarnShape`]) like the yarns, so a hair stays rooted
//! on the flattened surface; its round section of radius [`Hair::radius`] becomes an ellipse of
//! half-height `aspect·radius` in the world, which at a tenth of a yarn radius is below a pixel.

use super::yarn::{Family, YarnSet, PITCH};
use glam::Vec3;

/// Capsules per hair (a gently curved fibre: the radius, the angle and the axial position are
/// linear in `u`, so four chords follow it to within a few hundredths of a unit).
pub const HAIR_SEGMENTS: usize = 4;

/// The flyaway-fibre layer of a cloth (docs/params.md). Off (density 0) by default: the cloth is
/// then exactly the yarn tubes, and parameter files without it load as before.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Hair {
    /// Hairs per yarn per pitch of yarn length (the fitted value), [0, 8]; 0 = no hairs.
    pub density: f32,
    /// Mean hair length in cloth units (pitch = 10), [1, 20]; each hair's length is drawn
    /// uniformly in `[0.5, 1.5]×` it.
    pub length: f32,
    /// Hair (fibre) radius in cloth units, [0.02, 0.5].
    pub radius: f32,
}

impl Default for Hair {
    fn default() -> Self {
        Hair { density: 0.0, length: 6.0, radius: 0.12 }
    }
}

impl Hair {
    /// Range of [`Hair::density`].
    pub const DENSITY_RANGE: (f32, f32) = (0.0, 8.0);
    /// Range of [`Hair::length`].
    pub const LENGTH_RANGE: (f32, f32) = (1.0, 20.0);
    /// Range of [`Hair::radius`].
    pub const RADIUS_RANGE: (f32, f32) = (0.02, 0.5);

    /// True for the default layer (no hairs, default length and radius): parameter files leave it out.
    pub fn is_default(&self) -> bool {
        *self == Hair::default()
    }

    /// True when the layer grows hairs.
    pub fn is_on(&self) -> bool {
        self.density > 0.0
    }
}

/// One generated hair: its chain of points (stretched space, unwrapped: it may leave the tile)
/// and the yarn it grows from.
#[derive(Clone, Debug, PartialEq)]
pub struct HairFibre {
    /// Index of the root yarn in [`YarnSet::yarns`].
    pub yarn: usize,
    /// `HAIR_SEGMENTS + 1` points from the root to the tip.
    pub points: [Vec3; HAIR_SEGMENTS + 1],
}

/// SplitMix64 finaliser: a well-mixed 64-bit hash of `x` (Steele et al. 2014), so hair draws do not
/// depend on the `rand` crate's generators.
fn mix(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    x ^ (x >> 31)
}

/// A stream of uniform numbers in [0, 1) keyed by `(yarn, cell, k)`.
struct Draws(u64);

impl Draws {
    fn new(keys: [u64; 3]) -> Self {
        Draws(keys.iter().fold(0x4841_4952_u64, |h, &k| mix(h ^ k)))
    }
    fn next(&mut self) -> f32 {
        self.0 = mix(self.0);
        (self.0 >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// Generate the hairs of `set` (none when `hair` is off). Yarn `k` grows, in each pitch-long cell
/// along its period, `⌊density + ξ⌋` hairs (`ξ` uniform: `density` per cell on average), each with
///
/// - root `s₀` uniform in the cell and `θ₀` uniform around the yarn (hairs leave on every side:
///   up towards the camera, down towards a back light, and sideways over the gaps);
/// - length `L = length·U(0.5, 1.5)` and an elevation `φ ∈ U(15°, 60°)` off the surface: the tip
///   is `rise = L·sin φ` further from the yarn centre and `Δs = ±L·cos φ` along it (Zhao et al.
///   2016 draw the hair's radial span and axial span from fitted distributions; these fixed ones
///   stand in for them, with the length as the free scale);
/// - a turn `Δθ ∈ U(−0.6, 0.6)` rad around the yarn.
pub fn generate(set: &YarnSet, hair: &Hair) -> Vec<HairFibre> {
    if !hair.is_on() {
        return Vec::new();
    }
    // The minimum repeat in cells along each family (a weft's repeat spans the repeat's columns,
    // a warp's its rows): hairs are keyed by yarn and cell modulo it, so a tile of several repeats
    // (an unreduced pattern, or `RenderOptions::whole_fabric`) grows the same hairs in each repeat
    // and renders like the one-repeat tile.
    let repeat_cells = |fam: Family| {
        let y = set.yarns.iter().find(|y| y.family == fam);
        y.map_or(1, |y| ((y.repeat / PITCH).round() as u64).max(1))
    };
    let (cols, rows) = (repeat_cells(Family::Weft), repeat_cells(Family::Warp));
    let mut out = Vec::new();
    for (yi, y) in set.yarns.iter().enumerate() {
        let cells = (y.period() / PITCH).round().max(1.0) as u64;
        let (fam, index, along) = match y.family {
            Family::Weft => (0u64, y.index as u64 % rows, cols),
            Family::Warp => (1u64 << 32, y.index as u64 % cols, rows),
        };
        for cell in 0..cells {
            let key = [fam | index, cell % along];
            let mut count_draw = Draws::new([key[0], key[1], u64::MAX]);
            let n = (hair.density + count_draw.next()).floor() as u64;
            for k in 0..n {
                let mut d = Draws::new([key[0], key[1], k]);
                let s0 = (cell as f32 + d.next()) * PITCH;
                let theta0 = std::f32::consts::TAU * d.next();
                let len = hair.length * (0.5 + d.next());
                let phi = (15.0 + 45.0 * d.next()).to_radians();
                let ds = len * phi.cos() * if d.next() < 0.5 { -1.0 } else { 1.0 };
                let rise = len * phi.sin();
                let dtheta = 1.2 * (d.next() - 0.5);
                // Root a little inside the surface, so the chain has no gap where it leaves the yarn.
                let r0 = y.radius - 0.5 * hair.radius;
                let points = std::array::from_fn(|j| {
                    let u = j as f32 / HAIR_SEGMENTS as f32;
                    let f = y.frame(s0 + u * ds);
                    let th = theta0 + u * dtheta;
                    f.c + (f.ex * th.cos() + f.ey * th.sin()) * (r0 + u * rise)
                });
                out.push(HairFibre { yarn: yi, points });
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pattern::WeavePattern;

    fn set() -> YarnSet {
        YarnSet::new(&WeavePattern::preset("twill22").unwrap(), 3.5, 3.0)
    }

    #[test]
    fn off_grows_nothing_and_density_sets_the_count() {
        let s = set();
        assert!(generate(&s, &Hair::default()).is_empty());
        // 8 yarns × 4 cells each = 32 cells; density 2.5 → 80 hairs expected (±√80·… by cell).
        let h = generate(&s, &Hair { density: 2.5, ..Hair::default() });
        assert!((64..=96).contains(&h.len()), "{}", h.len());
        let whole = generate(&s, &Hair { density: 3.0, ..Hair::default() });
        assert_eq!(whole.len(), 96, "an integer density is exact per cell");
    }

    #[test]
    fn hairs_are_deterministic_rooted_on_the_surface_and_rise_off_it() {
        let s = set();
        let hair = Hair { density: 2.0, length: 8.0, radius: 0.1 };
        let a = generate(&s, &hair);
        assert_eq!(a, generate(&s, &hair));
        for f in &a {
            let y = &s.yarns[f.yarn];
            let (d0, _) = y.distance(f.points[0]);
            assert!((d0 - (y.radius - 0.05)).abs() < 0.05, "root at {d0}, radius {}", y.radius);
            // The distance from the centre grows along the hair (Zhao et al.'s hair type).
            let dists: Vec<f32> = f.points.iter().map(|p| y.distance(*p).0).collect();
            assert!(dists.windows(2).all(|w| w[1] > w[0] - 0.05), "{dists:?}");
            let rise = dists[HAIR_SEGMENTS] - dists[0];
            assert!(rise > 8.0 * 0.5 * 15f32.to_radians().sin() - 0.1 && rise < 8.0 * 1.5 + 0.1, "rise {rise}");
        }
    }
}
