//! The ray traversal against a brute-force reference: every cell whose box the
//! segment crosses is found by testing all cells of the segment's bounding box.
//! Then the same through a whole insertion.

use earcore_core::octree::{compute_ray_keys, KeyConverter, OcTree, OcTreeKey};
use std::collections::BTreeSet;

/// Length of the part of segment `a→b` inside the axis-aligned box `[lo, hi]`
/// (slab test in double precision).
fn crossing_length(a: [f64; 3], b: [f64; 3], lo: [f64; 3], hi: [f64; 3]) -> f64 {
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for i in 0..3 {
        let d = b[i] - a[i];
        if d == 0.0 {
            if a[i] < lo[i] || a[i] > hi[i] {
                return 0.0;
            }
            continue;
        }
        let (u, v) = ((lo[i] - a[i]) / d, (hi[i] - a[i]) / d);
        t0 = t0.max(u.min(v));
        t1 = t1.min(u.max(v));
    }
    let len = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2) + (b[2] - a[2]).powi(2)).sqrt();
    (t1 - t0).max(0.0) * len
}

/// Tiny deterministic generator (the tests need no external crates).
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next()
    }
}

/// Cells of the segment `a→b`: (clearly crossed, touched). A crossed cell whose box
/// also holds the end point (the end lies on its boundary) is left out of "crossed":
/// OctoMap stops the walk once the distance travelled exceeds the length, and with
/// rounding that can happen just before such a cell.
fn brute_force_cells(
    conv: &KeyConverter,
    a: [f32; 3],
    b: [f32; 3],
    res: f64,
) -> (BTreeSet<OcTreeKey>, BTreeSet<OcTreeKey>) {
    let a64 = a.map(f64::from);
    let b64 = b.map(f64::from);
    let ka = conv.coord_to_key_checked(a).unwrap();
    let kb = conv.coord_to_key_checked(b).unwrap();
    let (mut crossed, mut touched) = (BTreeSet::new(), BTreeSet::new());
    let lo = [0, 1, 2].map(|i| ka.0[i].min(kb.0[i]) - 1);
    let hi = [0, 1, 2].map(|i| ka.0[i].max(kb.0[i]) + 1);
    for x in lo[0]..=hi[0] {
        for y in lo[1]..=hi[1] {
            for z in lo[2]..=hi[2] {
                let key = OcTreeKey([x, y, z]);
                let c = [x, y, z].map(|k| conv.key_to_coord_axis(k));
                let (blo, bhi) = (c.map(|v| v - res / 2.0), c.map(|v| v + res / 2.0));
                let len = crossing_length(a64, b64, blo, bhi);
                // Touching within rounding, and crossed clearly (not grazing an edge).
                let grown = crossing_length(a64, b64, blo.map(|v| v - 1e-6), bhi.map(|v| v + 1e-6));
                if grown > 0.0 {
                    touched.insert(key);
                }
                let holds_end = (0..3).all(|i| b64[i] >= blo[i] - 1e-6 && b64[i] <= bhi[i] + 1e-6);
                if len > 1e-6 && !holds_end {
                    crossed.insert(key);
                }
            }
        }
    }
    (crossed, touched)
}

#[test]
fn ray_cells_match_brute_force() {
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    for &res in &[0.05, 0.1, 0.02] {
        let conv = KeyConverter::new(res);
        for _ in 0..400 {
            let a = [0; 3].map(|_| rng.range(-1.0, 1.0) as f32);
            let b = [0; 3].map(|_| rng.range(-1.0, 1.0) as f32);
            let mut dda = BTreeSet::new();
            compute_ray_keys(&conv, a, b, |k| {
                assert!(dda.insert(k), "a cell visited twice");
            });
            let end = conv.coord_to_key_checked(b).unwrap();
            let (crossed, touched) = brute_force_cells(&conv, a, b, res);
            assert!(!dda.contains(&end), "the end cell is excluded");
            // Every visited cell is touched by the segment...
            for k in &dda {
                assert!(
                    touched.contains(k),
                    "visited {k:?} which the segment does not touch"
                );
            }
            // ...and every clearly crossed cell but the end cell is visited.
            for k in crossed.iter().filter(|&&k| k != end) {
                assert!(
                    dda.contains(k),
                    "missed crossed cell {k:?} on ray {a:?} -> {b:?} at {res}"
                );
            }
        }
    }
}

