//! OctoMap itself as the reference, without Python: `tests/data/` holds a small scene
//! and the files OctoMap (pyoctomap, see `tests/data/make_octomap_fixture.py`) wrote
//! for it. The same map built here must serialise to the same bytes, `.ot` and `.bt`,
//! and agree with OctoMap's node counts and log-odds; a few of OctoMap's update rules
//! (hit and miss values, clamping, pruning) are checked on their own as well.

use earcore_core::octree::{logodds, probability, OcTree, OccupancyParams};

/// The fixture: the scene, the scans and single-cell updates, and OctoMap's answers.
#[derive(Default)]
struct Fixture {
    resolution: f64,
    points: Vec<[f64; 3]>,
    /// Origin, max range (None: unlimited), discretize.
    scans: Vec<([f64; 3], Option<f64>, bool)>,
    /// A cell and its update: `Ok(hit)` for a hit or a miss, `Err(delta)` for a
    /// log-odds change.
    updates: Vec<([f64; 3], Result<bool, f32>)>,
    /// Per tree ("scene" or "updates"): OctoMap's size and leaf count.
    counts: Vec<(String, &'static str, usize)>,
    /// Per tree: a point and OctoMap's log-odds there (NaN: unknown).
    probes: Vec<(String, [f64; 3], f64)>,
}

fn data(name: &str) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/data")
        .join(name)
}

fn read_bytes(name: &str) -> Vec<u8> {
    std::fs::read(data(name)).unwrap_or_else(|e| panic!("{name}: {e}"))
}

fn fixture() -> Fixture {
    let text = std::fs::read_to_string(data("octomap_scene.txt")).unwrap();
    let mut f = Fixture::default();
    for line in text.lines() {
        let line = line.split('#').next().unwrap().trim();
        if line.is_empty() {
            continue;
        }
        let words: Vec<&str> = line.split_whitespace().collect();
        let num = |i: usize| -> f64 { words[i].parse().unwrap_or_else(|_| panic!("{line}")) };
        let point = |i: usize| [num(i), num(i + 1), num(i + 2)];
        match words[0] {
            "resolution" => f.resolution = num(1),
            "p" => f.points.push(point(1)),
            "scan" => {
                let max_range = Some(num(4)).filter(|&r| r >= 0.0);
                f.scans.push((point(1), max_range, words[5] == "1"));
            }
            "update" => {
                let update = match words[4] {
                    "hit" => Ok(true),
                    "miss" => Ok(false),
                    _ => Err(num(4) as f32),
                };
                f.updates.push((point(1), update));
            }
            "size" => f.counts.push((words[1].into(), "size", num(2) as usize)),
            "leaves" => f.counts.push((words[1].into(), "leaves", num(2) as usize)),
            "probe" => f.probes.push((words[1].into(), point(2), num(5))),
            other => panic!("unknown fixture line {other:?}"),
        }
    }
    assert!(f.resolution > 0.0 && f.points.len() > 100 && f.scans.len() == 2);
    f
}

fn scanned(f: &Fixture) -> OcTree {
    let mut tree = OcTree::new(f.resolution).unwrap();
    for &(origin, max_range, discretize) in &f.scans {
        tree.insert_point_cloud(&f.points, origin, max_range, discretize)
            .unwrap();
    }
    tree
}

fn updated(f: &Fixture) -> OcTree {
    let mut tree = OcTree::new(f.resolution).unwrap();
    for &(p, update) in &f.updates {
        let key = tree.key_of("cell", p).unwrap();
        match update {
            Ok(hit) => tree.update_node(key, hit),
            Err(delta) => tree.update_node_log_odds(key, delta).unwrap(),
        }
    }
    tree
}

/// OctoMap's size, leaf count and probed log-odds for `which` tree.
fn check_against_octomap(f: &Fixture, which: &str, tree: &OcTree) {
    for (name, what, expected) in f.counts.iter().filter(|c| c.0 == which) {
        let got = match *what {
            "size" => tree.size(),
            _ => tree.num_leaf_nodes(),
        };
        assert_eq!(got, *expected, "{name} {what}");
    }
    let probes: Vec<_> = f.probes.iter().filter(|p| p.0 == which).collect();
    assert!(probes.len() >= 5);
    for (_, p, expected) in probes {
        let got = tree.search(tree.key_of("probe", *p).unwrap(), 0);
        match got {
            None => assert!(
                expected.is_nan(),
                "{which} {p:?}: unknown, OctoMap {expected}"
            ),
            // OctoMap stores float log-odds; the fixture wrote them as doubles.
            Some(l) => assert_eq!(f64::from(l), *expected, "{which} {p:?}"),
        }
    }
}

