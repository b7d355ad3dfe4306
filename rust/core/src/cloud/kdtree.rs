//! A static k-d tree over 3D points for k-nearest-neighbour queries: built once
//! (splits on the widest axis at the median rounded to whole leaves, so that leaves
//! hold sixteen points), queried many times, from any number of threads.

/// A leaf holds at most this many points.
const LEAF_SIZE: usize = 16;

/// Up to this k, k-nearest-neighbour queries keep their best in a sorted array
/// (fastest for small k); beyond it, in a heap.
const SORTED_K: usize = 48;

/// What a node is, as the searches see it.
#[derive(Clone, Copy, Debug)]
enum Node {
    /// The points of `blocks[block]`.
    Leaf { block: u32 },
    /// Points with `axis` coordinate below `value` go left (ties may go either way).
    Split {
        axis: u8,
        value: f64,
        left: u32,
        right: u32,
    },
}

/// A node in 16 bytes (four to a cache line), in depth-first order: a split's left
/// child is the node after it.
#[derive(Clone, Copy, Debug)]
struct Packed {
    /// The split value (unused in a leaf).
    value: f64,
    /// A split's right child; a leaf's block.
    link: u32,
    /// The split axis, or [`LEAF`].
    axis: u32,
}

/// [`Packed::axis`] of a leaf.
const LEAF: u32 = 3;

/// A k-d tree over 3D points, for nearest and k-nearest neighbour queries.
#[derive(Clone, Debug)]
pub struct KdTree {
    points: Vec<[f64; 3]>,
    /// Every leaf's points coordinate by coordinate, for distances a leaf at a time.
    blocks: Vec<Block>,
    nodes: Vec<Packed>,
}

/// A leaf's points, one array per coordinate, in increasing index (so that the first
/// of equally near points is the lowest index); unused slots hold infinities, which
/// are never nearer than anything.
#[derive(Clone, Copy, Debug)]
struct Block {
    coordinates: [[f64; LEAF_SIZE]; 3],
    indices: [u32; LEAF_SIZE],
}

impl Block {
    /// Squared distances from `q` to the block's points (infinity in unused slots), bit
    /// for bit as `geometry::distance_squared` gives them (ICP compares the two).
    #[inline(always)]
    fn distances(&self, q: &[f64; 3]) -> [f64; LEAF_SIZE] {
        let mut d = [0.0; LEAF_SIZE];
        for (a, axis) in self.coordinates.iter().enumerate() {
            for (d, &c) in d.iter_mut().zip(axis) {
                let e = c - q[a];
                *d += e * e;
            }
        }
        d
    }
}

