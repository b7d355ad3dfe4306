//! `OcTree`: probabilistic occupancy with OctoMap's update, pruning and query rules.

use super::arena::{NodeArena, NONE};
use super::danger::DangerMap;
use super::key::{child_runs, KeyConverter, OcTreeKey, TREE_DEPTH};
use crate::error::{Error, Result};

/// Sensor model and thresholds, as probabilities (OctoMap's defaults).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OccupancyParams {
    /// Probability that a cell is occupied after a hit (OctoMap: 0.7).
    pub prob_hit: f64,
    /// Probability that a cell is occupied after a miss (OctoMap: 0.4).
    pub prob_miss: f64,
    /// Lower clamping bound of a cell's occupancy (OctoMap: 0.1192).
    pub clamping_min: f64,
    /// Upper clamping bound of a cell's occupancy (OctoMap: 0.971).
    pub clamping_max: f64,
    /// A cell is occupied at or above this probability (OctoMap: 0.5).
    pub occupancy_threshold: f64,
}

impl Default for OccupancyParams {
    fn default() -> Self {
        OccupancyParams {
            prob_hit: 0.7,
            prob_miss: 0.4,
            clamping_min: 0.1192,
            clamping_max: 0.971,
            occupancy_threshold: 0.5,
        }
    }
}

impl OccupancyParams {
    /// Errors unless every value is a probability in (0, 1), `prob_hit` > 0.5 >
    /// `prob_miss`, and `clamping_min` < `clamping_max`.
    pub fn validate(&self) -> Result<()> {
        let open = |name: &str, p: f64| {
            if p.is_finite() && p > 0.0 && p < 1.0 {
                Ok(())
            } else {
                Err(Error::InvalidArgument(format!(
                    "{name} must be a probability in (0, 1), got {p}"
                )))
            }
        };
        open("prob_hit", self.prob_hit)?;
        open("prob_miss", self.prob_miss)?;
        open("clamping_min", self.clamping_min)?;
        open("clamping_max", self.clamping_max)?;
        open("occupancy_threshold", self.occupancy_threshold)?;
        // A hit must raise a cell's occupancy and a miss lower it, or scans build a
        // map upside down without a word.
        if self.prob_hit <= 0.5 || self.prob_miss >= 0.5 {
            return Err(Error::InvalidArgument(format!(
                "prob_hit must be above 0.5 and prob_miss below it, got {} and {}",
                self.prob_hit, self.prob_miss
            )));
        }
        if self.clamping_min >= self.clamping_max {
            return Err(Error::InvalidArgument(format!(
                "clamping_min ({}) must be below clamping_max ({})",
                self.clamping_min, self.clamping_max
            )));
        }
        Ok(())
    }
}

/// OctoMap's `logodds`: computed in double, stored as float.
#[inline]
pub fn logodds(p: f64) -> f32 {
    (p / (1.0 - p)).ln() as f32
}

/// Inverse of [`logodds`] (OctoMap's `probability`).
#[inline]
pub fn probability(l: f32) -> f64 {
    1.0 - 1.0 / (1.0 + f64::from(l).exp())
}

#[derive(Clone, Copy, Debug)]
pub(crate) struct LogOddsParams {
    pub hit: f32,
    pub miss: f32,
    pub clamp_min: f32,
    pub clamp_max: f32,
    pub occupied: f32,
}

impl From<&OccupancyParams> for LogOddsParams {
    fn from(p: &OccupancyParams) -> Self {
        LogOddsParams {
            hit: logodds(p.prob_hit),
            miss: logodds(p.prob_miss),
            clamp_min: logodds(p.clamping_min),
            clamp_max: logodds(p.clamping_max),
            occupied: logodds(p.occupancy_threshold),
        }
    }
}

/// One pending update in a batch: a cell (Morton code of its key) and a log-odds change.
pub type KeyUpdate = (u64, f32);

/// A leaf as reported by iteration: the key of its lower corner, its depth and log-odds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Leaf {
    /// Key of the leaf's lower corner (its finest cell with the smallest key).
    pub key: OcTreeKey,
    /// Depth of the leaf: 16 for a finest cell, less for a pruned leaf.
    pub depth: u32,
    /// Occupancy in log-odds.
    pub log_odds: f32,
}

