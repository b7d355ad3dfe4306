//! `SurfaceMap`: NOctoSLAM's octree (IROS 2017). Every node keeps an occupancy, a
//! position that may leave its voxel centre, and a surface normal, so that
//! point-to-plane ICP finds its reference point and normal in one descent, with no
//! k-d tree and no separate normal estimation.
//!
//! Update = insertion, then propagation (digest §D):
//! 1. each end point goes to its leaf and is blended with the stored position,
//!    `n ← (n·p_occ + d·M) / (p_occ + M)` (occupancy probability p_occ before the hit,
//!    sensor model M = prob_hit);
//! 2. every inner node above a touched leaf is recomputed bottom-up from its direct
//!    children: mean position (Eq. 3); normal from the PCA of the children's positions
//!    (Eq. 4) when exactly two eigenvalues are similar (a plane), else the mean of the
//!    children's normals, else none. Untouched branches are not visited, so an
//!    update's cost does not grow with the map.
//!
//! Dynamic leaf depth (the paper's Fig. 3, for sparse multi-line lidar): a point may
//! end in a leaf above the finest level, sized to the gap between neighbouring scan
//! lines at its range, so that leaves of neighbouring lines touch and a leaf averages
//! many points. A leaf is any node without children; an existing coarse leaf absorbs
//! finer points (it is never split), and a coarse point reaching an inner node goes on
//! into the existing finer branch.

use super::arena::{NodeArena, NONE};
use super::key::{child_runs, KeyConverter, OcTreeKey, TREE_DEPTH};
use super::occupancy::{logodds, probability};
use crate::error::{Error, Result};
use crate::geometry::{fmt_num, fmt_point};
use crate::na::{Matrix3, Vector3};

/// One node of the surface map.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SurfaceNode {
    /// Occupancy in log-odds.
    pub log_odds: f32,
    /// Position of the surface in this node (metres, map frame); may leave the voxel.
    pub position: [f32; 3],
    /// Unit normal; meaningful only when `has_normal`.
    pub normal: [f32; 3],
    /// Whether `normal` holds a normal.
    pub has_normal: bool,
    /// End points blended into this leaf (saturating; used by `position_memory`).
    pub hits: u16,
}

/// The surface map's sensor model and normal rules (NOctoSLAM).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceParams {
    /// Sensor model M: probability that a hit is real (OctoMap's prob_hit).
    pub prob_hit: f64,
    /// Upper clamping bound of the occupancy.
    pub clamping_max: f64,
    /// Two eigenvalues λ_a ≤ λ_b are "similar" when λ_a ≥ similar · λ_b.
    pub similar: f64,
    /// `None`: the paper's blend (a new point weighs M / (p_occ + M), ~0.42 once the
    /// leaf is certain, so a leaf follows its latest points). `Some(k)`: a leaf holds
    /// the mean of its first k points and then a moving average over k, so a map built
    /// while the sensor pose drifts keeps what it saw first (SLAM's anchor).
    pub position_memory: Option<u16>,
}

impl Default for SurfaceParams {
    fn default() -> Self {
        SurfaceParams {
            prob_hit: 0.7,
            clamping_max: 0.971,
            similar: 0.25,
            position_memory: None,
        }
    }
}

/// NOctoSLAM's octree: per node an occupancy, a surface position and a normal.
/// See the module documentation for the update rules.
///
/// ```
/// use earcore_core::octree::{SurfaceMap, SurfaceParams};
///
/// // A floor patch: points on z = 0 every 2 cm.
/// let floor: Vec<[f64; 3]> = (0..400)
///     .map(|i| [0.02 * (i % 20) as f64, 0.02 * (i / 20) as f64, 0.0])
///     .collect();
/// let mut map = SurfaceMap::new(0.05, SurfaceParams::default())?;
/// assert!(map.insert(&floor)? > 0);
/// // A point just above the floor pairs with the surface and its vertical normal.
/// let (position, normal, _depth) = map.associate([0.2, 0.2, 0.01]).unwrap();
/// assert!(position[2].abs() < 1e-6);
/// assert!(normal[2].abs() > 0.99);
/// # Ok::<(), earcore_core::Error>(())
/// ```
#[derive(Clone, Debug)]
pub struct SurfaceMap {
    conv: KeyConverter,
    params: SurfaceParams,
    hit: f32,
    clamp_max: f32,
    arena: NodeArena<SurfaceNode>,
    root: u32,
}

