//! Criterion benchmarks of the point-cloud core, one thread:
//! - pre-processing of the shared benchmark frame (`synthetic::benchmark_scene`, 512×424,
//!   ≤ 3 m): 1.5 m crop, 2 cm voxel grid, statistical outlier removal (k 20, 2σ);
//! - NOctoSLAM's surface map: the update (insert + propagate, dynamic leaf depth) of a
//!   VLP-16 scan of an 8 × 8 × 3.5 m room into the map of another scan from the same pose;
//! - point-to-plane ICP of such a scan against the map of scans along a short path;
//! - k-d tree queries as ICP's `PlaneTarget` makes them, 2 cm off the target in Morton
//!   order (a scan against five merged scans; the benchmark frame's every 13th point
//!   against the frame): the nearest two within 0.25 m (the fixed-array search) beside the
//!   general sorted-vector search (`knn`, no limit), and the nearest one.
//!
//! Run: `cargo bench --bench cloud`. The Python benchmarks (`benches/bench_preprocess.py`,
//! `bench_surface_map.py`) time the same stages from Python beside open3d and small_gicp.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use earcore_core::cloud::{
    crop_sphere, icp_point_to_plane, statistical_outliers, voxel_downsample, IcpParams, KdTree,
    Kernel, OutlierParams,
};
use earcore_core::na::{Matrix4, Rotation3, Vector3};
use earcore_core::octree::{SurfaceMap, SurfaceParams};
use earcore_core::synthetic::{benchmark_scene, lidar_scan, render_points, Lidar, Shape};
use earcore_core::threads;

/// The room (a box seen from inside) with furniture-sized boxes on its floor.
fn room() -> Vec<Shape> {
    let mut shapes = vec![Shape::Box {
        lo: [-4.0, -4.0, 0.0],
        hi: [4.0, 4.0, 3.5],
    }];
    for (lo, hi) in [
        ([-3.5, -3.2, 0.0], [-2.6, -2.4, 0.9]),
        ([1.2, 2.5, 0.0], [2.6, 3.6, 1.8]),
        ([2.8, -1.0, 0.0], [3.6, 0.2, 0.75]),
        ([-1.0, 1.0, 0.0], [-0.4, 1.9, 1.2]),
        ([0.5, -3.6, 0.0], [1.8, -3.0, 2.0]),
    ] {
        shapes.push(Shape::Box { lo, hi });
    }
    shapes
}

/// A lidar pose in the room: z up, yawed, at `position`.
fn pose(position: [f64; 3], yaw: f64) -> Matrix4<f64> {
    let mut m = Matrix4::identity();
    m.fixed_view_mut::<3, 3>(0, 0)
        .copy_from(Rotation3::from_axis_angle(&Vector3::z_axis(), yaw).matrix());
    m.fixed_view_mut::<3, 1>(0, 3)
        .copy_from(&Vector3::from(position));
    m
}

/// One scan in room coordinates.
fn scan(at: &Matrix4<f64>, seed: u64) -> Vec<[f64; 3]> {
    let mut points = lidar_scan(&Lidar::vlp16(), at, &room(), seed);
    earcore_core::geometry::transform_points(at, &mut points);
    points
}

/// NOctoSLAM's lidar settings (`earcore.lidar_odometry.OdometrySettings`): 1 cm, 2°
/// between rings, leaves up to 16 cm, a leaf the mean of its first 100 points.
fn lidar_map() -> SurfaceMap {
    let params = SurfaceParams {
        position_memory: Some(100),
        ..SurfaceParams::default()
    };
    SurfaceMap::new(0.01, params).expect("valid resolution")
}

fn insert(map: &mut SurfaceMap, points: &[[f64; 3]], at: &Matrix4<f64>) {
    let origin = [at[(0, 3)], at[(1, 3)], at[(2, 3)]];
    let depths = map
        .leaf_depths(points, origin, 2f64.to_radians(), 0.16)
        .expect("valid settings");
    map.insert_at_depths(points, Some(&depths))
        .expect("points in the map");
}

fn preprocessing(c: &mut Criterion) {
    threads::set_num_threads(1);
    let (camera, at, shapes) = benchmark_scene();
    let points = render_points(&camera, &at, &shapes);
    let kept = crop_sphere(&points, [0.0, 0.0, 0.0], 1.5).expect("finite points");
    let cropped: Vec<[f64; 3]> = kept.iter().map(|&i| points[i as usize]).collect();
    let (grid, _) = voxel_downsample(&cropped, 0.02, None).expect("valid voxel size");
    let mut group = c.benchmark_group("preprocess");
    group.bench_function("crop 1.5 m", |b| {
        b.iter(|| crop_sphere(&points, [0.0, 0.0, 0.0], 1.5).expect("finite points"))
    });
    group.bench_function("voxel grid 2 cm", |b| {
        b.iter(|| voxel_downsample(&cropped, 0.02, None).expect("valid voxel size"))
    });
    group.bench_function("outliers k 20, 2 sigma", |b| {
        b.iter(|| statistical_outliers(&grid, OutlierParams::default()).expect("enough points"))
    });
    group.finish();
}

