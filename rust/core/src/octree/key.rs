//! Cell keys laid out exactly as OctoMap's `OcTreeKey` (16 bits per axis, depth 16).
//!
//! OctoMap stores coordinates as `float` (`point3d`) but keys and resolutions as
//! `double`; the conversions below keep those precisions so that a point lands in
//! the same cell here as in OctoMap, bit for bit.

/// Tree depth; OctoMap's `OcTree` is fixed at 16 levels.
pub const TREE_DEPTH: u32 = 16;
/// Key of the cell whose lower corner is the origin (OctoMap's `tree_max_val`).
pub const TREE_MAX_VAL: i32 = 32768;

/// Smallest resolution a map takes, in metres. Points are float32 (OctoMap's
/// `point3d`) and a ray's length is a float32 sum of squares (`Vector3::norm`), so a
/// one-cell ray's squared length, `resolution²`, must be a normal float32 (≥ 2^-126,
/// i.e. resolution ≥ 1.1e-19) or short rays lose their cells; 1e-18 keeps two
/// decades of margin.
pub const MIN_RESOLUTION: f64 = 1e-18;
/// Largest resolution a map takes, in metres: the map's diagonal,
/// 2·32768·√3·resolution, squared in float32 must stay finite (< 3.4e38, i.e.
/// resolution < 1.6e14), or long rays get infinite lengths.
pub const MAX_RESOLUTION: f64 = 1e14;

/// Check a map resolution: a finite number of metres in
/// [[`MIN_RESOLUTION`], [`MAX_RESOLUTION`]].
pub fn check_resolution(resolution: f64) -> crate::Result<()> {
    if resolution.is_finite() && (MIN_RESOLUTION..=MAX_RESOLUTION).contains(&resolution) {
        return Ok(());
    }
    let why = if !(resolution.is_finite() && resolution > 0.0) {
        "must be a positive number of metres"
    } else {
        "is outside what 16-bit keys and float32 points can represent"
    };
    Err(crate::Error::InvalidArgument(format!(
        "resolution {why}: it must lie in [{MIN_RESOLUTION:e}, {MAX_RESOLUTION:e}] m, got {}",
        crate::geometry::fmt_num(resolution)
    )))
}

/// A cell at the finest depth: one 16-bit index per axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Default)]
pub struct OcTreeKey(pub [u16; 3]);

impl OcTreeKey {
    /// Morton code with x in the lowest bit: three bits per level give the child index
    /// at that level, so sorting by Morton code sorts cells depth-first as in the tree.
    #[inline]
    pub fn morton(self) -> u64 {
        spread(self.0[0]) | (spread(self.0[1]) << 1) | (spread(self.0[2]) << 2)
    }

    /// The key whose Morton code is `code` (the inverse of [`morton`](Self::morton)).
    #[inline]
    pub fn from_morton(code: u64) -> Self {
        OcTreeKey([compact(code), compact(code >> 1), compact(code >> 2)])
    }

    /// Index (0..8) of the child holding this key below a node whose children sit at
    /// key bit `level` (OctoMap's `computeChildIdx`: x adds 1, y adds 2, z adds 4).
    #[inline]
    pub fn child_index(self, level: u32) -> usize {
        let bit = |k: u16| ((k >> level) & 1) as usize;
        bit(self.0[0]) | (bit(self.0[1]) << 1) | (bit(self.0[2]) << 2)
    }

    /// The key of the node at `depth` that contains this key (OctoMap's `adjustKeyAtDepth`).
    #[inline]
    pub fn at_depth(self, depth: u32) -> Self {
        if depth >= TREE_DEPTH {
            return self;
        }
        let diff = TREE_DEPTH - depth;
        let adjust = |k: u16| -> u16 {
            let k = k as i32;
            (((k - TREE_MAX_VAL) >> diff << diff) + (1 << (diff - 1)) + TREE_MAX_VAL) as u16
        };
        OcTreeKey([adjust(self.0[0]), adjust(self.0[1]), adjust(self.0[2])])
    }
}

