//! Insert a frame repeatedly (for profilers): `cargo run --release --example insert_frame -- 0.02 1 [reps] [scan.bin]`.
//! Without a file, the benchmark frame; a file holds the sensor origin and then the
//! points, little-endian f64 triples.
use earcore_core::octree::OcTree;
use earcore_core::synthetic::{benchmark_scene, render_points};

fn read_scan(path: &str) -> ([f64; 3], Vec<[f64; 3]>) {
    let bytes = std::fs::read(path).expect("readable scan file");
    let values: Vec<f64> = bytes
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes(b.try_into().expect("8 bytes")))
        .collect();
    let triples: Vec<[f64; 3]> = values.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    (triples[0], triples[1..].to_vec())
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let res: f64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(0.05);
    let threads: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(1);
    let reps: usize = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(10);
    earcore_core::threads::set_num_threads(threads);
    let (origin, points) = match args.get(4) {
        Some(path) => read_scan(path),
        None => {
            let (camera, pose, shapes) = benchmark_scene();
            let points = render_points(&camera, &pose, &shapes);
            ([pose[(0, 3)], pose[(1, 3)], pose[(2, 3)]], points)
        }
    };
    let t = std::time::Instant::now();
    let mut size = 0;
    let mut best = f64::INFINITY;
    for _ in 0..reps {
        let one = std::time::Instant::now();
        let mut tree = OcTree::new(res).expect("valid resolution");
        let r = tree
            .insert_point_cloud(&points, origin, None, false)
            .expect("valid scan");
        size = tree.size();
        best = best.min(one.elapsed().as_secs_f64() * 1e3);
        if reps == 1 {
            println!("{r:?}");
        }
    }
    println!(
        "{} points, {} nodes, {:.2} ms per frame ({:.2} ms at best)",
        points.len(),
        size,
        t.elapsed().as_secs_f64() * 1e3 / reps as f64,
        best
    );
}
