//! Paper II's pre-processing chain (crop 1.5 m, 2 cm voxel grid, outlier removal k = 20,
//! 2σ) on one thread, per stage, for profilers. Reads a raw little-endian f64 (N, 3)
//! file of base-frame points if given (e.g. a frame dumped from the perception
//! benchmark), else renders the synthetic benchmark scene.
use earcore_core::cloud::{crop_sphere, statistical_outliers, voxel_downsample, OutlierParams};
use earcore_core::synthetic::{benchmark_scene, render_points};

fn median_ms(runs: usize, mut f: impl FnMut()) -> f64 {
    let mut t: Vec<f64> = (0..runs)
        .map(|_| {
            let t = std::time::Instant::now();
            f();
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[runs / 2]
}

fn main() {
    earcore_core::threads::set_num_threads(1);
    let points: Vec<[f64; 3]> = match std::env::args().nth(1) {
        Some(path) => std::fs::read(path)
            .expect("readable points file")
            .chunks_exact(24)
            .map(|c| [0, 1, 2].map(|a| f64::from_le_bytes(c[a * 8..a * 8 + 8].try_into().unwrap())))
            .collect(),
        None => {
            let (camera, pose, shapes) = benchmark_scene();
            render_points(&camera, &pose, &shapes)
        }
    };
    let runs: usize = std::env::var("RUNS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(40);
    let stage = std::env::var("STAGE").unwrap_or_default();
    let keep = crop_sphere(&points, [0.0; 3], 1.5).unwrap();
    let cropped: Vec<[f64; 3]> = keep.iter().map(|&i| points[i as usize]).collect();
    let (grid, _) = voxel_downsample(&cropped, 0.02, None).unwrap();
    let (kept, _) = statistical_outliers(&grid, OutlierParams::default()).unwrap();
    let all = stage.is_empty();
    let mut total = 0.0;
    if all || stage == "crop" {
        let t = median_ms(runs, || drop(crop_sphere(&points, [0.0; 3], 1.5)));
        println!(
            "crop      {t:6.2} ms  {} -> {}",
            points.len(),
            cropped.len()
        );
        total += t;
    }
    if all || stage == "grid" {
        let t = median_ms(runs, || drop(voxel_downsample(&cropped, 0.02, None)));
        println!("grid      {t:6.2} ms  -> {}", grid.len());
        total += t;
    }
    if all || stage == "outliers" {
        let t = median_ms(runs, || {
            drop(statistical_outliers(&grid, OutlierParams::default()));
        });
        println!("outliers  {t:6.2} ms  -> {}", kept.len());
        total += t;
    }
    println!("total     {total:6.2} ms");
}