/// A node as reported by queries.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceSample {
    /// Key of the node's lower corner (its finest cell with the smallest key).
    pub key: OcTreeKey,
    /// Depth of the node (0 = root, 16 = finest).
    pub depth: u32,
    /// Without children (with dynamic leaf depth, leaves lie above depth 16 too).
    pub leaf: bool,
    /// The node's values.
    pub node: SurfaceNode,
}

impl SurfaceMap {
    /// An empty map with finest cells of `resolution` metres. Errors when `resolution`
    /// is outside [[`MIN_RESOLUTION`](crate::octree::MIN_RESOLUTION),
    /// [`MAX_RESOLUTION`](crate::octree::MAX_RESOLUTION)] or a parameter is out of range
    /// (probabilities in (0, 1), `prob_hit` ≤ `clamping_max`, `position_memory` not
    /// `Some(0)`).
    pub fn new(resolution: f64, params: SurfaceParams) -> Result<Self> {
        super::key::check_resolution(resolution)?;
        let ok = |p: f64| p.is_finite() && p > 0.0 && p < 1.0;
        for (name, value) in [
            ("prob_hit", params.prob_hit),
            ("clamping_max", params.clamping_max),
            ("similar", params.similar),
        ] {
            if !ok(value) {
                return Err(Error::InvalidArgument(format!(
                    "{name} must lie strictly between 0 and 1, got {}",
                    fmt_num(value)
                )));
            }
        }
        if params.prob_hit > params.clamping_max {
            return Err(Error::InvalidArgument(format!(
                "prob_hit ({}) must not exceed clamping_max ({})",
                fmt_num(params.prob_hit),
                fmt_num(params.clamping_max)
            )));
        }
        if params.position_memory == Some(0) {
            return Err(Error::InvalidArgument(
                "position_memory must be at least 1 point (or None for the paper's blend)".into(),
            ));
        }
        Ok(SurfaceMap {
            conv: KeyConverter::new(resolution),
            hit: logodds(params.prob_hit),
            clamp_max: logodds(params.clamping_max),
            params,
            arena: NodeArena::new(),
            root: NONE,
        })
    }

    /// Edge length of a finest cell, in metres.
    pub fn resolution(&self) -> f64 {
        self.conv.resolution()
    }

    /// Conversions between metric points and this map's keys.
    pub fn key_converter(&self) -> &KeyConverter {
        &self.conv
    }

    /// Number of nodes.
    pub fn size(&self) -> usize {
        self.arena.len()
    }

    /// Bytes held by the map, spare capacity included.
    pub fn memory_usage(&self) -> usize {
        std::mem::size_of::<Self>() + self.arena.memory_usage()
    }

    /// Insert end points (map frame, metres) into leaves at the finest level and
    /// propagate; returns the number of distinct leaves touched. The input is checked
    /// before the map changes.
    pub fn insert(&mut self, points: &[[f64; 3]]) -> Result<usize> {
        self.insert_at_depths(points, None)
    }

    /// Dynamic leaf depth: the depth (≤ 16) of the smallest node at least as large as
    /// the gap `range · beam_spacing` between neighbouring scan lines at each point's
    /// range from `origin`, no coarser than `max_leaf_size` metres.
    pub fn leaf_depths(
        &self,
        points: &[[f64; 3]],
        origin: [f64; 3],
        beam_spacing: f64,
        max_leaf_size: f64,
    ) -> Result<Vec<u8>> {
        if !(beam_spacing.is_finite() && beam_spacing > 0.0 && beam_spacing < 1.0) {
            return Err(Error::InvalidArgument(format!(
                "beam_spacing must be an angle in radians in (0, 1), got {}",
                fmt_num(beam_spacing)
            )));
        }
        if !origin.iter().all(|c| c.is_finite()) {
            return Err(Error::InvalidArgument(format!(
                "sensor_origin {} is not finite",
                fmt_point(&origin)
            )));
        }
        if !(max_leaf_size.is_finite() && max_leaf_size > 0.0) {
            return Err(Error::InvalidArgument(format!(
                "max_leaf_size must be a positive number of metres, got {}",
                fmt_num(max_leaf_size)
            )));
        }
        let res = self.resolution();
        let coarsest = (max_leaf_size / res).log2().floor().clamp(0.0, 15.0) as i32;
        // A point needs L levels above the finest when its gap r·b exceeds 2^(L−1) cells:
        // L = #{l ≥ 0 : 4^l < x} for the squared gap in cells x = r²·(b/res)², read off
        // x's binary exponent e (2l < e, or 2l = e with a mantissa above 1): no root, log
        // or search per point, and the loop vectorises.
        let scale = (beam_spacing / res).powi(2);
        Ok(points
            .iter()
            .map(|p| {
                let range2 = (p[0] - origin[0]).powi(2)
                    + (p[1] - origin[1]).powi(2)
                    + (p[2] - origin[2]).powi(2);
                let bits = (range2 * scale).to_bits();
                let e = ((bits >> 52) & 0x7ff) as i32 - 1023;
                let above = bits & ((1 << 52) - 1) != 0;
                let even_above = i32::from((e >= 0) & (e % 2 == 0) & above);
                let levels = ((e.max(-1) + 1) / 2 + even_above).min(coarsest);
                (TREE_DEPTH as i32 - levels) as u8
            })
            .collect())
    }

