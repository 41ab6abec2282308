//! The flyaway-fibre layer (`geometry::hair`): off changes nothing, on it covers the gaps,
//! deterministic, seamless across the tile, and bad values are refused.

use glam::Vec3;
use woven::geometry::hair::{Hair, HAIR_SEGMENTS};
use woven::geometry::tile::TileGeometry;
use woven::geometry::yarn::YarnSet;
use woven::params::{ClothParams, ParamFile};
use woven::render::{render, RenderOptions};
use woven::scene::{LightRig, Scene};
use woven::{Image, WeavePattern};

/// The rig's back light alone, without the ambient term.
fn back_only() -> LightRig {
    LightRig { ambient: [0.0; 3], ..LightRig::named("back").unwrap() }
}

/// An open plain weave (radius 2.5 on pitch 10: wide gaps) with `density` hairs per yarn per pitch.
fn open_plain(density: f32) -> ClothParams {
    let mut c = ClothParams::preset("plain").unwrap();
    (c.r_e, c.r_a) = (2.5, 2.5);
    c.hair.density = density;
    c
}

fn mean(img: &Image) -> f32 {
    let m = img.mean();
    (m[0] + m[1] + m[2]) / 3.0
}

#[test]
fn hair_off_renders_bit_for_bit_as_without_the_layer() {
    // Density 0 with other lengths and radii grows nothing: same BVH, same slab, same pixels.
    let cloth = open_plain(0.0);
    let mut odd = cloth.clone();
    odd.hair = Hair { density: 0.0, length: 15.0, radius: 0.4 };
    let scene = Scene { width: 40, height: 40, spp: 2, ..Scene::default() };
    let a = render(&cloth, &scene, &RenderOptions::default());
    let b = render(&odd, &scene, &RenderOptions::default());
    assert_eq!(a.data, b.data);
    let set = || YarnSet::new(&cloth.pattern, 2.5, 2.5);
    let bare = TileGeometry::new(set());
    let off = TileGeometry::with_hair(set(), &odd.hair);
    assert_eq!(bare.capsule_count(), off.capsule_count());
    assert_eq!(bare.z_top(), off.z_top());
    assert!(off.hairs.is_empty());
    // And a file without the layer does not mention it (files written before load as before).
    let file = ParamFile { cloth, scene };
    assert!(!file.to_json().contains("hair"));
    let back = ParamFile::from_json(&file.to_json()).unwrap();
    assert_eq!(back.cloth.hair, Hair::default());
}

#[test]
fn hair_under_a_back_light_darkens_the_gaps_and_covers_them() {
    let p = WeavePattern::preset("plain").unwrap();
    let tile = |density: f32| TileGeometry::with_hair(YarnSet::new(&p, 2.5, 2.5), &Hair { density, ..Hair::default() });
    let (bare_tile, hairy_tile) = (tile(0.0), tile(3.0));
    let (tx, ty) = (bare_tile.set.tile_x, bare_tile.set.tile_y);
    assert_eq!((tx, ty), (20.0, 20.0));
    // Coverage: vertical rays through a 64×64 grid over the tile that meet nothing. The grid's
    // step (20/64 = 0.3125) divides the tubes' edges (5 ± 2.5, 15 ± 2.5: multiples of 2.5 = 8
    // steps) and the rays sit at half steps, so none grazes a silhouette, where the capsule test's
    // rounding decides (a 60×60 grid put 4 of its 60 columns and rows exactly on the edges, and the
    // count moved with the BVH's box rounding: session 15, docs/benchmarks.md).
    let n = 64;
    let miss_fraction = |g: &TileGeometry| {
        let mut miss = 0;
        for i in 0..n {
            for j in 0..n {
                let o = Vec3::new((i as f32 + 0.5) / n as f32 * tx, (j as f32 + 0.5) / n as f32 * ty, 40.0);
                miss += g.closest(o, -Vec3::Z, None).is_none() as usize;
            }
        }
        miss as f32 / (n * n) as f32
    };
    let (bare, hairy) = (miss_fraction(&bare_tile), miss_fraction(&hairy_tile));
    // Seen from above, each family's straight-in-plan tubes shadow 2r of every pitch P, so the open
    // area is (1 − 2r/P)² = (1 − 5/10)² = 1/4: exactly 32 of 64 columns times 32 of 64 rows.
    assert_eq!(bare, 0.25, "the open plain weave's gaps");
    // Hairs grow from the yarns wherever the draws put them, not towards the gaps, so they cover
    // the same share of the gaps as of the tile: with A their projected area over the tile's (2r·
    // length of each segment's xy shadow) and overlaps as in a Boolean model of random shapes,
    // 1 − e^(−A). 24 hairs at density 3 shadow A ≈ 7.5 %; the share is asserted within a factor of
    // 1.5 either way (24 hairs: the share over the gaps of each one varies from 0 to 1).
    let r = Hair::default().radius;
    let area: f32 = hairy_tile
        .hairs
        .iter()
        .map(|f| f.points.windows(2).map(|w| 2.0 * r * (w[1] - w[0]).truncate().length()).sum::<f32>())
        .sum();
    let expect = 1.0 - (-area / (tx * ty)).exp();
    let covered = 1.0 - hairy / bare;
    assert!(expect > 0.05, "the hairs shadow {expect} of the tile");
    assert!(
        covered > expect / 1.5 && covered < expect * 1.5,
        "hairs cover the gaps as their shadow the tile: open {bare} → {hairy}, {covered} covered vs {expect}"
    );
    // Light through the gaps (back light only): the hairs take some of it.
    let scene = Scene { width: 32, height: 32, spp: 4, lights: back_only(), ..Scene::default() };
    let ro = RenderOptions::default();
    let (l0, l3) = (mean(&render(&open_plain(0.0), &scene, &ro)), mean(&render(&open_plain(3.0), &scene, &ro)));
    assert!(l3 < 0.95 * l0, "back light through the cloth: bare {l0}, hairy {l3}");
    assert!(l3 > 0.3 * l0, "hairs are thin: they cannot close the gaps: bare {l0}, hairy {l3}");
}

