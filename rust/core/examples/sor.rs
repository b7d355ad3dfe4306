//! Statistical outlier removal on the benchmark frame (for profilers).
use earcore_core::cloud::{statistical_outliers, voxel_downsample, OutlierParams};
use earcore_core::synthetic::{benchmark_scene, render_points};

fn main() {
    earcore_core::threads::set_num_threads(1);
    let (camera, pose, shapes) = benchmark_scene();
    let points = render_points(&camera, &pose, &shapes);
    let (v, _) = voxel_downsample(&points, 0.02, None).unwrap();
    let t = std::time::Instant::now();
    for _ in 0..20 {
        statistical_outliers(&v, OutlierParams::default()).unwrap();
    }
    println!(
        "{} points: {:.2} ms",
        v.len(),
        t.elapsed().as_secs_f64() * 1e3 / 20.0
    );
}