    /// `insert` with a leaf depth per point (`leaf_depths`; `None`: all at 16).
    pub fn insert_at_depths(
        &mut self,
        points: &[[f64; 3]],
        depths: Option<&[u8]>,
    ) -> Result<usize> {
        if let Some(d) = depths {
            if d.len() != points.len() {
                return Err(Error::InvalidArgument(format!(
                    "one leaf depth per point expected ({} points, {} depths)",
                    points.len(),
                    d.len()
                )));
            }
            // One pass without an early exit vectorises; the search runs only on failure.
            let outside = |x: u8| x == 0 || u32::from(x) > TREE_DEPTH;
            if d.iter().fold(false, |any, &x| any | outside(x)) {
                let bad = d.iter().find(|&&x| outside(x)).copied().unwrap_or(0);
                return Err(Error::InvalidArgument(format!(
                    "leaf depths must lie in 1..=16, got {bad}"
                )));
            }
        }
        let mut items = self.conv.morton_keyed(points).map_err(|i| {
            let p = points[i];
            // NaN has no key either: say which it is.
            if !p.iter().all(|c| c.is_finite()) {
                Error::InvalidArgument(format!("point {i} {} is not finite", fmt_point(&p)))
            } else {
                Error::OutOfBounds {
                    what: "a point",
                    point: p,
                    limit: self.conv.metric_limits().1,
                }
            }
        })?;
        if items.is_empty() {
            return Ok(0);
        }
        // Input order within a leaf: points blend in input order.
        crate::geometry::sort_keyed(&mut items);
        if self.root == NONE {
            self.root = self.arena.alloc(SurfaceNode::default());
        }
        let mut touched = 0;
        // With the shallowest leaf depth known, nodes above it skip the scan of their items.
        let depths = depths.map(|d| (d, u32::from(d.iter().copied().min().unwrap_or(16))));
        self.insert_recursive(self.root, 0, &items, points, depths, &mut touched);
        self.arena.trim_spare();
        Ok(touched)
    }

    /// Whether `items` end in `node` (at `depth`): the finest level, an existing leaf
    /// (a node without children that holds a position), or a new node at or below the
    /// leaf depth one of the items asks for (all of a node's points end together, so
    /// no position is lost to propagation).
    fn ends_here(
        &self,
        node: u32,
        depth: u32,
        items: &[(u64, u32)],
        depths: Option<(&[u8], u32)>,
    ) -> bool {
        if depth == TREE_DEPTH {
            return true;
        }
        if self.arena.has_children(node) {
            return false;
        }
        self.arena.value(node).log_odds != 0.0
            || depths.is_some_and(|(d, shallowest)| {
                depth >= shallowest
                    && items
                        .iter()
                        .any(|&(_, i)| u32::from(d[i as usize]) <= depth)
            })
    }

