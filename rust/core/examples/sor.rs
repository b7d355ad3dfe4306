//! Statistical outlier removal (k-d tree k-NN) on the benchmark frame's 2 cm voxel
//! grid and on as many uniform random points, one thread (for profilers).
use earcore_core::cloud::{statistical_outliers, voxel_downsample, OutlierParams};
use earcore_core::synthetic::{benchmark_scene, render_points};

fn time(label: &str, points: &[[f64; 3]]) {
    let mut runs: Vec<f64> = (0..40)
        .map(|_| {
            let t = std::time::Instant::now();
            statistical_outliers(points, OutlierParams::default()).expect("enough points");
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    runs.sort_by(f64::total_cmp);
    println!(
        "{label}: {} points, median {:.2} ms, fastest {:.2} ms",
        points.len(),
        runs[20],
        runs[0]
    );
}

fn main() {
    earcore_core::threads::set_num_threads(1);
    let (camera, pose, shapes) = benchmark_scene();
    let points = render_points(&camera, &pose, &shapes);
    let (surface, _) = voxel_downsample(&points, 0.02, None).expect("valid voxel size");
    time("surface (2 cm voxel grid)", &surface);
    let mut s = 1u64;
    let mut rnd = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 11) as f64 / (1u64 << 53) as f64
    };
    let uniform: Vec<[f64; 3]> = (0..surface.len()).map(|_| [rnd(), rnd(), rnd()]).collect();
    time("uniform in a cube", &uniform);
}