impl KdTree {
    /// Build over `points` (they are copied). Points must be finite: a NaN coordinate
    /// can hide other points from searches.
    pub fn new(points: &[[f64; 3]]) -> Self {
        let mut tree = KdTree {
            points: points.to_vec(),
            blocks: Vec::new(),
            nodes: Vec::new(),
        };
        if !points.is_empty() {
            let mut order: Vec<u32> = (0..points.len() as u32).collect();
            tree.build(&mut order);
        }
        tree
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// Whether the tree holds no points.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The points, in the order they were given (or in leaf order, after
    /// [`Self::into_leaf_order`]).
    pub fn points(&self) -> &[[f64; 3]] {
        &self.points
    }

    /// The same tree with its points renumbered in leaf order (depth first, so that
    /// points near in space are near in memory); returns it with `order`, where
    /// `order[new] = old`.
    pub fn into_leaf_order(mut self) -> (Self, Vec<u32>) {
        let mut order = Vec::with_capacity(self.points.len());
        for block in &mut self.blocks {
            // A leaf's indices ascend, and so do their new numbers.
            for index in block.indices.iter_mut().filter(|i| **i != u32::MAX) {
                order.push(*index);
                *index = (order.len() - 1) as u32;
            }
        }
        self.points = order.iter().map(|&i| self.points[i as usize]).collect();
        (self, order)
    }

    /// Build the subtree over the points `order` names (permuting it); returns its
    /// node index.
    fn build(&mut self, order: &mut [u32]) -> u32 {
        let id = self.nodes.len() as u32;
        if order.len() <= LEAF_SIZE {
            let mut block = Block {
                coordinates: [[f64::INFINITY; LEAF_SIZE]; 3],
                indices: [u32::MAX; LEAF_SIZE],
            };
            order.sort_unstable();
            for (slot, &i) in order.iter().enumerate() {
                for a in 0..3 {
                    block.coordinates[a][slot] = self.points[i as usize][a];
                }
                block.indices[slot] = i;
            }
            self.nodes.push(Packed {
                value: 0.0,
                link: self.blocks.len() as u32,
                axis: LEAF,
            });
            self.blocks.push(block);
            return id;
        }
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for &i in order.iter() {
            let p = self.points[i as usize];
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        let axis = (0..3)
            .max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b])))
            .unwrap_or(0);
        // Half the points, rounded up to whole leaves, so that leaves are full.
        let mid = order.len().div_ceil(2).div_ceil(LEAF_SIZE) * LEAF_SIZE;
        let pts = &self.points;
        order.select_nth_unstable_by(mid, |&a, &b| {
            pts[a as usize][axis].total_cmp(&pts[b as usize][axis])
        });
        let value = self.points[order[mid] as usize][axis];
        self.nodes.push(Packed {
            value,
            link: 0, // the right child, known below
            axis: axis as u32,
        });
        let (left, right) = order.split_at_mut(mid);
        self.build(left);
        let right = self.build(right);
        self.nodes[id as usize].link = right;
        id
    }

    /// Node `id` unpacked.
    #[inline(always)]
    fn node(&self, id: u32) -> Node {
        let n = self.nodes[id as usize];
        if n.axis == LEAF {
            Node::Leaf { block: n.link }
        } else {
            Node::Split {
                axis: n.axis as u8,
                value: n.value,
                left: id + 1,
                right: n.link,
            }
        }
    }

    /// The nearest point to `q` as (squared distance, index); ties go to the lower index.
    pub fn nearest(&self, q: [f64; 3]) -> Option<(f64, u32)> {
        self.nearest_within(q, f64::INFINITY)
    }

    /// The nearest point within squared distance `limit` (inclusive) of `q`, if any
    /// (ties go to the lower index). The limit prunes the walk, which matters for
    /// points with no near neighbour.
    pub fn nearest_within(&self, q: [f64; 3], limit: f64) -> Option<(f64, u32)> {
        let [best] = self.nearest_k::<1>(&q, limit);
        (best.1 != u32::MAX).then_some(best)
    }

    /// The `k` nearest points to `q` as (squared distance, index), nearest first
    /// (ties by index), leaving out the point with index `exclude` (a query point's
    /// own entry). O(k log k) beyond the points visited, for any k.
    pub fn knn(&self, q: [f64; 3], k: usize, exclude: Option<u32>, out: &mut Vec<(f64, u32)>) {
        out.clear();
        if k == 0 || self.nodes.is_empty() {
            return;
        }
        if k <= SORTED_K {
            self.search(0, q, k, exclude, out);
            return;
        }
        let mut heap = std::collections::BinaryHeap::with_capacity(k.min(self.len()));
        self.search(0, q, k, exclude, &mut heap);
        out.extend(
            heap.into_sorted_vec()
                .into_iter()
                .map(|(d, i)| (f64::from_bits(d), i)),
        );
    }

    /// The up to `k` nearest points within squared distance `limit` (inclusive) of
    /// `q`, as [`Self::knn`] gives them (nearest first, ties by index).
    pub fn knn_within(&self, q: [f64; 3], k: usize, limit: f64, out: &mut Vec<(f64, u32)>) {
        out.clear();
        if k == 0 || self.nodes.is_empty() {
            return;
        }
        match k {
            1 => self.knn_fixed::<1>(q, k, limit, out),
            2 => self.knn_fixed::<2>(q, k, limit, out),
            3 | 4 => self.knn_fixed::<4>(q, k, limit, out),
            5..=8 => self.knn_fixed::<8>(q, k, limit, out),
            _ => self.search(0, q, k, None, &mut Bounded { kept: out, limit }),
        }
    }

    /// The `K` nearest within squared distance `limit` (inclusive) of `q`, nearest
    /// first (ties by index), kept in a fixed array on the stack with no call per
    /// candidate (the hot path of ICP's pairing); slots not filled hold (`limit`,
    /// `u32::MAX`).
    #[inline]
    pub(crate) fn nearest_k<const K: usize>(&self, q: &[f64; 3], limit: f64) -> [(f64, u32); K] {
        let mut best = [(limit, u32::MAX); K];
        if !self.nodes.is_empty() {
            self.search_fixed(0, q, &mut best);
        }
        best
    }

    /// [`Self::knn_within`] for `k ≤ K`, through [`Self::nearest_k`].
    fn knn_fixed<const K: usize>(
        &self,
        q: [f64; 3],
        k: usize,
        limit: f64,
        out: &mut Vec<(f64, u32)>,
    ) {
        let best = self.nearest_k::<K>(&q, limit);
        out.extend(best.iter().take(k).filter(|b| b.1 != u32::MAX));
    }

    /// Depth-first search gathering the `K` nearest within `best[K - 1]`'s distance, in
    /// order (ties by index). Unfilled entries hold index `u32::MAX` at the limit, so
    /// any point within the limit displaces them.
    fn search_fixed<const K: usize>(&self, node: u32, q: &[f64; 3], best: &mut [(f64, u32); K]) {
        let n = self.nodes[node as usize];
        if n.axis == LEAF {
            let block = &self.blocks[n.link as usize];
            let d = block.distances(q);
            let worst = best[K - 1].0;
            // Which slots can enter, found without a branch per slot (NaN never does).
            let mut mask = 0u32;
            for (slot, &v) in d.iter().enumerate() {
                mask |= u32::from(v <= worst) << slot;
            }
            while mask != 0 {
                let slot = mask.trailing_zeros() as usize;
                mask &= mask - 1;
                let entry = (d[slot], block.indices[slot]);
                if entry < best[K - 1] {
                    let mut at = K - 1;
                    while at > 0 && best[at - 1] > entry {
                        best[at] = best[at - 1];
                        at -= 1;
                    }
                    best[at] = entry;
                }
            }
            return;
        }
        let diff = q[n.axis as usize] - n.value;
        let (near, far) = if diff < 0.0 {
            (node + 1, n.link)
        } else {
            (n.link, node + 1)
        };
        self.search_fixed(near, q, best);
        if diff * diff <= best[K - 1].0 {
            self.search_fixed(far, q, best);
        }
    }

    /// Depth-first search for the `k` nearest to `q`, gathering them in `best`: the
    /// far side of a split is visited while it can hold a point nearer than the
    /// worst kept.
    fn search<C: Candidates>(
        &self,
        node: u32,
        q: [f64; 3],
        k: usize,
        exclude: Option<u32>,
        best: &mut C,
    ) {
        match self.node(node) {
            Node::Leaf { block } => {
                let block = &self.blocks[block as usize];
                let d = block.distances(&q);
                let worst = best.worst(k).unwrap_or(f64::INFINITY);
                for (&d, &i) in d.iter().zip(&block.indices) {
                    // NaN distances are offered too, as one by one.
                    let within = d.partial_cmp(&worst) != Some(std::cmp::Ordering::Greater);
                    if within && i != u32::MAX && Some(i) != exclude {
                        best.offer(d, i, k);
                    }
                }
            }
            Node::Split {
                axis,
                value,
                left,
                right,
            } => {
                let diff = q[axis as usize] - value;
                let (near, far) = if diff < 0.0 {
                    (left, right)
                } else {
                    (right, left)
                };
                self.search(near, q, k, exclude, best);
                if best.worst(k).is_none_or(|worst| diff * diff <= worst) {
                    self.search(far, q, k, exclude, best);
                }
            }
        }
    }
}