#[test]
fn hairy_renders_are_deterministic_and_finite_for_any_thread_count() {
    let cloth = open_plain(2.0);
    let scene = Scene { width: 40, height: 40, spp: 2, ..Scene::default() };
    let a = render(&cloth, &scene, &RenderOptions { threads: Some(1), ..Default::default() });
    let b = render(&cloth, &scene, &RenderOptions { threads: Some(2), ..Default::default() });
    assert_eq!(a.data, b.data);
    assert!(a.data.iter().flatten().all(|v| v.is_finite() && *v >= 0.0));
    assert_ne!(a.data, render(&open_plain(0.0), &scene, &RenderOptions::default()).data);
    // Flattened yarns (stretched space) too.
    let mut flat = cloth.clone();
    flat.shape.aspect = 0.5;
    let f = render(&flat, &scene, &RenderOptions::default());
    assert!(f.data.iter().flatten().all(|v| v.is_finite() && *v >= 0.0));
}

#[test]
fn hairs_leaving_the_tile_are_met_across_the_seam() {
    let p = WeavePattern::preset("twill22").unwrap();
    let g = TileGeometry::with_hair(YarnSet::new(&p, 3.0, 3.0), &Hair { density: 3.0, length: 10.0, radius: 0.15 });
    let (tx, ty) = (g.set.tile_x, g.set.tile_y);
    let n_yarns = g.set.yarns.len();
    let (mut outside, mut met) = (0, 0);
    for (h, f) in g.hairs.iter().enumerate() {
        for j in 1..=HAIR_SEGMENTS {
            // Midpoint of segment j, if it lies off the tile: the ray must meet the hair's copy there.
            let m = 0.5 * (f.points[j - 1] + f.points[j]);
            if (0.0..tx).contains(&m.x) && (0.0..ty).contains(&m.y) {
                continue;
            }
            outside += 1;
            let axis = (f.points[j] - f.points[j - 1]).normalize();
            let side = axis.any_orthogonal_vector().normalize();
            // From just outside the fibre, towards its axis.
            let o = m + side * 0.25;
            if let Some(hit) = g.closest(o, -side, None) {
                if hit.hair.map(|x| x.id) == Some(n_yarns + h) && hit.t < 0.2 {
                    met += 1;
                    assert!(hit.p.x >= 0.0 && hit.p.x <= tx && hit.p.y >= 0.0 && hit.p.y <= ty);
                    assert_eq!(hit.yarn, f.yarn);
                }
            }
        }
    }
    assert!(outside > 20, "{outside} segments off the tile");
    // Rare misses: the probe starts inside another yarn or hair.
    assert!(met as f32 >= 0.9 * outside as f32, "{met}/{outside} met across the seam");
    // And a view shifted by whole repeats renders the same picture.
    let mut cloth = ClothParams::preset("twill22").unwrap();
    cloth.hair.density = 3.0;
    let scene = Scene { width: 40, height: 40, spp: 1, ..Scene::default() };
    let mut shifted = scene.clone();
    shifted.camera.offset = [1.0, -2.0];
    let a = render(&cloth, &scene, &RenderOptions::default());
    let b = render(&cloth, &shifted, &RenderOptions::default());
    let close = a.data.iter().zip(&b.data).filter(|(p, q)| (0..3).all(|k| (p[k] - q[k]).abs() < 1e-3)).count();
    assert!(close as f32 >= 0.98 * a.data.len() as f32, "only {close}/{} pixels match", a.data.len());
}