/// Split items sorted by Morton code (the `u64` of each pair) into the runs that fall
/// into the same child of a node at `depth`: yields (child index, run). Batch updates
/// walk the tree once this way instead of once per cell.
pub(crate) fn child_runs<T>(
    items: &[(u64, T)],
    depth: u32,
) -> impl Iterator<Item = (usize, &[(u64, T)])> {
    let shift = 3 * (TREE_DEPTH - 1 - depth);
    let mut rest = items;
    std::iter::from_fn(move || {
        let &(first, _) = rest.first()?;
        let pos = ((first >> shift) & 7) as usize;
        let same = |&(m, _): &(u64, T)| ((m >> shift) & 7) as usize == pos;
        // Gallop, then bisect what is left: runs are short deep in the tree, where
        // most nodes are, and a search from both ends mispredicts a branch per step.
        let mut reach = 1;
        while reach < rest.len() && same(&rest[reach]) {
            reach *= 2;
        }
        let known = reach / 2 + 1; // rest[..known] is in the run
        let end = known + rest[known.min(rest.len())..reach.min(rest.len())].partition_point(same);
        let (run, tail) = rest.split_at(end);
        rest = tail;
        Some((pos, run))
    })
}

/// Spread the 16 bits of `v` so that bit i lands on bit 3i: two table lookups (a
/// third of the instructions of the shift-and-mask cascade).
#[inline]
fn spread(v: u16) -> u64 {
    SPREAD_BYTE[usize::from(v & 255)] | (SPREAD_BYTE[usize::from(v >> 8)] << 24)
}

/// Every byte spread so that bit i lands on bit 3i.
static SPREAD_BYTE: [u64; 256] = {
    let mut table = [0u64; 256];
    let mut v = 0;
    while v < 256 {
        let mut bit = 0;
        while bit < 8 {
            table[v] |= ((v as u64 >> bit) & 1) << (3 * bit);
            bit += 1;
        }
        v += 1;
    }
    table
};

#[inline]
fn compact(code: u64) -> u16 {
    let mut x = code & 0x2492_4924_9249;
    x = (x | (x >> 2)) & 0x0c30_c30c_30c3;
    x = (x | (x >> 4)) & 0x00f0_0f00_f00f;
    x = (x | (x >> 8)) & 0x0000_ff00_00ff;
    x = (x | (x >> 16)) & 0xffff;
    x as u16
}

/// Whether a coordinate in cells (`coordinate / resolution`) has a key. The bounds are
/// whole numbers, so testing before the floor is the same test; NaN fails both
/// comparisons. Written without short-circuit so batches of it vectorise.
#[inline(always)]
fn in_key_range(scaled: f64) -> bool {
    (scaled >= -(TREE_MAX_VAL as f64)) & (scaled < TREE_MAX_VAL as f64)
}

/// The key of a coordinate in cells that `in_key_range` accepts: a floor in 32 bits
/// (|scaled| ≤ 2^15 there), which vectorises.
#[inline(always)]
fn key_in_range(scaled: f64) -> u16 {
    // Clamped (a NaN to the low end) so that the truncation below is defined for any
    // input; within the key range it changes nothing.
    let clamped = scaled.max(-(TREE_MAX_VAL as f64)).min(TREE_MAX_VAL as f64);
    // SAFETY: `clamped` is finite and within ±2^15, so its truncation fits an i32.
    // (A checked `as` cast here keeps insertion's key pass from vectorising.)
    let toward_zero: i32 = unsafe { clamped.to_int_unchecked() };
    let floor = toward_zero - i32::from(toward_zero as f64 > clamped);
    (floor + TREE_MAX_VAL) as u16
}

/// Conversions between metric coordinates and keys for one resolution.
#[derive(Clone, Copy, Debug)]
pub struct KeyConverter {
    resolution: f64,
    resolution_factor: f64,
}

impl KeyConverter {
    /// `resolution` must be finite and positive (checked by the caller).
    pub fn new(resolution: f64) -> Self {
        KeyConverter {
            resolution,
            resolution_factor: 1.0 / resolution,
        }
    }

    /// Edge length of a finest cell, in metres.
    #[inline]
    pub fn resolution(&self) -> f64 {
        self.resolution
    }