#[test]
fn scanned_scene_serialises_to_octomaps_bytes() {
    let f = fixture();
    let tree = scanned(&f);
    check_against_octomap(&f, "scene", &tree);
    assert!(
        tree.write_full_bytes() == read_bytes("octomap_scene.ot"),
        ".ot differs from OctoMap's"
    );
    assert!(
        tree.write_binary_bytes() == read_bytes("octomap_scene.bt"),
        ".bt differs from OctoMap's"
    );
}

#[test]
fn single_cell_updates_serialise_to_octomaps_bytes() {
    let f = fixture();
    let tree = updated(&f);
    check_against_octomap(&f, "updates", &tree);
    assert!(tree.write_full_bytes() == read_bytes("octomap_updates.ot"));
}

#[test]
fn octomaps_files_read_back_and_write_the_same_bytes() {
    let params = OccupancyParams::default();
    for name in ["octomap_scene.ot", "octomap_updates.ot"] {
        let bytes = read_bytes(name);
        let tree = OcTree::read_full_bytes(&bytes, params).unwrap();
        assert!(tree.write_full_bytes() == bytes, "{name}");
    }
    let bytes = read_bytes("octomap_scene.bt");
    let tree = OcTree::read_binary_bytes(&bytes, params).unwrap();
    assert!(tree.write_binary_bytes() == bytes);
    // A .bt keeps occupied / free per cell: the scanned scene's classes survive it.
    let scene = scanned(&fixture());
    let mut checked = 0;
    scene.for_each_leaf(|leaf| {
        let back = tree.search(leaf.key, leaf.depth).unwrap();
        assert_eq!(
            tree.is_occupied_log_odds(back),
            scene.is_occupied_log_odds(leaf.log_odds)
        );
        checked += 1;
    });
    assert!(checked > 1000, "{checked}");
}

#[test]
fn hits_and_misses_use_octomaps_sensor_model_and_clamping() {
    let mut tree = OcTree::new(0.1).unwrap();
    let p = tree.key_of("cell", [0.25, -0.15, 0.35]).unwrap();
    let q = tree.key_of("cell", [-0.25, 0.15, 0.05]).unwrap();
    assert_eq!(tree.search(p, 0), None, "unknown before any update");
    tree.update_node(p, true);
    tree.update_node(q, false);
    // One hit or miss from unknown (0): OctoMap's prob_hit 0.7 and prob_miss 0.4.
    assert_eq!(tree.search(p, 0), Some(logodds(0.7)));
    assert_eq!(tree.search(q, 0), Some(logodds(0.4)));
    assert!((probability(tree.search(p, 0).unwrap()) - 0.7).abs() < 1e-6);
    assert!(tree.is_occupied_log_odds(tree.search(p, 0).unwrap()));
    assert!(!tree.is_occupied_log_odds(tree.search(q, 0).unwrap()));
    // Hits and misses add up in log-odds.
    tree.update_node(p, false);
    let expected = logodds(0.7) + logodds(0.4);
    assert_eq!(tree.search(p, 0), Some(expected));
    // Many updates stop at the clamping bounds (0.971 and 0.1192).
    let (lo, hi) = tree.clamping_log_odds();
    assert_eq!((lo, hi), (logodds(0.1192), logodds(0.971)));
    for _ in 0..50 {
        tree.update_node(p, true);
        tree.update_node(q, false);
    }
    assert_eq!(tree.search(p, 0), Some(hi));
    assert_eq!(tree.search(q, 0), Some(lo));
    // A raw change is clamped the same way.
    tree.update_node_log_odds(q, -100.0).unwrap();
    assert_eq!(tree.search(q, 0), Some(lo));
}

#[test]
fn equal_children_are_pruned_into_their_parent() {
    let mut tree = OcTree::new(0.1).unwrap();
    let corner = [0.05, 0.05, 0.05];
    let cells: Vec<[f64; 3]> = (0..8)
        .map(|i| [0, 1, 2].map(|a| corner[a] + 0.1 * f64::from((i >> a) & 1)))
        .collect();
    // Until all eight are clamped their values differ (the last updated is ahead).
    for round in 0..12 {
        for &c in &cells {
            let key = tree.key_of("cell", c).unwrap();
            tree.update_node(key, true);
        }
        if round == 0 {
            // Equal but not at a bound: OctoMap prunes any equal siblings.
            assert_eq!(tree.num_leaf_nodes(), 1);
        }
    }
    // One leaf at depth 15 stands for the eight cells, with their common value.
    assert_eq!(tree.num_leaf_nodes(), 1);
    assert_eq!(tree.size(), 16);
    let key = tree.key_of("cell", cells[5]).unwrap();
    let (_, depth) = tree.search_node(key, 0).unwrap();
    assert_eq!(depth, 15);
    assert_eq!(tree.search(key, 0), Some(tree.clamping_log_odds().1));
    // Changing one cell expands the parent again.
    tree.update_node(key, false);
    assert_eq!(tree.num_leaf_nodes(), 8);
    assert!(tree.search(key, 0).unwrap() < tree.clamping_log_odds().1);
}