#[test]
fn a_bad_hair_value_is_refused_with_its_name() {
    let mut file = ParamFile { cloth: open_plain(2.0), scene: Scene::default() };
    let good = file.to_json();
    assert!(good.contains("\"hair\""), "a hairy cloth writes its layer");
    assert_eq!(ParamFile::from_json(&good).unwrap().cloth.hair.density, 2.0);
    for (field, value, want) in [
        ("density", -1.0, "hair.density"),
        ("density", 9.0, "hair.density"),
        ("length", 0.0, "hair.length"),
        ("radius", 2.0, "hair.radius"),
    ] {
        let mut c = file.cloth.clone();
        match field {
            "density" => c.hair.density = value,
            "length" => c.hair.length = value,
            _ => c.hair.radius = value,
        }
        file.cloth = c;
        let e = ParamFile::from_json(&file.to_json()).unwrap_err().to_string();
        assert!(e.contains(want) && e.contains("out of range"), "{field} = {value}: {e}");
        file.cloth = open_plain(2.0);
    }
    let unknown = good.replace("\"density\": 2.0", "\"density\": 2.0, \"curl\": 1.0");
    let e = ParamFile::from_json(&unknown).unwrap_err().to_string();
    assert!(e.contains("curl"), "{e}");
    let typed = good.replace("\"density\": 2.0", "\"density\": \"lots\"");
    assert!(ParamFile::from_json(&typed).is_err());
}

#[test]
fn a_hairy_tile_renders_like_the_whole_hairy_fabric() {
    // Hairs are keyed by yarn and cell modulo the minimum repeat: every repeat of a many-repeat
    // tile grows the same hairs, so it renders like the one-repeat tile (up to hits that round
    // differently, as for the bare yarns in tests/render.rs).
    let mut cloth = ClothParams::preset("twill31").unwrap();
    cloth.hair.density = 3.0;
    let mut scene = Scene { width: 48, height: 48, spp: 2, ..Scene::default() };
    scene.camera.tiles = 3.0;
    let tile = render(&cloth, &scene, &RenderOptions::default());
    let whole = render(&cloth, &scene, &RenderOptions { whole_fabric: true, ..Default::default() });
    let close = tile.data.iter().zip(&whole.data).filter(|(p, q)| (0..3).all(|k| (p[k] - q[k]).abs() < 1e-3)).count();
    assert!(close as f32 >= 0.95 * tile.data.len() as f32, "only {close}/{} pixels match", tile.data.len());
}

#[test]
fn hairy_paths_reshade_exactly_and_their_gradient_matches_finite_differences() {
    use woven::params::param;
    use woven::render::Prepared;
    use woven::Appearance;
    let cloth = open_plain(4.0);
    let lights: LightRig = "both".parse().unwrap();
    let scene = Scene { width: 32, height: 32, spp: 2, lights, footprint_filter: false, ..Scene::default() };
    let prep = Prepared::new(&cloth, &scene, &RenderOptions::default());
    let direct = prep.render(&cloth.appearance);
    let cache = prep.record(&cloth.appearance);
    assert!(direct.rmse(&cache.shade(&cloth.appearance)) < 1e-6);
    // The hair vertices drop the specular transmission in the value and in the derivatives alike.
    let mut ta = cloth.appearance.clone();
    ta.r_b_e = [0.3, 0.5, 0.2];
    ta.m_r = 0.45;
    ta.t_s = [0.4; 3];
    let target = cache.shade(&ta);
    let (_, grad) = cache.mse_and_gradient(&cloth.appearance, &target);
    let base = cloth.appearance.to_vec();
    let mse = |v: &[f32]| {
        let img = cache.shade(&Appearance::from_slice(v));
        img.data
            .iter()
            .zip(&target.data)
            .map(|(p, q)| (0..3).map(|k| ((p[k] - q[k]) as f64).powi(2)).sum::<f64>())
            .sum::<f64>()
            / (3 * img.data.len()) as f64
    };
    for i in [param::M_R, param::T_S, param::R_B_E] {
        let h = 1e-3f32;
        let (mut up, mut down) = (base, base);
        up[i] += h;
        down[i] -= h;
        let fd = (mse(&up) - mse(&down)) / (2.0 * h as f64);
        let g = grad[i] as f64;
        assert!(fd.abs() > 1e-6, "parameter {i} must matter: {fd}");
        assert!((g - fd).abs() < 2e-2 * fd.abs(), "parameter {i}: analytic {g:e} vs fd {fd:e}");
    }
}
