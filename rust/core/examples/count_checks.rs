use earcore_core::na::Vector3;
use earcore_core::octree::OcTree;
use earcore_core::robot::{
    check_configurations, Body, Chain, CheckParams, Frame, Joint, JointKind, RobotModel,
    VoxelIndex, VoxelSource,
};
use earcore_core::synthetic::{robot_cell_voxels, Rng};
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
    load_model(include_str!("../../../benches/data/ur5.model"))
}

fn cell_tree() -> OcTree {
    let mut tree = OcTree::new(0.05).expect("resolution");
    for p in robot_cell_voxels(0.05, 0) {
        let key = tree.key_of("cell", p).expect("in map");
        tree.update_node(key, true);
    }
    tree
}

/// Random configurations within ±π per joint (row-major).
fn configurations(model: &RobotModel, n: usize, seed: u64) -> Vec<f64> {
    let mut rng = Rng::new(seed);
    let limits = model.chain().limits();
    (0..n)
        .flat_map(|_| {
            limits
                .iter()
                .map(|&(lo, hi)| {
                    rng.uniform(lo.max(-std::f64::consts::PI), hi.min(std::f64::consts::PI))
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

fn main() {
    earcore_core::threads::set_num_threads(1);
    let model = ur5();
    let tree = cell_tree();
    let index = index_for(&model, &tree);
    let qs = configurations(&model, 10_000, 1);
    let t = std::time::Instant::now();
    let c = check_configurations(&model, &index, &qs, CheckParams::default()).unwrap();
    let dt = t.elapsed().as_secs_f64();
    let hit = c.iter().filter(|c| !c.is_free()).count();
    println!("{:.0}/s colliding {}", 10000.0 / dt, hit);
}