/// Occupancy octree with OctoMap's semantics plus a per-voxel danger map.
///
/// ```
/// use earcore_core::octree::OcTree;
///
/// let mut tree = OcTree::new(0.1)?;
/// // One scan from the origin: a wall point 2 m ahead.
/// let report = tree.insert_point_cloud(&[[2.05, 0.05, 0.05]], [0.05, 0.05, 0.05], None, false)?;
/// assert_eq!((report.free_cells, report.occupied_cells), (20, 1));
/// let wall = tree.key_of("point", [2.05, 0.05, 0.05])?;
/// assert!(tree.is_occupied_log_odds(tree.search(wall, 0).unwrap()));
/// // The voxel just hit is dangerous until it has been seen free long enough.
/// tree.danger_map_mut().end_frame(1.0 / 15.0)?;
/// assert_eq!(tree.danger_map().value(wall.morton()), 0.999);
/// # Ok::<(), earcore_core::Error>(())
/// ```
#[derive(Clone, Debug)]
pub struct OcTree {
    pub(crate) conv: KeyConverter,
    params: OccupancyParams,
    pub(crate) lo: LogOddsParams,
    pub(crate) arena: NodeArena<f32>,
    pub(crate) root: u32,
    pub(crate) danger: DangerMap,
}

impl OcTree {
    /// An empty tree with cells of `resolution` metres and OctoMap's default parameters.
    /// Errors when `resolution` is not a positive number.
    pub fn new(resolution: f64) -> Result<Self> {
        Self::with_params(resolution, OccupancyParams::default())
    }

    /// An empty tree with cells of `resolution` metres and the given sensor model.
    /// Errors when `resolution` is not a positive number or `params` are invalid.
    pub fn with_params(resolution: f64, params: OccupancyParams) -> Result<Self> {
        if !(resolution.is_finite() && resolution > 0.0) {
            return Err(Error::InvalidArgument(format!(
                "resolution must be a positive number of metres, got {resolution}"
            )));
        }
        params.validate()?;
        Ok(OcTree {
            conv: KeyConverter::new(resolution),
            lo: LogOddsParams::from(&params),
            params,
            arena: NodeArena::new(),
            root: NONE,
            danger: DangerMap::default(),
        })
    }

    /// Edge length of a finest cell, in metres.
    pub fn resolution(&self) -> f64 {
        self.conv.resolution()
    }

    /// The sensor model and thresholds, as probabilities.
    pub fn params(&self) -> OccupancyParams {
        self.params
    }

    /// Conversions between metric points and this tree's keys.
    pub fn key_converter(&self) -> &KeyConverter {
        &self.conv
    }

    /// Clamping bounds and occupancy threshold in log-odds (float, as OctoMap stores them).
    pub fn clamping_log_odds(&self) -> (f32, f32) {
        (self.lo.clamp_min, self.lo.clamp_max)
    }

    /// The occupancy threshold in log-odds (float, as OctoMap stores it).
    pub fn occupancy_threshold_log_odds(&self) -> f32 {
        self.lo.occupied
    }

    /// Whether a log-odds value counts as occupied (OctoMap: `>=` threshold).
    #[inline]
    pub fn is_occupied_log_odds(&self, l: f32) -> bool {
        l >= self.lo.occupied
    }

    /// Number of nodes (OctoMap's `size()`).
    pub fn size(&self) -> usize {
        self.arena.len()
    }

    /// Remove every node and all danger.
    pub fn clear(&mut self) {
        self.arena.clear();
        self.root = NONE;
        self.danger = DangerMap::default();
    }

    /// Bytes held by the tree (nodes, child blocks, danger map), spare capacity included.
    pub fn memory_usage(&self) -> usize {
        std::mem::size_of::<Self>() + self.arena.memory_usage() + self.danger.memory_usage()
    }

    /// Number of leaves (OctoMap's `getNumLeafNodes()`).
    pub fn num_leaf_nodes(&self) -> usize {
        if self.root == NONE {
            return 0;
        }
        let mut count = 0;
        let mut stack = vec![self.root];
        while let Some(n) = stack.pop() {
            if self.arena.has_children(n) {
                stack.extend(self.arena.children(n).into_iter().filter(|&c| c != NONE));
            } else {
                count += 1;
            }
        }
        count
    }

    /// The node holding `key` at `depth` (0 or ≥ 16 = finest), or the pruned leaf
    /// above it; `None` where the cell is unknown. Returns (node, its depth).
    pub fn search_node(&self, key: OcTreeKey, depth: u32) -> Option<(u32, u32)> {
        if self.root == NONE {
            return None;
        }
        let depth = if depth == 0 || depth > TREE_DEPTH {
            TREE_DEPTH
        } else {
            depth
        };
        let key = key.at_depth(depth);
        let mut node = self.root;
        for d in 0..depth {
            match self.arena.child(node, key.child_index(TREE_DEPTH - 1 - d)) {
                Some(c) => node = c,
                None if !self.arena.has_children(node) => return Some((node, d)),
                None => return None,
            }
        }
        Some((node, depth))
    }

