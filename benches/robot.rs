//! Criterion benchmarks of the robot geometry core: a UR5 (bodies fitted by
//! `benches/export_robot_model.py`, stored in `benches/data/ur5.model`) in the shared
//! work cell (`earcore_core::synthetic::robot_cell_voxels`, about 18k occupied 5 cm
//! voxels). Run: `cargo bench --bench robot` (one thread).

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use earcore_core::na::Vector3;
use earcore_core::octree::OcTree;
use earcore_core::robot::{
    check_configurations, clearances, self_filter, Body, Chain, CheckParams, Frame, Joint,
    JointKind, RobotModel, VoxelIndex, VoxelSource,
};
use earcore_core::synthetic::{benchmark_scene, render_points, robot_cell_voxels, Rng};
use earcore_core::threads;

/// Parse the exported model (see `benches/export_robot_model.py` for the format).
fn load_model(text: &str) -> RobotModel {
    let mut links = Vec::new();
    let mut joints = Vec::new();
    let mut bodies = Vec::new();
    for line in text.lines().filter(|l| !l.starts_with('#')) {
        let f: Vec<&str> = line.split_whitespace().collect();
        let num = |i: usize| f[i].parse::<f64>().expect("number");
        match f.first() {
            Some(&"links") => links = f[1..].iter().map(|s| s.to_string()).collect(),
            Some(&"joint") => joints.push(Joint {
                name: f[1].into(),
                kind: match f[2] {
                    "revolute" => JointKind::Revolute,
                    "continuous" => JointKind::Continuous,
                    "prismatic" => JointKind::Prismatic,
                    _ => JointKind::Fixed,
                },
                parent: f[3].parse().expect("index"),
                child: f[4].parse().expect("index"),
                origin: Frame::from_xyz_rpy([num(5), num(6), num(7)], [num(8), num(9), num(10)]),
                axis: Vector3::new(num(11), num(12), num(13)),
                lower: num(14),
                upper: num(15),
            }),
            Some(&"body") => {
                let link: usize = f[1].parse().expect("index");
                let (a, b, r) = ([num(3), num(4), num(5)], [num(6), num(7), num(8)], num(9));
                let body = if f[2] == "cylinder" {
                    Body::cylinder(a, b, r)
                } else {
                    Body::capsule(a, b, r)
                };
                bodies.push((link, body));
            }
            _ => {}
        }
    }
    let mut per_link = vec![None; links.len()];
    for (link, body) in bodies {
        per_link[link] = Some(body);
    }
    let chain = Chain::new(links, joints).expect("valid chain");
    RobotModel::new(chain, per_link).expect("valid model")
}

fn ur5() -> RobotModel {
    load_model(include_str!("data/ur5.model"))
}

fn cell_tree() -> OcTree {
    let mut tree = OcTree::new(0.05).expect("resolution");
    for p in robot_cell_voxels(0.05, 0) {
        let key = tree.key_of("cell", p).expect("in map");
        tree.update_node(key, true);
    }
    tree
}

/// Random configurations (row-major) within ±π per joint, with the upper arm above
/// the table (shoulder lift in [-π, 0]) as in `benches/bench_robot_vs_fcl.py`.
fn configurations(model: &RobotModel, n: usize, seed: u64) -> Vec<f64> {
    let mut rng = Rng::new(seed);
    let limits = model.chain().limits();
    let pi = std::f64::consts::PI;
    (0..n)
        .flat_map(|_| {
            limits
                .iter()
                .enumerate()
                .map(|(j, &(lo, hi))| match j {
                    1 => rng.uniform(-pi, 0.0),
                    _ => rng.uniform(lo.max(-pi), hi.min(pi)),
                })
                .collect::<Vec<_>>()
        })
        .collect()
}

fn index_for(model: &RobotModel, tree: &OcTree) -> VoxelIndex {
    VoxelIndex::from_tree(
        tree,
        VoxelSource::Occupied,
        [0.0; 3],
        model.reach_bound() + 0.5,
    )
    .expect("index")
}

fn collision(c: &mut Criterion) {
    threads::set_num_threads(1);
    let model = ur5();
    let tree = cell_tree();
    let index = index_for(&model, &tree);
    let qs = configurations(&model, 10_000, 1);
    let mut group = c.benchmark_group("ur5_in_cell");
    group.throughput(Throughput::Elements(10_000));
    group.sample_size(20);
    group.bench_function("check_configurations/1 thread", |b| {
        b.iter(|| {
            check_configurations(&model, &index, &qs, CheckParams::default()).expect("checks")
        })
    });
    // Against the map only, as the FCL side-by-side (benches/bench_robot_vs_fcl.py) checks.
    let map_only = CheckParams {
        self_collision: false,
    };
    group.bench_function("check_configurations, map only/1 thread", |b| {
        b.iter(|| check_configurations(&model, &index, &qs, map_only).expect("checks"))
    });
    // Clearance is asked of configurations the robot can be in: the free ones.
    let contacts =
        check_configurations(&model, &index, &qs, CheckParams::default()).expect("checks");
    let free: Vec<f64> = qs
        .chunks(model.dof())
        .zip(&contacts)
        .filter(|(_, c)| c.is_free())
        .flat_map(|(q, _)| q.to_vec())
        .collect();
    group.throughput(Throughput::Elements((free.len() / model.dof()) as u64));
    group.bench_function("clearance (free configurations)/1 thread", |b| {
        b.iter(|| clearances(&model, &index, &free).expect("clearances"))
    });
    group.finish();
    let mut group = c.benchmark_group("collision_index");
    group.sample_size(10);
    group.bench_function("build 5cm", |b| b.iter(|| index_for(&model, &tree)));
    group.finish();
    threads::set_num_threads(0);
}

fn filter(c: &mut Criterion) {
    let model = ur5();
    let (camera, pose, shapes) = benchmark_scene();
    let points = render_points(&camera, &pose, &shapes);
    let placed = model
        .place(&[0.3, -1.2, 1.0, -0.5, 0.4, 0.0])
        .expect("valid q");
    let mut group = c.benchmark_group("self_filter");
    group.throughput(Throughput::Elements(points.len() as u64));
    group.sample_size(20);
    for n in [1, 0] {
        threads::set_num_threads(n);
        let label = if n == 1 { "1 thread" } else { "all threads" };
        group.bench_function(label, |b| b.iter(|| self_filter(&points, &placed)));
    }
    threads::set_num_threads(0);
    group.finish();
}

criterion_group!(benches, collision, filter);
criterion_main!(benches);