    /// Edge length of a node at `depth` (0 = root, 16 = finest cell).
    #[inline]
    pub fn node_size(&self, depth: u32) -> f64 {
        self.resolution * f64::from(1u32 << (TREE_DEPTH - depth.min(TREE_DEPTH)))
    }

    /// One axis, without bounds check; out-of-range values saturate.
    #[inline]
    pub fn coord_to_key_axis(&self, coordinate: f64) -> i64 {
        (self.resolution_factor * coordinate).floor() as i64 + TREE_MAX_VAL as i64
    }

    /// The key of a metric point, or an error naming it (`what`) when it is not
    /// finite or off the map.
    pub fn checked_key(&self, what: &'static str, p: [f64; 3]) -> crate::error::Result<OcTreeKey> {
        if !p.iter().all(|c| c.is_finite()) {
            return Err(crate::error::Error::InvalidArgument(format!(
                "{what} {} is not finite",
                crate::geometry::fmt_point(&p)
            )));
        }
        self.coord_to_key_checked_f64(p)
            .ok_or_else(|| self.out_of_bounds(what, p))
    }

    /// The error for `point` (named `what`) off the map.
    pub fn out_of_bounds(&self, what: &'static str, point: [f64; 3]) -> crate::error::Error {
        crate::error::Error::OutOfBounds {
            what,
            point,
            limit: self.metric_limits().1,
        }
    }

    /// OctoMap's `coordToKeyChecked` for one axis.
    #[inline]
    pub fn coord_to_key_axis_checked(&self, coordinate: f64) -> Option<u16> {
        let scaled = self.resolution_factor * coordinate;
        in_key_range(scaled).then(|| key_in_range(scaled))
    }

    /// The key of the cell holding a point given as OctoMap's `point3d` (float).
    #[inline]
    pub fn coord_to_key_checked(&self, p: [f32; 3]) -> Option<OcTreeKey> {
        Some(OcTreeKey([
            self.coord_to_key_axis_checked(p[0] as f64)?,
            self.coord_to_key_axis_checked(p[1] as f64)?,
            self.coord_to_key_axis_checked(p[2] as f64)?,
        ]))
    }

    /// Whether a float point has a key (`coord_to_key_checked` is `Some`), without
    /// branches, so that a pass over many points vectorises.
    #[inline(always)]
    pub fn has_key(&self, p: [f32; 3]) -> bool {
        let f = self.resolution_factor;
        in_key_range(f * f64::from(p[0]))
            & in_key_range(f * f64::from(p[1]))
            & in_key_range(f * f64::from(p[2]))
    }

    /// The key of a point that has one (`has_key` is true), without the checks, so that
    /// a pass over many points vectorises; equal to `coord_to_key_checked` there.
    #[inline(always)]
    pub fn key_of_checked_point(&self, p: [f32; 3]) -> OcTreeKey {
        let f = self.resolution_factor;
        OcTreeKey(p.map(|c| key_in_range(f * f64::from(c))))
    }

    /// Same, for double-precision coordinates (queries).
    #[inline]
    pub fn coord_to_key_checked_f64(&self, p: [f64; 3]) -> Option<OcTreeKey> {
        Some(OcTreeKey([
            self.coord_to_key_axis_checked(p[0])?,
            self.coord_to_key_axis_checked(p[1])?,
            self.coord_to_key_axis_checked(p[2])?,
        ]))
    }

    /// `(Morton code of the key, index)` of every point, or the index of the first
    /// point without a key (outside the map, or not finite). Same keys as
    /// `coord_to_key_checked_f64`, in two branch-free passes that vectorise: the bounds
    /// of all points first, then keys by a 32-bit floor (in bounds, |scaled| ≤ 2^15).
    pub fn morton_keyed(&self, points: &[[f64; 3]]) -> std::result::Result<Vec<(u64, u32)>, usize> {
        let factor = self.resolution_factor;
        let inside = |c: f64| in_key_range(factor * c);
        let all_inside = points.iter().fold(true, |all, p| {
            all & inside(p[0]) & inside(p[1]) & inside(p[2])
        });
        if !all_inside {
            let bad = points.iter().position(|p| !p.iter().all(|&c| inside(c)));
            return Err(bad.unwrap_or(0));
        }
        Ok(points
            .iter()
            .enumerate()
            .map(|(i, p)| {
                (
                    OcTreeKey(p.map(|c| key_in_range(factor * c))).morton(),
                    i as u32,
                )
            })
            .collect())
    }