    /// Log-odds of the node holding `key` at `depth`, `None` where unknown.
    pub fn search(&self, key: OcTreeKey, depth: u32) -> Option<f32> {
        self.search_node(key, depth)
            .map(|(n, _)| self.arena.value(n))
    }

    /// Add `delta` to the log-odds of one cell (OctoMap's `updateNode(key, float)`).
    pub fn update_node_log_odds(&mut self, key: OcTreeKey, delta: f32) -> Result<()> {
        if !delta.is_finite() {
            return Err(Error::InvalidArgument(format!(
                "log-odds update must be finite, got {delta}"
            )));
        }
        self.apply_sorted_updates(&[(key.morton(), delta)]);
        Ok(())
    }

    /// Integrate one hit (`occupied`) or miss at a cell.
    pub fn update_node(&mut self, key: OcTreeKey, occupied: bool) {
        let delta = if occupied { self.lo.hit } else { self.lo.miss };
        self.apply_sorted_updates(&[(key.morton(), delta)]);
    }

    /// Apply updates to distinct cells sorted by Morton code in one walk down the tree.
    ///
    /// The result equals OctoMap applying `updateNode(key, delta)` to each cell in any
    /// order, including its early abort for cells already at the clamping bound: a
    /// cell's abort depends only on the leaf that held it before the batch, and pruning
    /// is decided once all children are final.
    pub fn apply_sorted_updates(&mut self, updates: &[KeyUpdate]) {
        debug_assert!(
            updates.windows(2).all(|w| w[0].0 < w[1].0),
            "updates must be sorted and distinct"
        );
        if updates.is_empty() {
            return;
        }
        let created = if self.root == NONE {
            self.root = self.arena.alloc(0.0);
            true
        } else {
            false
        };
        self.update_recursive(self.root, created, 0, updates);
    }

    /// Returns whether anything below `node` changed.
    fn update_recursive(
        &mut self,
        node: u32,
        just_created: bool,
        depth: u32,
        updates: &[KeyUpdate],
    ) -> bool {
        let filtered: Vec<KeyUpdate>;
        let mut updates = updates;
        if !just_created && !self.arena.has_children(node) {
            // OctoMap searches each cell first and skips it when the leaf holding it is
            // already clamped in the update's direction.
            let v = self.arena.value(node);
            let (lo, hi) = (self.lo.clamp_min, self.lo.clamp_max);
            let aborts = |d: f32| (d >= 0.0 && v >= hi) || (d <= 0.0 && v <= lo);
            if updates.iter().any(|&(_, d)| aborts(d)) {
                filtered = updates
                    .iter()
                    .copied()
                    .filter(|&(_, d)| !aborts(d))
                    .collect();
                if filtered.is_empty() {
                    return false;
                }
                updates = &filtered;
            }
            if depth == TREE_DEPTH {
                self.apply_log_odds(node, updates[0].1);
                return true;
            }
            self.arena.expand(node);
        } else if depth == TREE_DEPTH {
            self.apply_log_odds(node, updates[0].1);
            return true;
        }

        let mut changed = false;
        for (pos, group) in child_runs(updates, depth) {
            let (child, created) = match self.arena.child(node, pos) {
                Some(c) => (c, false),
                None => (self.arena.create_child(node, pos, 0.0), true),
            };
            changed |= self.update_recursive(child, created, depth + 1, group);
        }
        // Like OctoMap, a node is re-pruned or re-valued only when something below changed.
        if changed && !self.prune_node(node) {
            let max = self.max_child_log_odds(node);
            self.arena.set_value(node, max);
        }
        changed
    }

    #[inline]
    fn apply_log_odds(&mut self, node: u32, delta: f32) {
        let mut v = self.arena.value(node) + delta;
        if v < self.lo.clamp_min {
            v = self.lo.clamp_min;
        } else if v > self.lo.clamp_max {
            v = self.lo.clamp_max;
        }
        self.arena.set_value(node, v);
    }

    pub(crate) fn max_child_log_odds(&self, node: u32) -> f32 {
        let mut max = -f32::MAX;
        for c in self.arena.children(node) {
            if c != NONE {
                let l = self.arena.value(c);
                if l > max {
                    max = l;
                }
            }
        }
        max
    }

