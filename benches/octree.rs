//! Criterion benchmarks of the map core on the shared benchmark scene
//! (`earcore_core::synthetic::benchmark_scene`): one 512×424 depth frame, range ≤ 3 m.
//! Run: `cargo bench` (single thread and all threads are both reported).

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use earcore_core::octree::OcTree;
use earcore_core::synthetic::{benchmark_scene, render_points};
use earcore_core::threads;

/// The benchmark frame: points and sensor origin.
fn frame() -> (Vec<[f64; 3]>, [f64; 3]) {
    let (camera, pose, shapes) = benchmark_scene();
    (
        render_points(&camera, &pose, &shapes),
        [pose[(0, 3)], pose[(1, 3)], pose[(2, 3)]],
    )
}

/// The benchmark frame inserted into a 5 cm map.
fn mapped_frame() -> (Vec<[f64; 3]>, OcTree) {
    let (points, origin) = frame();
    let mut tree = OcTree::new(0.05).expect("valid resolution");
    tree.insert_point_cloud(&points, origin, None, false)
        .expect("valid scan");
    (points, tree)
}

fn insert_frame(c: &mut Criterion) {
    let (points, origin) = frame();
    let mut group = c.benchmark_group("insert_point_cloud");
    group.throughput(Throughput::Elements(points.len() as u64));
    group.sample_size(20);
    for resolution in [0.05, 0.02] {
        for n_threads in [1, 0] {
            threads::set_num_threads(n_threads);
            let label = format!(
                "{}cm/{}",
                resolution * 100.0,
                if n_threads == 1 {
                    "1 thread"
                } else {
                    "all threads"
                }
            );
            group.bench_with_input(
                BenchmarkId::from_parameter(label),
                &resolution,
                |b, &res| {
                    b.iter(|| {
                        let mut tree = OcTree::new(res).expect("valid resolution");
                        tree.insert_point_cloud(&points, origin, None, false)
                            .expect("valid scan");
                        tree
                    })
                },
            );
        }
    }
    threads::set_num_threads(0);
    group.finish();
}

fn queries(c: &mut Criterion) {
    let (points, tree) = mapped_frame();
    let mut group = c.benchmark_group("queries");
    group.throughput(Throughput::Elements(points.len() as u64));
    group.bench_function("search 217k points", |b| {
        b.iter(|| {
            points
                .iter()
                .filter_map(|&p| tree.key_converter().coord_to_key_checked_f64(p))
                .filter_map(|k| tree.search(k, 0))
                .filter(|&l| tree.is_occupied_log_odds(l))
                .count()
        })
    });
    group.bench_function("write .bt", |b| b.iter(|| tree.write_binary_bytes().len()));
    group.finish();
}

fn danger_frame(c: &mut Criterion) {
    let (_, mut tree) = mapped_frame();
    c.bench_function("end_frame with the frame's hits active", |b| {
        b.iter(|| {
            tree.danger_map_mut()
                .end_frame(1.0 / 15.0)
                .expect("valid dt")
        })
    });
}

criterion_group!(benches, insert_frame, queries, danger_frame);
criterion_main!(benches);
