//! `OcTree`: probabilistic occupancy with OctoMap's update, pruning and query rules.

use super::arena::{NodeArena, NONE};
use super::danger::DangerMap;
use super::key::{child_runs, KeyConverter, OcTreeKey, TREE_DEPTH};
use crate::error::{Error, Result};
use crate::geometry::{fmt_num, fmt_point};

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
                    "{name} must be a probability in (0, 1), got {}",
                    fmt_num(p)
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
                fmt_num(self.prob_hit),
                fmt_num(self.prob_miss)
            )));
        }
        if self.clamping_min >= self.clamping_max {
            return Err(Error::InvalidArgument(format!(
                "clamping_min ({}) must be below clamping_max ({})",
                fmt_num(self.clamping_min),
                fmt_num(self.clamping_max)
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
    /// Errors when `resolution` is outside
    /// [[`MIN_RESOLUTION`](crate::octree::MIN_RESOLUTION),
    /// [`MAX_RESOLUTION`](crate::octree::MAX_RESOLUTION)].
    pub fn new(resolution: f64) -> Result<Self> {
        Self::with_params(resolution, OccupancyParams::default())
    }

    /// An empty tree with cells of `resolution` metres and the given sensor model.
    /// Errors when `resolution` is outside
    /// [[`MIN_RESOLUTION`](crate::octree::MIN_RESOLUTION),
    /// [`MAX_RESOLUTION`](crate::octree::MAX_RESOLUTION)] or `params` are invalid.
    pub fn with_params(resolution: f64, params: OccupancyParams) -> Result<Self> {
        super::key::check_resolution(resolution)?;
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

    /// Remove every node and all danger; the sensor model and the danger's parameters
    /// stay.
    pub fn clear(&mut self) {
        self.arena.clear();
        self.root = NONE;
        self.danger.clear();
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

    /// Set the log-odds of every cell in `keys` to `value` clamped to the clamping
    /// bounds (±∞ give the bounds), in one walk down the tree.
    ///
    /// The result equals OctoMap's `setNodeValue(key, value)` (without lazy
    /// evaluation) for each cell in any order: pruned nodes on the way are expanded,
    /// ancestors re-valued as the maximum of their children, and nodes whose eight
    /// children end up equal pruned. A cell listed twice is set once (setting is
    /// idempotent). Danger is not touched. A NaN `value` is an error and changes nothing.
    pub fn set_log_odds(&mut self, keys: &[OcTreeKey], value: f32) -> Result<()> {
        if value.is_nan() {
            return Err(Error::InvalidArgument(
                "log-odds value must not be NaN".into(),
            ));
        }
        let value = value.clamp(self.lo.clamp_min, self.lo.clamp_max);
        let mut cells: Vec<KeyUpdate> = keys.iter().map(|k| (k.morton(), value)).collect();
        cells.sort_unstable_by_key(|&(m, _)| m);
        cells.dedup_by_key(|&mut (m, _)| m);
        if cells.is_empty() {
            return Ok(());
        }
        let created = if self.root == NONE {
            self.root = self.arena.alloc(0.0);
            true
        } else {
            false
        };
        self.update_recursive::<true>(self.root, created, 0, &cells);
        self.arena.trim_spare();
        Ok(())
    }

    /// Add `delta` to the log-odds of every cell in `keys`, `repeat` times per listed
    /// key: the tree ends as after OctoMap's `updateNode(key, delta)` called `repeat`
    /// times for each entry of `keys` (a cell listed twice is updated twice as often),
    /// in any order, clamping and early aborts at the bounds included. Danger is not
    /// touched. A non-finite `delta` is an error and changes nothing.
    ///
    /// Runs in rounds of distinct cells (one batched walk each) and stops early once a
    /// round would change no cell's value.
    pub fn update_log_odds(&mut self, keys: &[OcTreeKey], delta: f32, repeat: u32) -> Result<()> {
        if !delta.is_finite() {
            return Err(Error::InvalidArgument(format!(
                "log-odds update must be finite, got {delta}"
            )));
        }
        let mut codes: Vec<u64> = keys.iter().map(|k| k.morton()).collect();
        codes.sort_unstable();
        // (cell, how many times it is updated), sorted by cell.
        let mut counts: Vec<(u64, u64)> = Vec::with_capacity(codes.len());
        for m in codes {
            match counts.last_mut() {
                Some((last, n)) if *last == m => *n += u64::from(repeat),
                _ => counts.push((m, u64::from(repeat))),
            }
        }
        let mut round: Vec<KeyUpdate> = Vec::with_capacity(counts.len());
        let mut done = 0u64;
        loop {
            counts.retain(|&(_, n)| n > done);
            if counts.is_empty() {
                return Ok(());
            }
            round.clear();
            round.extend(counts.iter().map(|&(m, _)| (m, delta)));
            if done > 0 && round.iter().all(|&(m, d)| self.update_is_noop(m, d)) {
                // Later rounds update subsets of these cells: no-ops too.
                return Ok(());
            }
            self.apply_sorted_updates(&round);
            done += 1;
        }
    }

    /// Whether `updateNode(cell, delta)` would leave the cell's value as it is (an
    /// early abort at a bound, or a change lost to rounding or clamping). Only used
    /// once the cell's path has been updated, so that the update would not re-prune
    /// or re-value any node either.
    fn update_is_noop(&self, code: u64, delta: f32) -> bool {
        let Some(v) = self.search(OcTreeKey::from_morton(code), 0) else {
            return false;
        };
        let (lo, hi) = (self.lo.clamp_min, self.lo.clamp_max);
        if (delta >= 0.0 && v >= hi) || (delta <= 0.0 && v <= lo) {
            return true;
        }
        (v + delta).clamp(lo, hi).to_bits() == v.to_bits()
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
        self.update_recursive::<false>(self.root, created, 0, updates);
        self.arena.trim_spare();
    }

    /// Returns whether anything below `node` changed. With `ASSIGN`, each update's
    /// value replaces the cell's log-odds (already clamped by the caller) and nothing
    /// aborts, as in OctoMap's `setNodeValue`; otherwise it is added (a compile-time
    /// flag, so that the scan path is the same code as without it).
    fn update_recursive<const ASSIGN: bool>(
        &mut self,
        node: u32,
        just_created: bool,
        depth: u32,
        updates: &[KeyUpdate],
    ) -> bool {
        debug_assert!(depth < TREE_DEPTH, "cells are updated by their parents");
        let filtered: Vec<KeyUpdate>;
        let mut updates = updates;
        if ASSIGN {
            if !just_created && !self.arena.has_children(node) {
                self.arena.expand(node);
            }
        } else if !just_created && !self.arena.has_children(node) {
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
            if covers_alike(updates, depth) {
                self.apply_log_odds(node, updates[0].1);
                return true;
            }
            self.arena.expand(node);
        } else if just_created && covers_alike(updates, depth) {
            self.apply_log_odds(node, updates[0].1);
            return true;
        }

        let mut changed = false;
        if depth + 1 == TREE_DEPTH {
            // Cells are distinct, so each update is its own leaf: no runs to find.
            for &(m, d) in updates {
                let pos = (m & 7) as usize;
                changed |= match self.arena.child(node, pos) {
                    Some(leaf) => self.update_leaf::<ASSIGN>(leaf, d),
                    None => {
                        let leaf = self.arena.create_child(node, pos, 0.0);
                        self.set_new_leaf::<ASSIGN>(leaf, d);
                        true
                    }
                };
            }
        } else {
            for (pos, group) in child_runs(updates, depth) {
                let (child, created) = match self.arena.child(node, pos) {
                    Some(c) => (c, false),
                    None => (self.arena.create_child(node, pos, 0.0), true),
                };
                changed |= self.update_recursive::<ASSIGN>(child, created, depth + 1, group);
            }
        }
        // Like OctoMap, a node is re-pruned or re-valued only when something below changed.
        if changed && !self.prune_node(node) {
            let max = self.max_child_log_odds(node);
            self.arena.set_value(node, max);
        }
        changed
    }

    /// An existing cell at the finest level: what `update_recursive` does there.
    #[inline]
    fn update_leaf<const ASSIGN: bool>(&mut self, leaf: u32, delta: f32) -> bool {
        if ASSIGN {
            self.arena.set_value(leaf, delta);
            return true;
        }
        let v = self.arena.value(leaf);
        if (delta >= 0.0 && v >= self.lo.clamp_max) || (delta <= 0.0 && v <= self.lo.clamp_min) {
            return false;
        }
        self.apply_log_odds(leaf, delta);
        true
    }

    /// A cell the batch just created at the finest level.
    #[inline]
    fn set_new_leaf<const ASSIGN: bool>(&mut self, leaf: u32, delta: f32) {
        if ASSIGN {
            self.arena.set_value(leaf, delta);
        } else {
            self.apply_log_odds(leaf, delta);
        }
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

    /// Every known finest-resolution cell whose centre lies in the closed box
    /// `[lo, hi]` (metres), as (key, log-odds): finest leaves as they are, pruned
    /// leaves split into their cells (each with the leaf's log-odds). With
    /// `occupied_only`, only cells at or above the occupancy threshold.
    ///
    /// Cells come leaf by leaf in the tree's Morton order, the cells of a pruned leaf
    /// with x slowest and z fastest. A box with `lo > hi` on some axis holds nothing;
    /// parts of the box beyond the map are ignored. NaN bounds, and boxes that would
    /// give more than `max_cells` cells, are errors.
    pub fn finest_cells_in_box(
        &self,
        lo: [f64; 3],
        hi: [f64; 3],
        occupied_only: bool,
        max_cells: usize,
    ) -> Result<Vec<(OcTreeKey, f32)>> {
        if lo.iter().chain(&hi).any(|c| c.is_nan()) {
            return Err(Error::InvalidArgument(format!(
                "box bounds must not be NaN, got {} to {}",
                fmt_point(&lo),
                fmt_point(&hi)
            )));
        }
        // Per axis, the keys of the cells whose centres lie in [lo, hi] (centres grow
        // with the key, so two bisections over the 2^16 keys find them exactly).
        let mut first = [0u16; 3];
        let mut last = [0u16; 3];
        for a in 0..3 {
            let centre = |k: u32| self.conv.key_to_coord_axis(k as u16);
            let start = partition_keys(|k| centre(k) < lo[a]);
            let end = partition_keys(|k| centre(k) <= hi[a]);
            if start >= end {
                return Ok(Vec::new());
            }
            first[a] = start as u16;
            last[a] = (end - 1) as u16;
        }
        let mut leaves = Vec::new();
        self.for_each_leaf_in_keys(OcTreeKey(first), OcTreeKey(last), |l| {
            if !occupied_only || self.is_occupied_log_odds(l.log_odds) {
                leaves.push(l);
            }
        });
        // The cells of each leaf inside the key box, per axis [from, to].
        let spans = |l: &Leaf| -> [(u32, u32); 3] {
            let side = 1u32 << (TREE_DEPTH - l.depth);
            std::array::from_fn(|a| {
                let base = u32::from(l.key.0[a]);
                (
                    base.max(u32::from(first[a])),
                    (base + side - 1).min(u32::from(last[a])),
                )
            })
        };
        let mut total = 0usize;
        for l in &leaves {
            let n = spans(l)
                .iter()
                .map(|&(f, t)| (t - f + 1) as usize)
                .product::<usize>();
            total = total.saturating_add(n);
        }
        if total > max_cells {
            return Err(Error::InvalidArgument(format!(
                "the box holds {total} finest cells, more than the {max_cells} allowed (use a smaller box)"
            )));
        }
        let mut cells = Vec::with_capacity(total);
        for l in &leaves {
            let [(x0, x1), (y0, y1), (z0, z1)] = spans(l);
            for x in x0..=x1 {
                for y in y0..=y1 {
                    for z in z0..=z1 {
                        cells.push((OcTreeKey([x as u16, y as u16, z as u16]), l.log_odds));
                    }
                }
            }
        }
        Ok(cells)
    }

    /// Centre (metres) of the node at `depth` whose lower-corner key is `key`.
    pub fn node_center(&self, key: OcTreeKey, depth: u32) -> [f64; 3] {
        self.conv.key_to_coord_at_depth(key, depth)
    }

    /// Key of a metric point, or an error naming the point when it is off the map.
    pub fn key_of(&self, what: &'static str, p: [f64; 3]) -> Result<OcTreeKey> {
        self.conv.checked_key(what, p)
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

/// Whether `updates` (distinct cells under one node at `depth`) cover every cell under
/// it with the same delta. A leaf updated so ends as one leaf again: all its cells
/// would get the same value and be pruned back into it, so it takes the update itself.
fn covers_alike(updates: &[KeyUpdate], depth: u32) -> bool {
    let cells = 1u64 << (3 * (TREE_DEPTH - depth));
    updates.len() as u64 == cells
        && updates
            .iter()
            .all(|u| u.1.to_bits() == updates[0].1.to_bits())
}

/// How many keys 0, 1, ... satisfy `pred` from the start (`pred` true then false over
/// the 2^16 keys of an axis): a bisection.
fn partition_keys(pred: impl Fn(u32) -> bool) -> u32 {
    let (mut lo, mut hi) = (0u32, 1u32 << 16);
    while lo < hi {
        let mid = (lo + hi) / 2;
        if pred(mid) {
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    lo
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::Rng;

    /// A tree with pruned regions, clamped cells, free and occupied cells, all within
    /// a 16-cell cube around the origin.
    fn random_tree(seed: u64) -> OcTree {
        let mut rng = Rng::new(seed);
        let mut tree = OcTree::new(0.1).unwrap();
        // Whole 4×4×4 and 2×2×2 blocks at the clamps (pruned into single leaves).
        for (corner, side, hit) in [
            ([0i32, 0, 0], 4, true),
            ([-4, -4, 0], 4, false),
            ([2, -2, -2], 2, true),
        ] {
            let keys: Vec<OcTreeKey> = (0..side * side * side)
                .map(|i| {
                    let c = [i % side, (i / side) % side, i / (side * side)];
                    key_at(corner[0] + c[0], corner[1] + c[1], corner[2] + c[2])
                })
                .collect();
            let delta = if hit { 100.0 } else { -100.0 };
            for &k in &keys {
                tree.update_node_log_odds(k, delta).unwrap();
            }
        }
        for _ in 0..300 {
            let k = key_at(
                rand_cell(&mut rng),
                rand_cell(&mut rng),
                rand_cell(&mut rng),
            );
            let hit = rng.unit() < 0.5;
            for _ in 0..(1 + (rng.unit() * 3.0) as usize) {
                tree.update_node(k, hit);
            }
        }
        tree
    }

    fn rand_cell(rng: &mut Rng) -> i32 {
        (rng.unit() * 16.0) as i32 - 8
    }

    fn key_at(x: i32, y: i32, z: i32) -> OcTreeKey {
        let k = |c: i32| (c + TREE_MAX_VAL) as u16;
        OcTreeKey([k(x), k(y), k(z)])
    }

    use super::super::key::TREE_MAX_VAL;

    /// OctoMap's `setNodeValueRecurs` / `updateNodeRecurs` (lazy_eval = false) for one
    /// cell, written out node by node: the cell becomes `leaf(its value)`, pruned nodes
    /// on the way are expanded, and every node on the way back is re-pruned or takes
    /// its children's maximum. The reference for the batched updates.
    fn octomap_one(tree: &mut OcTree, key: OcTreeKey, leaf: &dyn Fn(f32) -> f32) {
        let created = tree.root == NONE;
        if created {
            tree.root = tree.arena.alloc(0.0);
        }
        fn recurse(
            t: &mut OcTree,
            node: u32,
            just_created: bool,
            key: OcTreeKey,
            depth: u32,
            leaf: &dyn Fn(f32) -> f32,
        ) {
            if depth == TREE_DEPTH {
                let v = leaf(t.arena.value(node));
                t.arena.set_value(node, v);
                return;
            }
            let pos = key.child_index(TREE_DEPTH - 1 - depth);
            let mut created = false;
            if t.arena.child(node, pos).is_none() {
                if !t.arena.has_children(node) && !just_created {
                    t.arena.expand(node);
                } else {
                    t.arena.create_child(node, pos, 0.0);
                    created = true;
                }
            }
            let child = t.arena.child(node, pos).unwrap();
            recurse(t, child, created, key, depth + 1, leaf);
            if !t.prune_node(node) {
                let max = t.max_child_log_odds(node);
                t.arena.set_value(node, max);
            }
        }
        let root = tree.root;
        recurse(tree, root, created, key, 0, leaf);
    }

    /// OctoMap's `setNodeValue(key, value)`.
    fn set_one(tree: &mut OcTree, key: OcTreeKey, value: f32) {
        let value = value.clamp(tree.lo.clamp_min, tree.lo.clamp_max);
        octomap_one(tree, key, &|_| value);
    }

    /// OctoMap's `updateNode(key, delta)`: a search first, and no change at all when the
    /// leaf holding the cell is already clamped in the update's direction.
    fn update_one(tree: &mut OcTree, key: OcTreeKey, delta: f32) {
        let (lo, hi) = (tree.lo.clamp_min, tree.lo.clamp_max);
        if let Some(v) = tree.search(key, 0) {
            if (delta >= 0.0 && v >= hi) || (delta <= 0.0 && v <= lo) {
                return;
            }
        }
        octomap_one(tree, key, &|v| (v + delta).clamp(lo, hi));
    }

    /// `base` after the batch equals `base` after OctoMap's `updateNode` per cell.
    fn assert_batch_is_octomap(base: &OcTree, updates: &[KeyUpdate], case: &str) {
        let mut ours = base.clone();
        ours.apply_sorted_updates(updates);
        let mut want = base.clone();
        for &(code, d) in updates {
            update_one(&mut want, OcTreeKey::from_morton(code), d);
        }
        assert_eq!(ours.write_full_bytes(), want.write_full_bytes(), "{case}");
        assert_eq!(ours.size(), want.size(), "{case}");
    }

    fn random_keys(rng: &mut Rng, n: usize) -> Vec<OcTreeKey> {
        (0..n)
            .map(|_| key_at(rand_cell(rng), rand_cell(rng), rand_cell(rng)))
            .collect()
    }

    #[test]
    fn set_log_odds_equals_octomap_set_node_value_per_cell() {
        let mut rng = Rng::new(5);
        for seed in 0..40 {
            let base = random_tree(seed);
            let n = 1 + (rng.unit() * 200.0) as usize;
            let mut keys = random_keys(&mut rng, n);
            // Duplicates, and whole pruned blocks set to what they hold already.
            keys.extend_from_within(..n / 3);
            let (lo, hi) = base.clamping_log_odds();
            for value in [
                hi,
                lo,
                0.0,
                0.85,
                -0.4,
                f32::INFINITY,
                f32::NEG_INFINITY,
                7.0,
            ] {
                let mut ours = base.clone();
                ours.set_log_odds(&keys, value).unwrap();
                let mut want = base.clone();
                for &k in &keys {
                    set_one(&mut want, k, value);
                }
                assert_eq!(
                    ours.write_full_bytes(),
                    want.write_full_bytes(),
                    "seed {seed}, value {value}"
                );
                for &k in &keys {
                    assert_eq!(ours.search(k, 0), Some(value.clamp(lo, hi)));
                }
            }
        }
        let mut empty = OcTree::new(0.1).unwrap();
        empty.set_log_odds(&[], 1.0).unwrap();
        assert_eq!(empty.size(), 0);
        let err = empty
            .set_log_odds(&[key_at(0, 0, 0)], f32::NAN)
            .unwrap_err();
        assert!(err.to_string().contains("NaN"));
        assert_eq!(empty.size(), 0);
    }

    #[test]
    fn update_log_odds_equals_update_node_per_listed_key_and_repeat() {
        let mut rng = Rng::new(6);
        for seed in 0..40 {
            let base = random_tree(100 + seed);
            let n = 1 + (rng.unit() * 200.0) as usize;
            let mut keys = random_keys(&mut rng, n);
            keys.extend_from_within(..n / 2);
            for (delta, repeat) in [
                (0.85f32, 1u32),
                (-0.4, 3),
                (0.4, 10),
                (-1.3, 40),
                (0.0, 2),
                (1e-9, 5),
                (2.5, 0),
            ] {
                let mut ours = base.clone();
                ours.update_log_odds(&keys, delta, repeat).unwrap();
                let mut want = base.clone();
                for _ in 0..repeat {
                    for &k in &keys {
                        want.update_node_log_odds(k, delta).unwrap();
                    }
                }
                assert_eq!(
                    ours.write_full_bytes(),
                    want.write_full_bytes(),
                    "seed {seed}, delta {delta}, repeat {repeat}"
                );
            }
        }
        let mut tree = random_tree(1);
        let before = tree.write_full_bytes();
        assert!(tree
            .update_log_odds(&[key_at(0, 0, 0)], f32::INFINITY, 1)
            .is_err());
        assert!(tree
            .update_log_odds(&[key_at(0, 0, 0)], f32::NAN, 1)
            .is_err());
        assert_eq!(tree.write_full_bytes(), before);
    }

    #[test]
    fn whole_blocks_updated_alike_equal_update_node_per_cell() {
        // Batches that cover whole aligned blocks (2, 4 and 8 cells a side) with one
        // delta take the leaf shortcut; blocks off the grid, partly clamped blocks and
        // mixed deltas do not. Both must equal OctoMap's per-cell updates.
        let mut rng = Rng::new(11);
        for seed in 0..30 {
            let base = random_tree(200 + seed);
            for (side, aligned, delta) in [
                (2i32, true, -0.4f32),
                (4, true, 0.85),
                (8, true, -0.4),
                (4, false, -0.4),
                (4, true, -100.0),
                (2, true, 100.0),
            ] {
                let mut cells = std::collections::BTreeMap::new();
                for _ in 0..3 {
                    let mut corner = [0, 1, 2].map(|_| rand_cell(&mut rng));
                    if aligned {
                        corner = corner.map(|c| c.div_euclid(side) * side);
                    }
                    for i in 0..side * side * side {
                        let c = [i % side, (i / side) % side, i / (side * side)];
                        let key = key_at(corner[0] + c[0], corner[1] + c[1], corner[2] + c[2]);
                        // Every tenth block gets one cell with another delta.
                        let d = if seed % 10 == 0 && i == 0 {
                            delta * 0.5
                        } else {
                            delta
                        };
                        cells.insert(key.morton(), d);
                    }
                }
                let updates: Vec<KeyUpdate> = cells.into_iter().collect();
                assert_batch_is_octomap(
                    &base,
                    &updates,
                    &format!("seed {seed}, side {side}, aligned {aligned}, delta {delta}"),
                );
            }
        }
    }

    #[test]
    fn random_batches_equal_octomap_update_node_per_cell() {
        // Pruned leaves at every level (random_tree), clamped cells, cells the batch
        // creates; deltas of both signs, zeros and ones that clamp at once.
        let mut rng = Rng::new(12);
        let deltas = [0.85f32, -0.4, 100.0, -100.0, 0.0, -0.0, 1e-9];
        for seed in 0..60 {
            let base = random_tree(300 + seed);
            let mut cells = std::collections::BTreeMap::new();
            let one = deltas[seed as usize % deltas.len()];
            for _ in 0..(1 + (rng.unit() * 120.0) as usize) {
                let key = key_at(
                    rand_cell(&mut rng),
                    rand_cell(&mut rng),
                    rand_cell(&mut rng),
                );
                let d = if seed % 2 == 0 {
                    one
                } else {
                    deltas[(rng.unit() * deltas.len() as f64) as usize % deltas.len()]
                };
                cells.insert(key.morton(), d);
            }
            let updates: Vec<KeyUpdate> = cells.into_iter().collect();
            assert_batch_is_octomap(&base, &updates, &format!("seed {seed}"));
        }
    }

    /// Eight hits reach the upper clamp from anywhere in the clamping range (the
    /// loop the perception pipeline ran for its support voxels): same tree as one set.
    #[test]
    fn eight_hits_equal_setting_the_upper_clamp() {
        let mut rng = Rng::new(8);
        for seed in 0..20 {
            let base = random_tree(200 + seed);
            let keys = random_keys(&mut rng, 150);
            let mut looped = base.clone();
            for _ in 0..8 {
                for &k in &keys {
                    looped.update_node(k, true);
                }
            }
            let mut set = base.clone();
            set.set_log_odds(&keys, f32::INFINITY).unwrap();
            assert_eq!(
                looped.write_full_bytes(),
                set.write_full_bytes(),
                "seed {seed}"
            );
        }
    }

    #[test]
    fn finest_cells_in_box_are_the_known_cells_with_centres_inside() {
        let mut rng = Rng::new(9);
        for seed in 0..30 {
            let mut tree = random_tree(300 + seed);
            tree.prune();
            let (lo, hi): ([f64; 3], [f64; 3]) = if seed == 0 {
                // Bounds exactly on cell centres (inclusive) and on borders.
                ([-0.35, -0.4, 0.05], [0.25, 0.3, 0.4])
            } else {
                let a: [f64; 3] = std::array::from_fn(|_| rng.uniform(-1.0, 1.0));
                let b: [f64; 3] = std::array::from_fn(|_| rng.uniform(-1.0, 1.0));
                (
                    std::array::from_fn(|i| a[i].min(b[i])),
                    std::array::from_fn(|i| a[i].max(b[i])),
                )
            };
            for occupied_only in [false, true] {
                let got = tree
                    .finest_cells_in_box(lo, hi, occupied_only, 1 << 20)
                    .unwrap();
                let mut want = Vec::new();
                for x in -12..12 {
                    for y in -12..12 {
                        for z in -12..12 {
                            let key = key_at(x, y, z);
                            let c = tree.node_center(key, TREE_DEPTH);
                            let inside = (0..3).all(|a| lo[a] <= c[a] && c[a] <= hi[a]);
                            if let (true, Some(l)) = (inside, tree.search(key, 0)) {
                                if !occupied_only || tree.is_occupied_log_odds(l) {
                                    want.push((key.morton(), l));
                                }
                            }
                        }
                    }
                }
                let mut got: Vec<(u64, f32)> = got.iter().map(|&(k, l)| (k.morton(), l)).collect();
                got.sort_by_key(|&(m, _)| m);
                want.sort_by_key(|&(m, _)| m);
                assert_eq!(got, want, "seed {seed}, box {lo:?} {hi:?}");
            }
        }
        let tree = random_tree(1);
        assert!(tree
            .finest_cells_in_box([0.5; 3], [0.4; 3], false, 10)
            .unwrap()
            .is_empty());
        let err = tree
            .finest_cells_in_box([-1.0; 3], [1.0; 3], false, 10)
            .unwrap_err()
            .to_string();
        assert!(err.contains("more than the 10 allowed"), "{err}");
        assert!(tree
            .finest_cells_in_box([f64::NAN, 0.0, 0.0], [1.0; 3], false, 10)
            .is_err());
        // A box reaching beyond the map is cut at its edge.
        let all = tree
            .finest_cells_in_box([f64::NEG_INFINITY; 3], [f64::INFINITY; 3], false, 1 << 20)
            .unwrap();
        let known = tree
            .finest_cells_in_box([-2.0; 3], [2.0; 3], false, 1 << 20)
            .unwrap();
        assert_eq!(all.len(), known.len());
    }
}