/// The k best candidates of a search so far.
trait Candidates {
    /// Keep (squared distance `d`, index `i`) if it is among the `k` best so far
    /// (ties by index).
    fn offer(&mut self, d: f64, i: u32, k: usize);
    /// The worst kept squared distance once `k` are kept; `None` before.
    fn worst(&self, k: usize) -> Option<f64>;
}

/// For small k: the best in order in a vector, inserted by shifting by hand (no
/// heap, no memmove call).
impl Candidates for Vec<(f64, u32)> {
    fn offer(&mut self, d: f64, i: u32, k: usize) {
        let full = self.len() == k;
        if full && (d, i) >= self[k - 1] {
            return;
        }
        if !full {
            self.push((d, i));
        }
        let mut at = self.len() - 1;
        while at > 0 && self[at - 1] > (d, i) {
            self[at] = self[at - 1];
            at -= 1;
        }
        self[at] = (d, i);
    }

    fn worst(&self, k: usize) -> Option<f64> {
        (self.len() == k).then(|| self[k - 1].0)
    }
}

/// The sorted array, taking only points within `limit` and pruning by it until full.
struct Bounded<'a> {
    kept: &'a mut Vec<(f64, u32)>,
    limit: f64,
}

impl Candidates for Bounded<'_> {
    fn offer(&mut self, d: f64, i: u32, k: usize) {
        if d <= self.limit {
            self.kept.offer(d, i, k);
        }
    }

    fn worst(&self, k: usize) -> Option<f64> {
        Some(self.kept.worst(k).unwrap_or(self.limit))
    }
}

