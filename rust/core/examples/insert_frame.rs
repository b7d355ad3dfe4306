//! Insert the benchmark frame repeatedly (for profilers): `cargo run --release --example insert_frame -- 0.02 1`
use earcore_core::octree::OcTree;
use earcore_core::synthetic::{benchmark_scene, render_points};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let res: f64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(0.05);
    let threads: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(1);
    let reps: usize = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(10);
    earcore_core::threads::set_num_threads(threads);
    let (camera, pose, shapes) = benchmark_scene();
    let points = render_points(&camera, &pose, &shapes);
    let origin = [pose[(0, 3)], pose[(1, 3)], pose[(2, 3)]];
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