#[test]
fn insertion_marks_ray_cells_free_and_end_cells_occupied() {
    let res = 0.05;
    let mut tree = OcTree::new(res).unwrap();
    let origin = [0.013, -0.021, 0.4];
    let points = [[1.234, 0.55, 0.12], [-0.8, 0.31, 1.9], [0.5, -1.3, 0.4]];
    tree.insert_point_cloud(&points, origin, None, false)
        .unwrap();
    let conv = *tree.key_converter();
    let (hit, miss) = (
        earcore_core::octree::logodds(0.7),
        earcore_core::octree::logodds(0.4),
    );
    let o32 = origin.map(|v| v as f32);
    let mut expected_free = BTreeSet::new();
    let mut expected_occupied = BTreeSet::new();
    for p in points {
        let p32 = p.map(|v| v as f32);
        let (crossed, _) = brute_force_cells(&conv, o32, p32, res);
        let end = conv.coord_to_key_checked(p32).unwrap();
        expected_free.extend(crossed.into_iter().filter(|&k| k != end));
        expected_occupied.insert(end);
    }
    for k in &expected_occupied {
        assert_eq!(tree.search(*k, 0), Some(hit));
    }
    for k in expected_free.difference(&expected_occupied) {
        assert_eq!(tree.search(*k, 0), Some(miss), "{k:?} should be free");
    }
    let mut leaves = 0;
    tree.for_each_leaf(|l| {
        assert_eq!(l.depth, 16);
        assert!(l.log_odds == hit || l.log_odds == miss);
        leaves += 1;
    });
    // At most the cells next to an end point on a cell boundary come on top.
    let expected = expected_free.union(&expected_occupied).count();
    assert!(
        leaves >= expected && leaves <= expected + 3 * points.len(),
        "{leaves} leaves, expected about {expected}"
    );
}

#[test]
fn files_round_trip_in_rust() {
    let mut tree = OcTree::new(0.1).unwrap();
    let pts: Vec<[f64; 3]> = (0..200)
        .map(|i| {
            [
                (i as f64 * 0.37).sin() * 2.0,
                (i as f64 * 0.11).cos() * 2.0,
                0.7,
            ]
        })
        .collect();
    tree.insert_point_cloud(&pts, [0.0, 0.0, 1.5], None, false)
        .unwrap();
    let leaves = |t: &OcTree| {
        let mut all = Vec::new();
        t.for_each_leaf(|l| all.push((l.key.0, l.depth, l.log_odds)));
        all.sort_by_key(|a| (a.0, a.1));
        all
    };
    // .ot keeps every leaf with its log-odds; reading it back gives the same tree.
    let full = OcTree::read_full_bytes(&tree.write_full_bytes(), Default::default()).unwrap();
    assert_eq!(leaves(&full), leaves(&tree));
    assert_eq!(full.write_full_bytes(), tree.write_full_bytes());
    // .bt keeps only free / occupied: each leaf comes back at the clamping bound of
    // its side of the threshold.
    let bt = tree.write_binary_bytes();
    let back = OcTree::read_binary_bytes(&bt, Default::default()).unwrap();
    let (lo, hi) = tree.clamping_log_odds();
    let want: Vec<_> = leaves(&tree)
        .into_iter()
        .map(|(k, d, l)| (k, d, if tree.is_occupied_log_odds(l) { hi } else { lo }))
        .collect();
    assert!(want.iter().any(|l| l.2 == hi) && want.iter().any(|l| l.2 == lo));
    assert_eq!(leaves(&back), want);
    assert_eq!(back.write_binary_bytes(), bt);
}