    /// Centre of the finest cell along one axis (OctoMap's `keyToCoord(key_type)`).
    #[inline]
    pub fn key_to_coord_axis(&self, key: u16) -> f64 {
        (f64::from(i32::from(key) - TREE_MAX_VAL) + 0.5) * self.resolution
    }

    /// Centre of the node at `depth` holding `key` along one axis.
    #[inline]
    pub fn key_to_coord_axis_at_depth(&self, key: u16, depth: u32) -> f64 {
        if depth == 0 {
            // The root is centred on the origin (OctoMap's keyToCoord at depth 0).
            return 0.0;
        }
        if depth >= TREE_DEPTH {
            return self.key_to_coord_axis(key);
        }
        let span = f64::from(1u32 << (TREE_DEPTH - depth));
        (((f64::from(key) - f64::from(TREE_MAX_VAL)) / span).floor() + 0.5) * self.node_size(depth)
    }

    /// Centre of the finest cell as OctoMap's `point3d` (float).
    #[inline]
    pub fn key_to_point(&self, key: OcTreeKey) -> [f32; 3] {
        [
            self.key_to_coord_axis(key.0[0]) as f32,
            self.key_to_coord_axis(key.0[1]) as f32,
            self.key_to_coord_axis(key.0[2]) as f32,
        ]
    }

    /// Centre of the node at `depth` holding `key`, in double precision.
    #[inline]
    pub fn key_to_coord_at_depth(&self, key: OcTreeKey, depth: u32) -> [f64; 3] {
        [
            self.key_to_coord_axis_at_depth(key.0[0], depth),
            self.key_to_coord_axis_at_depth(key.0[1], depth),
            self.key_to_coord_axis_at_depth(key.0[2], depth),
        ]
    }