fn surface_map(c: &mut Criterion) {
    threads::set_num_threads(1);
    let at = pose([0.4, -0.7, 1.6], 0.3);
    let (first, probe) = (scan(&at, 1), scan(&at, 2));
    let mut map = lidar_map();
    insert(&mut map, &first, &at);
    let mut group = c.benchmark_group("surface_map");
    group.throughput(Throughput::Elements(probe.len() as u64));
    group.bench_function("update, VLP-16 scan, dynamic leaf depth", |b| {
        b.iter(|| insert(&mut map, &probe, &at))
    });
    group.finish();
}

fn icp(c: &mut Criterion) {
    threads::set_num_threads(1);
    let mut map = lidar_map();
    for k in 0..20 {
        let at = pose([0.02 * k as f64, -0.7, 1.6], 0.3 + 0.01 * k as f64);
        insert(&mut map, &scan(&at, 10 + k), &at);
    }
    let truth = pose([0.41, -0.7, 1.6], 0.5);
    let source = lidar_scan(&Lidar::vlp16(), &truth, &room(), 99);
    let mut guess = truth;
    guess[(0, 3)] += 0.02;
    guess[(1, 3)] -= 0.01;
    let params = |iterations| IcpParams {
        max_iterations: iterations,
        max_correspondence_distance: 0.2,
        translation_tolerance: 0.0,
        rotation_tolerance: 0.0,
        sigma_tolerance: 0.0,
        kernel: Kernel::Huber(0.03),
    };
    let mut group = c.benchmark_group("icp_point_to_plane");
    group.throughput(Throughput::Elements(source.len() as u64));
    for iterations in [1, 11] {
        group.bench_function(
            format!("VLP-16 scan vs surface map, {iterations} iterations"),
            |b| {
                b.iter(|| {
                    icp_point_to_plane(&source, &map, &guess, params(iterations)).expect("aligns")
                })
            },
        );
    }
    group.finish();
}

fn kdtree(c: &mut Criterion) {
    // Sparse rings: five VLP-16 scans, queries from a sixth.
    let mut rings = Vec::new();
    for k in 0..5 {
        let at = pose([0.3 * k as f64, -0.7, 1.6], 0.3 + 0.2 * k as f64);
        rings.extend(scan(&at, 20 + k));
    }
    let at = pose([0.65, -0.6, 1.6], 0.7);
    let ring_queries = scan(&at, 98);
    // A dense surface: the benchmark depth frame, queries from every 13th of its points.
    let (camera, frame_pose, shapes) = benchmark_scene();
    let frame = render_points(&camera, &frame_pose, &shapes);
    let frame_queries: Vec<[f64; 3]> = frame.iter().step_by(13).copied().collect();
    for (name, target, mut queries) in [
        ("VLP-16 scans", rings, ring_queries),
        ("depth frame", frame, frame_queries),
    ] {
        let tree = KdTree::new(&target);
        for q in &mut queries {
            q[0] += 0.02;
        }
        let order = earcore_core::geometry::morton_order(&queries);
        let queries: Vec<[f64; 3]> = order.iter().map(|&i| queries[i as usize]).collect();
        let mut group = c.benchmark_group(format!("kdtree, {name}, {} targets", target.len()));
        group.throughput(Throughput::Elements(queries.len() as u64));
        let mut out = Vec::new();
        group.bench_function("nearest two within 0.25 m", |b| {
            b.iter(|| {
                for &q in &queries {
                    tree.knn_within(q, 2, 0.0625, &mut out);
                }
            })
        });
        group.bench_function("nearest two, general search", |b| {
            b.iter(|| {
                for &q in &queries {
                    tree.knn(q, 2, None, &mut out);
                }
            })
        });
        group.bench_function("nearest within 0.25 m", |b| {
            b.iter(|| {
                queries
                    .iter()
                    .filter_map(|&q| tree.nearest_within(q, 0.0625))
                    .count()
            })
        });
        group.finish();
    }
}

criterion_group!(benches, preprocessing, surface_map, icp, kdtree);
criterion_main!(benches);