/// For large k: a max-heap of (distance bits, index), where an insertion costs
/// O(log k) instead of shifting up to k entries (which made k near N quadratic per
/// query). Squared distances are never negative, so their bits order as the numbers do.
impl Candidates for std::collections::BinaryHeap<(u64, u32)> {
    fn offer(&mut self, d: f64, i: u32, k: usize) {
        let entry = (d.to_bits(), i);
        if self.len() < k {
            self.push(entry);
        } else if self.peek().is_some_and(|&worst| entry < worst) {
            self.pop();
            self.push(entry);
        }
    }

    fn worst(&self, k: usize) -> Option<f64> {
        if self.len() < k {
            return None;
        }
        self.peek().map(|&(d, _)| f64::from_bits(d))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::distance_squared;

    #[test]
    fn nearest_equals_brute_force() {
        let mut s = 777u64;
        let mut rnd = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let pts: Vec<[f64; 3]> = (0..3000)
            .map(|_| [rnd(), rnd() * 2.0, rnd() * 0.05])
            .collect();
        let tree = KdTree::new(&pts);
        for _ in 0..500 {
            let q = [rnd() * 1.2 - 0.1, rnd() * 2.2 - 0.1, rnd() * 0.3 - 0.1];
            let brute = pts
                .iter()
                .enumerate()
                .map(|(i, p)| {
                    (
                        (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2),
                        i as u32,
                    )
                })
                .min_by(|a, b| a.partial_cmp(b).unwrap());
            assert_eq!(tree.nearest(q), brute);
            // Within a limit: the same point when it is inside, else none.
            for limit in [1e-4, 4e-3, 0.05] {
                let expected = brute.filter(|&(d2, _)| d2 <= limit);
                assert_eq!(tree.nearest_within(q, limit), expected, "{q:?} {limit}");
            }
        }
    }

    /// Renumbered in leaf order, a tree answers as one built over its points in that
    /// order: the same points, at their new numbers, by brute force.
    #[test]
    fn a_tree_in_leaf_order_equals_brute_force_over_the_reordered_points() {
        let mut rng = crate::synthetic::Rng::new(4242);
        let mut rnd = || rng.uniform(0.0, 1.0);
        // A coarse grid, so that equally near points (ties by index) are common.
        let pts: Vec<[f64; 3]> = (0..1500)
            .map(|_| {
                [
                    (rnd() * 20.0).floor(),
                    (rnd() * 20.0).floor(),
                    (rnd() * 3.0).floor(),
                ]
            })
            .collect();
        let (tree, order) = KdTree::new(&pts).into_leaf_order();
        let mut seen = order.clone();
        seen.sort_unstable();
        assert_eq!(seen, (0..pts.len() as u32).collect::<Vec<_>>());
        let reordered: Vec<[f64; 3]> = order.iter().map(|&i| pts[i as usize]).collect();
        assert_eq!(tree.points(), &reordered[..]);
        let mut got = Vec::new();
        for _ in 0..300 {
            let q = [rnd() * 22.0 - 1.0, rnd() * 22.0 - 1.0, rnd() * 5.0 - 1.0];
            let mut brute: Vec<(f64, u32)> = reordered
                .iter()
                .enumerate()
                .map(|(i, p)| (distance_squared(&q, p), i as u32))
                .collect();
            brute.sort_by(|a, b| a.partial_cmp(b).unwrap());
            for k in [1, 2, 4, 9] {
                tree.knn_within(q, k, 2.5, &mut got);
                let expected: Vec<_> = brute
                    .iter()
                    .copied()
                    .filter(|e| e.0 <= 2.5)
                    .take(k)
                    .collect();
                assert_eq!(got, expected, "{q:?} {k}");
            }
        }
    }

    /// Every tree size up to a few leaves (leaves are filled to sixteen, the last one
    /// partly): each point is found, with its nearest others in order.
    #[test]
    fn small_trees_of_every_size_equal_brute_force() {
        let mut rng = crate::synthetic::Rng::new(4);
        let mut out = Vec::new();
        for n in 1..=4 * LEAF_SIZE + 1 {
            let points: Vec<[f64; 3]> = (0..n)
                .map(|_| {
                    [
                        rng.uniform(0.0, 1.0),
                        rng.uniform(0.0, 1.0),
                        rng.uniform(0.0, 0.1),
                    ]
                })
                .collect();
            let tree = KdTree::new(&points);
            for (i, p) in points.iter().enumerate() {
                assert_eq!(tree.nearest(*p), Some((0.0, i as u32)), "n = {n}");
                let mut brute: Vec<(f64, u32)> = points
                    .iter()
                    .enumerate()
                    .filter(|&(j, _)| j != i)
                    .map(|(j, q)| (distance_squared(p, q), j as u32))
                    .collect();
                brute.sort_by(|a, b| a.partial_cmp(b).unwrap());
                tree.knn(*p, 5, Some(i as u32), &mut out);
                assert_eq!(out, brute[..brute.len().min(5)], "n = {n}");
            }
        }
    }

    /// A NaN query finds nothing nearest, and k-nearest lists the points (at NaN), as
    /// a scan one point at a time does.
    #[test]
    fn nan_queries_find_no_nearest() {
        let points: Vec<[f64; 3]> = (0..20).map(|i| [i as f64, 0.0, 0.0]).collect();
        let tree = KdTree::new(&points);
        let q = [f64::NAN, 0.0, 0.0];
        assert_eq!(tree.nearest(q), None);
        assert_eq!(tree.nearest_within(q, f64::INFINITY), None);
        let mut out = Vec::new();
        tree.knn(q, 3, None, &mut out);
        assert_eq!(out.len(), 3);
        assert!(out.iter().all(|(d, _)| d.is_nan()));
    }

    #[test]
    fn knn_within_equals_brute_force() {
        let mut rng = crate::synthetic::Rng::new(11);
        let scattered: Vec<[f64; 3]> = (0..700)
            .map(|_| {
                [
                    rng.uniform(-1.0, 1.0),
                    rng.uniform(-1.0, 1.0),
                    rng.uniform(-0.2, 0.2),
                ]
            })
            .collect();
        // Points on a coarse lattice, many twice: equal distances everywhere, so the
        // order among equals (by index) is tested too.
        let lattice: Vec<[f64; 3]> = (0..900)
            .map(|_| [0, 1, 2].map(|_| 0.1 * (rng.uniform(-4.0, 4.0).round())))
            .collect();
        let mut out = Vec::new();
        for points in [scattered, lattice] {
            let tree = KdTree::new(&points);
            for round in 0..800 {
                let q = if round % 2 == 0 {
                    [
                        rng.uniform(-1.3, 1.3),
                        rng.uniform(-1.3, 1.3),
                        rng.uniform(-0.5, 0.5),
                    ]
                } else {
                    [0, 1, 2].map(|_| 0.05 * (rng.uniform(-9.0, 9.0).round()))
                };
                // Some limits exactly at a point's distance (the limit is inclusive), one
                // without any.
                let limit = match round % 5 {
                    0 => distance_squared(&points[round % points.len()], &q),
                    1 if round % 3 == 0 => f64::INFINITY,
                    _ => rng.uniform(0.0, 0.2),
                };
                // Every size of the searches' fixed arrays, and the general search.
                let k = [1, 2, 3, 4, 5, 6, 7, 8, 9, 20][round % 10];
                let mut all: Vec<(f64, u32)> = points
                    .iter()
                    .enumerate()
                    .map(|(i, p)| (distance_squared(p, &q), i as u32))
                    .filter(|&(d, _)| d <= limit)
                    .collect();
                all.sort_by(|a, b| a.partial_cmp(b).unwrap());
                tree.knn_within(q, k, limit, &mut out);
                assert_eq!(out, all[..all.len().min(k)], "k = {k}");
                assert_eq!(tree.nearest_within(q, limit), all.first().copied());
            }
            let nan = [f64::NAN, 0.0, 0.0];
            for k in [1, 2, 4, 8, 9] {
                tree.knn_within(nan, k, 1.0, &mut out);
                assert!(out.is_empty());
            }
            assert_eq!(tree.nearest_within(nan, f64::INFINITY), None);
        }
    }

    #[test]
    fn knn_equals_brute_force() {
        let mut s = 12345u64;
        let mut rnd = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut pts: Vec<[f64; 3]> = (0..2000).map(|_| [rnd(), rnd(), rnd() * 0.1]).collect();
        let duplicates = pts[..50].to_vec();
        pts.extend(duplicates);
        let tree = KdTree::new(&pts);
        let mut out = Vec::new();
        for qi in 0..290 {
            let q = pts[qi * 7];
            let mut brute: Vec<(f64, u32)> = pts
                .iter()
                .enumerate()
                .filter(|&(i, _)| i != qi * 7)
                .map(|(i, p)| {
                    (
                        (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2),
                        i as u32,
                    )
                })
                .collect();
            brute.sort_by(|a, b| a.partial_cmp(b).unwrap());
            // The sorted array (k = 10) and the heap (k beyond SORTED_K, up to all).
            for k in [10, SORTED_K + 1, 300, pts.len() - 1, pts.len() + 5] {
                tree.knn(q, k, Some((qi * 7) as u32), &mut out);
                assert_eq!(out, brute[..k.min(brute.len())], "k = {k}");
            }
        }
    }
}
