//! SurfaceMap update (insert + propagate) of one lidar scan into the map of another
//! scan from the same pose, with dynamic leaf depth, one thread (for profilers).
//! Reads two raw little-endian f64 (N, 3) files and the sensor origin:
//!
//!     surface_insert FIRST.bin PROBE.bin X Y Z
//!
//! (`benches/bench_surface_map.py`'s "one scan" case; dump its scans with numpy's `tofile`).
use earcore_core::octree::{SurfaceMap, SurfaceParams};

fn read(path: &str) -> Vec<[f64; 3]> {
    std::fs::read(path)
        .expect("readable points file")
        .chunks_exact(24)
        .map(|c| [0, 1, 2].map(|a| f64::from_le_bytes(c[a * 8..a * 8 + 8].try_into().unwrap())))
        .collect()
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let (first, probe) = (read(&args[1]), read(&args[2]));
    let origin = [3, 4, 5].map(|i| args[i].parse::<f64>().expect("origin x y z"));
    let runs: usize = std::env::var("RUNS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(41);
    // The lidar odometry's settings: 1 cm, 2° between rings, leaves up to 16 cm, a leaf
    // the mean of its first 100 points.
    let params = SurfaceParams {
        position_memory: Some(100),
        ..SurfaceParams::default()
    };
    let mut map = SurfaceMap::new(0.01, params).unwrap();
    let depths =
        |m: &SurfaceMap, p: &[[f64; 3]]| m.leaf_depths(p, origin, 2f64.to_radians(), 0.16).unwrap();
    let d = depths(&map, &first);
    map.insert_at_depths(&first, Some(&d)).unwrap();
    let mut times: Vec<f64> = (0..runs)
        .map(|_| {
            let t = std::time::Instant::now();
            let d = depths(&map, &probe);
            map.insert_at_depths(&probe, Some(&d)).unwrap();
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    times.sort_by(f64::total_cmp);
    println!(
        "{} points into a map of {} nodes: median {:.3} ms, fastest {:.3} ms",
        probe.len(),
        map.size(),
        times[runs / 2],
        times[0]
    );
}