    /// Smallest and largest coordinate that still maps to a key.
    pub fn metric_limits(&self) -> (f64, f64) {
        (
            -(TREE_MAX_VAL as f64) * self.resolution,
            TREE_MAX_VAL as f64 * self.resolution,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::super::ray::compute_ray_keys;
    use super::*;

    #[test]
    fn child_runs_are_the_groups_of_equal_child_index() {
        let mut rng = crate::synthetic::Rng::new(4);
        for n in [1, 2, 3, 5, 17, 100, 1000] {
            for spread in [2u64, 8, 64, 1 << 20] {
                // Codes under one node at depth 14 (the top bits shared), sorted.
                let mut items: Vec<(u64, u32)> = (0..n)
                    .map(|i| ((rng.unit() * spread as f64) as u64 % 64, i))
                    .collect();
                items.sort_unstable();
                let runs: Vec<(usize, Vec<(u64, u32)>)> = child_runs(&items, 14)
                    .map(|(pos, run)| (pos, run.to_vec()))
                    .collect();
                let mut want: Vec<(usize, Vec<(u64, u32)>)> = Vec::new();
                for &item in &items {
                    let pos = ((item.0 >> 3) & 7) as usize;
                    match want.last_mut() {
                        Some((p, run)) if *p == pos => run.push(item),
                        _ => want.push((pos, vec![item])),
                    }
                }
                assert_eq!(runs, want, "{n} items spread over {spread}");
            }
        }
    }

    #[test]
    fn spread_puts_bit_i_on_bit_3i() {
        for v in 0..=u16::MAX {
            let want = (0..16).fold(0u64, |acc, i| acc | (u64::from((v >> i) & 1) << (3 * i)));
            assert_eq!(spread(v), want);
            assert_eq!(compact(want), v);
        }
    }

    #[test]
    fn morton_round_trips_and_orders_children() {
        let k = OcTreeKey([0xabcd, 0x1234, 0xfe01]);
        assert_eq!(OcTreeKey::from_morton(k.morton()), k);
        for level in 0..16 {
            assert_eq!(
                ((k.morton() >> (3 * level)) & 7) as usize,
                k.child_index(level)
            );
        }
    }

    #[test]
    fn origin_cells_straddle_zero() {
        let c = KeyConverter::new(0.05);
        assert_eq!(c.coord_to_key_axis_checked(0.0), Some(32768));
        assert_eq!(c.coord_to_key_axis_checked(-1e-9), Some(32767));
        assert!((c.key_to_coord_axis(32768) - 0.025).abs() < 1e-12);
        assert_eq!(c.coord_to_key_axis_checked(f64::NAN), None);
        assert_eq!(c.coord_to_key_axis_checked(1638.39), Some(65535));
        assert_eq!(c.coord_to_key_axis_checked(1638.4), None);
        assert_eq!(c.coord_to_key_axis_checked(-1638.4), Some(0));
    }

    #[test]
    fn batched_morton_keys_equal_single_keys() {
        let c = KeyConverter::new(0.05);
        let mut rng = crate::synthetic::Rng::new(5);
        // Cell borders (and the floats just beside them), the map's edges, random points.
        let mut values = vec![0.0, -0.0, 1638.35, -1638.4, 1e-300, -1e-300];
        for k in -40..40 {
            let border = f64::from(k) * 0.05;
            values.extend([border, border.next_up(), border.next_down()]);
        }
        values.extend((0..300).map(|_| rng.uniform(-1638.4, 1638.4)));
        // Every value on every axis, beside others and beside zeros.
        let n = values.len();
        let points: Vec<[f64; 3]> = (0..n)
            .map(|i| [values[i], values[(i + 1) % n], values[(i + 2) % n]])
            .chain((0..n).flat_map(|i| {
                [0, 1, 2].map(|a| {
                    let mut p = [0.0; 3];
                    p[a] = values[i];
                    p
                })
            }))
            .collect();
        let keyed = c.morton_keyed(&points).unwrap();
        for (i, (p, (code, index))) in points.iter().zip(keyed).enumerate() {
            assert_eq!(index as usize, i);
            // The reference: the standard library's floor.
            let key = p.map(|x| ((c.resolution_factor * x).floor() + 32768.0) as u16);
            assert_eq!(code, OcTreeKey(key).morton(), "{p:?}");
            assert_eq!(
                Some(OcTreeKey(key)),
                c.coord_to_key_checked_f64(*p),
                "{p:?}"
            );
            // Insertion's keys, of the point as OctoMap's float point.
            let p32 = p.map(|x| x as f32);
            if c.has_key(p32) {
                let key32 =
                    p32.map(|x| ((c.resolution_factor * f64::from(x)).floor() + 32768.0) as u16);
                assert_eq!(c.key_of_checked_point(p32), OcTreeKey(key32), "{p:?}");
            }
        }
        // Defined for points without a key too (its truncation is clamped), if meaningless.
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 1e30, -1e30] {
            assert!(!c.has_key([bad, 0.0, 0.0]));
            let _ = c.key_of_checked_point([bad, bad, 0.0]);
        }
        // The first point without a key is named: beyond the edge, NaN, infinite.
        for bad in [1638.4, f64::NAN, f64::NEG_INFINITY, -1638.41] {
            let mut with_bad = points.clone();
            with_bad[7][2] = bad;
            with_bad[9][0] = bad;
            assert_eq!(c.morton_keyed(&with_bad), Err(7), "{bad}");
        }
    }

    /// Leaves and ray ends of one scan at `resolution`, its coordinates given in cells
    /// (`scene` scales them by the resolution).
    type Scan = (Vec<(OcTreeKey, u32, f32)>, Vec<(bool, [f64; 3])>);
    fn scan_at(resolution: f64, cells: &[[f64; 3]], origin: [f64; 3]) -> Scan {
        let scale = |p: &[f64; 3]| p.map(|c| c * resolution);
        let points: Vec<[f64; 3]> = cells.iter().map(scale).collect();
        let mut tree = crate::OcTree::new(resolution).unwrap();
        tree.insert_point_cloud(&points, scale(&origin), None, false)
            .unwrap();
        let mut leaves = Vec::new();
        tree.for_each_leaf(|l| leaves.push((l.key, l.depth, l.log_odds)));
        // Rays cast back along the scan's directions, ends in cells.
        let rays = cells
            .iter()
            .take(50)
            .map(|p| {
                let d = [p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]];
                let hit = tree.cast_ray(scale(&origin), d, None, true).unwrap();
                (hit.hit, hit.end.map(|c| c / resolution))
            })
            .collect();
        (leaves, rays)
    }

