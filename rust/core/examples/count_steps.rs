use earcore_core::octree::{compute_ray_keys, KeyConverter};
use earcore_core::synthetic::{benchmark_scene, render_points};
fn main() {
    let (camera, pose, shapes) = benchmark_scene();
    let points = render_points(&camera, &pose, &shapes);
    let o = [
        pose[(0, 3)] as f32,
        pose[(1, 3)] as f32,
        pose[(2, 3)] as f32,
    ];
    for res in [0.05, 0.02] {
        let conv = KeyConverter::new(res);
        let mut n = 0u64;
        let t = std::time::Instant::now();
        for p in &points {
            compute_ray_keys(&conv, o, [p[0] as f32, p[1] as f32, p[2] as f32], |_| {
                n += 1
            });
        }
        let dt = t.elapsed().as_secs_f64();
        println!(
            "res {res}: {} steps, {:.1} ms bare DDA, {:.2} ns/step",
            n,
            dt * 1e3,
            dt * 1e9 / n as f64
        );
    }
}
