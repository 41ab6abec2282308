use woven::params::*;
use woven::render::*;
use woven::scene::*;
use woven::pattern::WeavePattern;
#[test]
fn probe() {
    for (c, spp) in [(8u32, 4u32), (16, 4), (16, 8)] {
    let pat = WeavePattern::preset("twill22").unwrap();
    let cloth = ClothParams { pattern: pat.clone(), n_p: 3, n_f: 30, r_e: 4.2, r_a: 4.2, appearance: Appearance::default() };
    let scene = Scene { width: 4*c, height: 4*c, spp, seed: 1, camera: CameraSpec { tiles: 1.0, offset: [0.5,0.5], ..Default::default() }, ..Default::default() };
    let t = std::time::Instant::now();
    let prep = Prepared::new(&cloth, &scene, &RenderOptions::default());
    let t1 = t.elapsed().as_secs_f64();
    let cache = prep.record(&cloth.appearance);
    let t2 = t.elapsed().as_secs_f64();
    let img = cache.shade(&cloth.appearance);
    let t3 = t.elapsed().as_secs_f64();
    let _ = cache.mse_and_gradient(&cloth.appearance, &img);
    let t4 = t.elapsed().as_secs_f64();
    println!("c={c} spp={spp} new {t1:.4} record {:.4} shade {:.4} grad {:.4} verts {}", t2-t1, t3-t2, t4-t3, cache.vertex_count());
    }
}