    fn insert_recursive(
        &mut self,
        node: u32,
        depth: u32,
        items: &[(u64, u32)],
        points: &[[f64; 3]],
        depths: Option<(&[u8], u32)>,
        touched: &mut usize,
    ) {
        if self.ends_here(node, depth, items, depths) {
            *touched += 1;
            let mut n = self.arena.value(node);
            let m = self.params.prob_hit;
            // Blended in double precision and stored once: the weights do not depend on
            // the position, so only the blend itself is a chain from point to point.
            let mut position = n.position.map(f64::from);
            for &(_, i) in items {
                let d = points[i as usize];
                // Hits only raise the log-odds: zero means this leaf has no position yet.
                if n.log_odds == 0.0 {
                    position = d;
                } else {
                    // Weights of the stored position and of the new point.
                    let (w_old, w_new) = match self.params.position_memory {
                        None => (probability(n.log_odds), m),
                        Some(k) => (f64::from(n.hits.min(k)), 1.0),
                    };
                    // (stored·w_old + new·w_new) / (w_old + w_new), one division per point.
                    let share = w_new / (w_old + w_new);
                    for (stored, new) in position.iter_mut().zip(d) {
                        *stored += (new - *stored) * share;
                    }
                }
                n.hits = n.hits.saturating_add(1);
                n.log_odds = (n.log_odds + self.hit).min(self.clamp_max);
            }
            n.position = position.map(|c| c as f32);
            self.arena.set_value(node, n);
            return;
        }
        for (pos, group) in child_runs(items, depth) {
            let child = match self.arena.child(node, pos) {
                Some(c) => c,
                None => self.arena.create_child(node, pos, SurfaceNode::default()),
            };
            self.insert_recursive(child, depth + 1, group, points, depths, touched);
        }
        self.propagate(node);
    }

    /// Recompute an inner node from its direct children (Eqs. 3-4).
    fn propagate(&mut self, node: u32) {
        // At most eight children: gather them on the stack (this runs per touched node).
        let mut buffer = [SurfaceNode::default(); 8];
        let mut count = 0;
        for c in self.arena.children(node) {
            if c != NONE {
                buffer[count] = self.arena.value(c);
                count += 1;
            }
        }
        let children = &buffer[..count];
        let k = children.len() as f64;
        let mean = children
            .iter()
            .fold(Vector3::zeros(), |acc, c| acc + pos(c))
            / k;
        let mut n = SurfaceNode {
            log_odds: children.iter().map(|c| c.log_odds).fold(f32::MIN, f32::max),
            position: [mean.x as f32, mean.y as f32, mean.z as f32],
            ..Default::default()
        };
        if let Some(normal) = self.plane_normal(children, mean) {
            n.normal = normal;
            n.has_normal = true;
        } else {
            let sum = children
                .iter()
                .filter(|c| c.has_normal)
                .fold(Vector3::zeros(), |acc, c| {
                    acc + Vector3::new(
                        f64::from(c.normal[0]),
                        f64::from(c.normal[1]),
                        f64::from(c.normal[2]),
                    )
                });
            if sum.norm() > 1e-9 {
                let u = sum.normalize();
                n.normal = [u.x as f32, u.y as f32, u.z as f32];
                n.has_normal = true;
            }
        }
        self.arena.set_value(node, n);
    }

    /// The PCA normal of the children's positions when they form a plane: the two
    /// largest eigenvalues similar, the smallest not similar to them.
    fn plane_normal(&self, children: &[SurfaceNode], mean: Vector3<f64>) -> Option<[f32; 3]> {
        if children.len() < 3 {
            return None;
        }
        let cov = children.iter().fold(Matrix3::zeros(), |acc, c| {
            let d = pos(c) - mean;
            acc + d * d.transpose()
        }) / children.len() as f64;
        // The test compares eigenvalues by ratio: the scaled matrix's serve, and its
        // eigenvector is the original's.
        let unit = crate::eigen3::UnitSymmetric3::new(&cov)?;
        let values = unit.eigenvalues();
        let [l0, l1, l2] = values.map(|l| l.max(0.0));
        let similar = |a: f64, b: f64| a >= self.params.similar * b;
        if l2 > 0.0 && similar(l1, l2) && !similar(l0, l1) {
            let v = unit.smallest_eigenvector(values[0]);
            Some([v.x as f32, v.y as f32, v.z as f32])
        } else {
            None
        }
    }

    /// Every node at `depth` (1..=16), or every node when `None`, depth first.
    pub fn for_each_node(&self, depth: Option<u32>, mut f: impl FnMut(SurfaceSample)) {
        if self.root == NONE {
            return;
        }
        let mut stack = vec![(self.root, 0u32, OcTreeKey([0, 0, 0]))];
        while let Some((n, d, base)) = stack.pop() {
            if depth.is_none_or(|want| want == d) {
                f(SurfaceSample {
                    key: base,
                    depth: d,
                    leaf: !self.arena.has_children(n),
                    node: self.arena.value(n),
                });
            }
            if d == TREE_DEPTH || depth.is_some_and(|want| d >= want) {
                continue;
            }
            let half = 1u16 << (TREE_DEPTH - 1 - d);
            for (pos, c) in self.arena.children(n).into_iter().enumerate().rev() {
                if c != NONE {
                    let mut k = base.0;
                    for (axis, bit) in [(0, 1), (1, 2), (2, 4)] {
                        if pos & bit != 0 {
                            k[axis] |= half;
                        }
                    }
                    stack.push((c, d + 1, OcTreeKey(k)));
                }
            }
        }
    }