    /// OctoMap's `pruneNode`: collapse eight equal leaf children into their parent.
    pub(crate) fn prune_node(&mut self, node: u32) -> bool {
        let children = self.arena.children(node);
        if children[0] == NONE {
            return false;
        }
        let first = self.arena.value(children[0]);
        for &c in &children {
            if c == NONE || self.arena.has_children(c) || self.arena.value(c) != first {
                return false;
            }
        }
        self.arena.set_value(node, first);
        self.arena.delete_children(node);
        true
    }

    /// Collapse every prunable node, deepest first (OctoMap's `prune`, including its
    /// stop after a depth where nothing was pruned).
    pub fn prune(&mut self) {
        if self.root == NONE {
            return;
        }
        for depth in (1..TREE_DEPTH).rev() {
            let mut pruned = 0usize;
            let mut stack = vec![(self.root, 0u32)];
            while let Some((n, d)) = stack.pop() {
                if d < depth {
                    for c in self.arena.children(n) {
                        if c != NONE {
                            stack.push((c, d + 1));
                        }
                    }
                } else if self.prune_node(n) {
                    pruned += 1;
                }
            }
            if pruned == 0 {
                break;
            }
        }
    }

    /// Recompute every inner node as the maximum of its children (OctoMap's
    /// `updateInnerOccupancy`, needed after edits that bypass the batch update).
    pub fn update_inner_occupancy(&mut self) {
        if self.root == NONE {
            return;
        }
        // Post-order over an explicit stack: children before parents.
        let mut order = Vec::new();
        let mut stack = vec![self.root];
        while let Some(n) = stack.pop() {
            if self.arena.has_children(n) {
                order.push(n);
                stack.extend(self.arena.children(n).into_iter().filter(|&c| c != NONE));
            }
        }
        for &n in order.iter().rev() {
            let max = self.max_child_log_odds(n);
            self.arena.set_value(n, max);
        }
    }

    /// Visit every leaf (pruned or finest) whose cube meets the key box
    /// `[min, max]` (inclusive); pass the full key range to visit all leaves.
    pub fn for_each_leaf_in_keys(&self, min: OcTreeKey, max: OcTreeKey, mut f: impl FnMut(Leaf)) {
        if self.root == NONE {
            return;
        }
        let mut stack = vec![(self.root, 0u32, OcTreeKey([0, 0, 0]))];
        while let Some((n, depth, base)) = stack.pop() {
            if !self.arena.has_children(n) {
                f(Leaf {
                    key: base,
                    depth,
                    log_odds: self.arena.value(n),
                });
                continue;
            }
            let level = TREE_DEPTH - 1 - depth;
            let half = 1u32 << level;
            let children = self.arena.children(n);
            for pos in (0..8).rev() {
                let c = children[pos];
                if c == NONE {
                    continue;
                }
                let mut k = base.0;
                for (axis, bit) in [(0, 1), (1, 2), (2, 4)] {
                    if pos & bit != 0 {
                        k[axis] |= half as u16;
                    }
                }
                // Skip children whose key span misses the box.
                let inside = (0..3).all(|a| {
                    let lo = u32::from(k[a]);
                    let hi = lo + half - 1;
                    hi >= u32::from(min.0[a]) && lo <= u32::from(max.0[a])
                });
                if inside {
                    stack.push((c, depth + 1, OcTreeKey(k)));
                }
            }
        }
    }

    /// Visit every leaf (pruned or finest), as [`for_each_leaf_in_keys`](Self::for_each_leaf_in_keys)
    /// over all keys.
    pub fn for_each_leaf(&self, f: impl FnMut(Leaf)) {
        self.for_each_leaf_in_keys(OcTreeKey([0; 3]), OcTreeKey([u16::MAX; 3]), f)
    }

    /// Centre (metres) of the node at `depth` whose lower-corner key is `key`.
    pub fn node_center(&self, key: OcTreeKey, depth: u32) -> [f64; 3] {
        self.conv.key_to_coord_at_depth(key, depth)
    }

    /// Key of a metric point, or an error naming the point when it is off the map.
    pub fn key_of(&self, what: &'static str, p: [f64; 3]) -> Result<OcTreeKey> {
        if !p.iter().all(|c| c.is_finite()) {
            return Err(Error::InvalidArgument(format!(
                "{what} {p:?} is not finite"
            )));
        }
        self.conv
            .coord_to_key_checked_f64(p)
            .ok_or(Error::OutOfBounds {
                what,
                point: p,
                limit: self.conv.metric_limits().1,
            })
    }

    /// The per-voxel danger kept alongside the occupancy.
    pub fn danger_map(&self) -> &DangerMap {
        &self.danger
    }

    /// The per-voxel danger, to record frames or change parameters.
    pub fn danger_map_mut(&mut self) -> &mut DangerMap {
        &mut self.danger
    }
}