    #[test]
    fn scans_are_the_same_at_every_resolution_in_the_range() {
        // Scaling by a power of two is exact in float and double, so a scene in cells
        // gives the same keys and values at every resolution the key arithmetic can
        // represent: long rays across most of the map and rays of a cell or two.
        let mut rng = crate::synthetic::Rng::new(7);
        let mut cells: Vec<[f64; 3]> = (0..60)
            .map(|_| [0; 3].map(|_: i32| rng.uniform(-32000.0, 32000.0)))
            .collect();
        cells.extend((0..200).map(|_| [0; 3].map(|_: i32| rng.uniform(-3.0, 3.0))));
        let origin = [0.3, -0.6, 0.45];
        let reference = scan_at(1.0, &cells, origin);
        assert!(reference.0.len() > 100_000, "{}", reference.0.len());
        let (lo, hi) = (MIN_RESOLUTION.log2().ceil(), MAX_RESOLUTION.log2().floor());
        for exponent in [lo, lo + 1.0, -30.0, -7.0, 20.0, hi - 1.0, hi] {
            let res = exponent.exp2();
            assert!(check_resolution(res).is_ok());
            assert!(
                scan_at(res, &cells, origin) == reference,
                "resolution 2^{exponent}"
            );
        }
        // Beyond the range the float32 arithmetic breaks down, which is why it ends
        // where it does: above, the map's diagonal has an infinite float length (its
        // walk never ends: at 2^48 it ran until memory ran out); far below, a ray of
        // a few cells loses cells.
        let diagonal = |res: f64| {
            let corner = (32767.5 * res) as f32;
            super::super::ray::norm([2.0 * corner; 3])
        };
        assert!(diagonal(MAX_RESOLUTION).is_finite());
        assert!(diagonal(f64::exp2(48.0)).is_infinite());
        let ray_keys = |res: f64| {
            let f = |p: [f64; 3]| p.map(|c| (c * res) as f32);
            let mut keys = Vec::new();
            compute_ray_keys(
                &KeyConverter::new(res),
                f([0.5, 0.5, 0.5]),
                f([3.5, 2.5, 0.5]),
                |k| keys.push(k),
            );
            keys
        };
        assert_eq!(ray_keys(MIN_RESOLUTION), ray_keys(1.0));
        assert_ne!(ray_keys(f64::exp2(-80.0)), ray_keys(1.0));
    }

    #[test]
    fn resolutions_outside_the_range_are_refused_with_the_range() {
        for res in [
            1e-100,
            1e-19,
            2e14,
            1e308,
            0.0,
            -1.0,
            f64::NAN,
            f64::INFINITY,
        ] {
            let msg = check_resolution(res).unwrap_err().to_string();
            assert!(msg.contains("[1e-18, 1e14]"), "{msg}");
            assert!(msg.len() < 160, "{msg}");
        }
    }

    #[test]
    fn depth_centres_are_node_centres() {
        let c = KeyConverter::new(0.1);
        let key = OcTreeKey([32768, 32768, 32768]);
        // The node at depth 15 holding the first positive cell spans [0, 0.2).
        assert!((c.key_to_coord_axis_at_depth(key.0[0], 15) - 0.1).abs() < 1e-12);
        assert_eq!(key.at_depth(15).0[0], 32769);
        // The root spans the whole map, [-3276.8, 3276.8), whatever key is asked for;
        // its two children are centred at ±1638.4.
        for k in [0u16, 1, 32767, 32768, 65535] {
            assert_eq!(c.key_to_coord_axis_at_depth(k, 0), 0.0);
            let child = if k < 32768 { -1638.4 } else { 1638.4 };
            assert!((c.key_to_coord_axis_at_depth(k, 1) - child).abs() < 1e-9);
        }
    }
}