    /// The node holding `key` at `depth` (16 = leaf), if it exists.
    pub fn search(&self, key: OcTreeKey, depth: u32) -> Option<SurfaceNode> {
        if self.root == NONE {
            return None;
        }
        let mut node = self.root;
        for d in 0..depth.min(TREE_DEPTH) {
            node = self
                .arena
                .child(node, key.child_index(TREE_DEPTH - 1 - d))?;
        }
        Some(self.arena.value(node))
    }

    /// NOctoSLAM's association for point-to-plane ICP: descend toward the leaf holding
    /// `p`; if that leaf exists and its parent has a normal, pair `p` with the leaf's
    /// position and the parent's normal, else with the deepest node passed that has a
    /// normal. Returns (position, unit normal, depth of the node that gave the
    /// position: the leaf, or the node with the normal).
    pub fn associate(&self, p: [f64; 3]) -> Option<([f64; 3], [f64; 3], u32)> {
        self.associate_from(p, &mut Descent::default())
    }

    /// `associate`, resuming below the deepest node this point shares with the
    /// previous descent recorded in `cursor` (ICP visits points in Morton order, so
    /// neighbours share all but the last few levels). Use one cursor per thread and map.
    pub fn associate_from(
        &self,
        p: [f64; 3],
        cursor: &mut Descent,
    ) -> Option<([f64; 3], [f64; 3], u32)> {
        let key = self.conv.coord_to_key_checked_f64(p)?;
        self.associate_key_from(key, cursor)
    }

    /// `associate_from` for the leaf key of a point: the association depends on
    /// nothing else (callers may cache it per key).
    pub fn associate_key_from(
        &self,
        key: OcTreeKey,
        cursor: &mut Descent,
    ) -> Option<([f64; 3], [f64; 3], u32)> {
        if self.root == NONE {
            return None;
        }
        // Nodes down to the depth where the keys' child indices first differ are shared.
        let shared = match cursor.key {
            Some(prev) => {
                let diff = (prev.0[0] ^ key.0[0]) | (prev.0[1] ^ key.0[1]) | (prev.0[2] ^ key.0[2]);
                (diff.leading_zeros() as usize).min(cursor.len.saturating_sub(1))
            }
            None => 0,
        };
        let (mut node, mut best, start) = if shared > 0 {
            (cursor.path[shared], cursor.best[shared], shared as u32)
        } else {
            (self.root, None, 0)
        };
        cursor.key = Some(key);
        for d in start..TREE_DEPTH {
            cursor.path[d as usize] = node;
            cursor.best[d as usize] = best;
            cursor.len = d as usize + 1;
            let here = self.arena.value(node);
            if here.has_normal {
                best = Some((node, d));
            }
            let Some(child) = self.arena.child(node, key.child_index(TREE_DEPTH - 1 - d)) else {
                break;
            };
            if here.has_normal && !self.arena.has_children(child) {
                // `child` is the leaf and `here` its parent, which has a normal.
                let leaf = self.arena.value(child);
                return Some((
                    leaf.position.map(f64::from),
                    here.normal.map(f64::from),
                    d + 1,
                ));
            }
            node = child;
        }
        best.map(|(n, d)| {
            let n = self.arena.value(n);
            (n.position.map(f64::from), n.normal.map(f64::from), d)
        })
    }

    /// `associate_key_from` kept to nodes no larger than `max_size` (m); where it finds
    /// none, the nearest such association of the six leaves beside `key`. A point just
    /// off a surface on a boundary the map's nodes do not straddle (a wall on x = 0,
    /// which the root's children split) shares no node below the root with it: only
    /// the points on the wall's mapped side would pair, all of them pulling the same
    /// way, and ICP would run off into the empty side.
    pub fn associate_within(
        &self,
        key: OcTreeKey,
        max_size: f64,
        cursor: &mut Descent,
    ) -> Option<Association> {
        let fits = |found: &Association| self.conv.node_size(found.2) <= max_size;
        if let Some(found) = self.associate_key_from(key, cursor).filter(fits) {
            return Some(found);
        }
        // Only leaves across a boundary of the largest node fine enough can help: one
        // within the same such node shares it with the point, whose descent found
        // nothing there (asking every neighbour of every unpaired point cost a frame's
        // alignment 4 ms).
        let coarsest = (0..=TREE_DEPTH)
            .find(|&d| self.conv.node_size(d) <= max_size)
            .unwrap_or(TREE_DEPTH);
        let shift = TREE_DEPTH - coarsest;
        let centre = self.conv.key_to_coord_at_depth(key, TREE_DEPTH);
        let mut nearest: Option<(f64, Association)> = None;
        for axis in 0..3 {
            for beside in [key.0[axis].checked_sub(1), key.0[axis].checked_add(1)] {
                let Some(k) = beside.filter(|&k| {
                    u32::from(k).checked_shr(shift) != u32::from(key.0[axis]).checked_shr(shift)
                }) else {
                    continue;
                };
                let mut neighbour = key;
                neighbour.0[axis] = k;
                let Some(found) = self
                    .associate_key_from(neighbour, &mut Descent::default())
                    .filter(fits)
                else {
                    continue;
                };
                let d = crate::geometry::distance_squared(&centre, &found.0);
                if nearest.is_none_or(|(best, _)| d < best) {
                    nearest = Some((d, found));
                }
            }
        }
        nearest.map(|(_, found)| found)
    }
}

/// An association: the position and unit normal a point pairs with, and the depth of
/// the node that gave the position.
pub type Association = ([f64; 3], [f64; 3], u32);

/// The nodes of the last `SurfaceMap::associate_from` descent (for one map that does
/// not change meanwhile): the node at each depth and the deepest node with a normal
/// above it.
#[derive(Clone, Debug)]
pub struct Descent {
    key: Option<OcTreeKey>,
    path: [u32; TREE_DEPTH as usize],
    /// (node, depth) of the deepest node with a normal above each depth.
    best: [Option<(u32, u32)>; TREE_DEPTH as usize],
    len: usize,
}

impl Default for Descent {
    fn default() -> Self {
        Descent {
            key: None,
            path: [NONE; TREE_DEPTH as usize],
            best: [None; TREE_DEPTH as usize],
            len: 0,
        }
    }
}

fn pos(c: &SurfaceNode) -> Vector3<f64> {
    Vector3::new(
        f64::from(c.position[0]),
        f64::from(c.position[1]),
        f64::from(c.position[2]),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::Rng;

    /// Leaf depths equal the definition, the smallest node of at least r·b (clamped to
    /// the coarsest), wherever r·b is not within rounding of a node size.
    #[test]
    fn leaf_depths_are_the_smallest_node_spanning_the_gap() {
        let mut rng = Rng::new(17);
        for (res, spacing, max_leaf) in [(0.01, 0.035, 0.16), (0.05, 0.004, 10.0), (0.2, 0.5, 0.2)]
        {
            let map = SurfaceMap::new(res, SurfaceParams::default()).unwrap();
            let origin = [0.3, -1.2, 0.7];
            let coarsest = (max_leaf / res).log2().floor().clamp(0.0, 15.0) as u32;
            // Ranges spread over many octaves, and exactly at node sizes (gap = 2^l cells).
            let mut ranges: Vec<f64> = (0..20_000)
                .map(|_| 10f64.powf(rng.uniform(-4.0, 3.5)))
                .collect();
            ranges.extend((0..16).map(|l| f64::from(1u32 << l) * res / spacing));
            let points: Vec<[f64; 3]> = ranges
                .iter()
                .map(|&r| {
                    let d = [
                        rng.uniform(-1.0, 1.0),
                        rng.uniform(-1.0, 1.0),
                        rng.uniform(-1.0, 1.0),
                    ];
                    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                    [0, 1, 2].map(|a| origin[a] + r * d[a] / n)
                })
                .collect();
            let depths = map.leaf_depths(&points, origin, spacing, max_leaf).unwrap();
            for (p, &depth) in points.iter().zip(&depths) {
                let r = crate::geometry::distance_squared(p, &origin).sqrt();
                let gap_cells = r * spacing / res;
                let levels = if gap_cells <= 1.0 {
                    0
                } else {
                    gap_cells.log2().ceil() as u32
                };
                let want = TREE_DEPTH - levels.min(coarsest);
                let near_size = (gap_cells.log2() - gap_cells.log2().round()).abs() < 1e-9;
                assert!(
                    u32::from(depth) == want || near_size,
                    "r {r}: {depth} vs {want}"
                );
            }
        }
    }

    #[test]
    fn a_point_off_a_surface_on_the_roots_boundary_pairs_with_the_leaf_beside_it() {
        // A noise-free wall on x = 0: all its points fall in the root's x >= 0 half, and
        // a point 1-9 mm in front of it shares no node below the root with the wall.
        let mut map = SurfaceMap::new(0.02, SurfaceParams::default()).unwrap();
        let wall: Vec<[f64; 3]> = (0..40)
            .flat_map(|i| (0..40).map(move |j| [0.0, 0.1 + 0.01 * i as f64, 0.1 + 0.01 * j as f64]))
            .collect();
        map.insert(&wall).unwrap();
        map.insert(&wall).unwrap();
        let conv = *map.key_converter();
        for gap in [0.001, 0.005, 0.009] {
            let p = [-gap, 0.305, 0.305];
            let key = conv.coord_to_key_checked_f64(p).unwrap();
            let plain = map.associate_key_from(key, &mut Descent::default());
            assert!(
                plain.is_none_or(|(_, _, depth)| conv.node_size(depth) > 0.2),
                "{plain:?}"
            );
            let (q, n, depth) = map
                .associate_within(key, 0.2, &mut Descent::default())
                .unwrap();
            // The leaf across the boundary: on the wall, beside the point, normal along x.
            assert_eq!(depth, TREE_DEPTH);
            assert_eq!(q[0], 0.0);
            assert!(
                (q[1] - p[1]).abs() <= 0.02 && (q[2] - p[2]).abs() <= 0.02,
                "{q:?}"
            );
            assert!(n[0].abs() > 0.999, "{n:?}");
            // Where the plain association pairs, it is what is returned.
            let on = conv.coord_to_key_checked_f64([0.0, 0.305, 0.305]).unwrap();
            assert_eq!(
                map.associate_within(on, 0.2, &mut Descent::default()),
                map.associate_key_from(on, &mut Descent::default())
            );
        }
        // Nothing beside either: nothing.
        let far = conv.coord_to_key_checked_f64([-0.5, 0.3, 0.3]).unwrap();
        assert_eq!(
            map.associate_within(far, 0.2, &mut Descent::default()),
            None
        );
    }

    /// A resumed descent gives exactly what a fresh one does, whatever the order of
    /// the points (Morton order shares long prefixes, random order short ones).
    #[test]
    fn resumed_descent_equals_fresh_descent() {
        let mut rng = Rng::new(11);
        let mut map = SurfaceMap::new(0.02, SurfaceParams::default()).unwrap();
        // Two walls and a floor, a little noisy, inserted twice (normals form).
        let mut points = Vec::new();
        for _ in 0..6000 {
            let (u, v) = (rng.uniform(-1.0, 1.0), rng.uniform(0.0, 1.0));
            let e = rng.uniform(-0.003, 0.003);
            points.push([u, 1.0 + e, v]);
            points.push([1.0 + e, u, v]);
            points.push([u, v, e]);
        }
        map.insert(&points).unwrap();
        map.insert(&points).unwrap();
        let queries: Vec<[f64; 3]> = (0..5000)
            .map(|_| {
                [
                    rng.uniform(-1.1, 1.1),
                    rng.uniform(-0.2, 1.1),
                    rng.uniform(-0.1, 1.1),
                ]
            })
            .chain(
                points
                    .iter()
                    .take(3000)
                    .map(|p| [p[0] + 0.004, p[1] - 0.003, p[2] + 0.002]),
            )
            .collect();
        let order = crate::geometry::morton_order(&queries);
        let morton: Vec<[f64; 3]> = order.iter().map(|&i| queries[i as usize]).collect();
        let mut paired = 0;
        for list in [&queries, &morton] {
            let mut cursor = Descent::default();
            for &q in list.iter() {
                let fresh = map.associate(q);
                assert_eq!(map.associate_from(q, &mut cursor), fresh, "{q:?}");
                paired += usize::from(fresh.is_some());
            }
        }
        assert!(paired > 4000, "{paired}");
    }
}
