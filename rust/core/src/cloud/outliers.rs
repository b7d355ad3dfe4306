//! Statistical outlier removal, as PCL defines it: for every point the mean distance
//! to its k nearest neighbours (itself excluded); a point is an outlier when that mean
//! exceeds μ + std_ratio·σ over all points (σ the sample standard deviation).

use super::kdtree::KdTree;
use crate::error::{Error, Result};
use crate::floor::floor_i64;
use crate::threads;

/// Statistical outlier removal's parameters (PCL's `StatisticalOutlierRemoval`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OutlierParams {
    /// Neighbours per point.
    pub k: usize,
    /// How many standard deviations above the mean a point's distance may be.
    pub std_ratio: f64,
}

impl Default for OutlierParams {
    fn default() -> Self {
        OutlierParams {
            k: 20,
            std_ratio: 2.0,
        }
    }
}

/// Indices of the inliers (ascending) and every point's mean neighbour distance.
pub fn statistical_outliers(
    points: &[[f64; 3]],
    params: OutlierParams,
) -> Result<(Vec<u32>, Vec<f64>)> {
    statistical_outliers_interruptible(points, params, &mut || false)?
        .ok_or_else(|| Error::InvalidArgument("outlier removal was interrupted".into()))
}

/// [`statistical_outliers`], asking `interrupt` on the calling thread between rounds
/// of the neighbour search (sized so a round takes milliseconds whatever `k` is);
/// `Ok(None)` when it asked to stop.
pub fn statistical_outliers_interruptible(
    points: &[[f64; 3]],
    params: OutlierParams,
    interrupt: &mut threads::Interrupt<'_>,
) -> Result<Option<(Vec<u32>, Vec<f64>)>> {
    if params.k == 0 || !params.std_ratio.is_finite() {
        return Err(Error::InvalidArgument(format!(
            "need k >= 1 and a finite std_ratio, got k = {}, std_ratio = {}",
            params.k, params.std_ratio
        )));
    }
    if points.len() <= params.k {
        return Err(Error::InvalidArgument(format!(
            "statistical outlier removal needs more points than k = {} neighbours, got {}",
            params.k,
            points.len()
        )));
    }
    crate::geometry::check_finite(points, "point")?;
    // Squared distances must neither overflow nor underflow: a cloud far from unit
    // size is scaled by a power of two first (exact, and distances scale with it).
    let largest = points
        .iter()
        .flat_map(|p| p.iter())
        .fold(0.0f64, |m, c| m.max(c.abs()));
    let scale = if largest > 1e100 || (largest > 0.0 && largest < 1e-100) {
        crate::geometry::unit_power_of_two(largest)
    } else {
        1.0
    };
    let found = if scale == 1.0 {
        mean_knn_distances(points, params.k, interrupt)
    } else {
        let scaled: Vec<[f64; 3]> = points.iter().map(|p| p.map(|c| c * scale)).collect();
        mean_knn_distances(&scaled, params.k, interrupt)
    };
    let Some(mut mean_distance) = found else {
        return Ok(None);
    };
    let n = mean_distance.len() as f64;
    let mean = mean_distance.iter().sum::<f64>() / n;
    let variance = mean_distance
        .iter()
        .map(|d| (d - mean).powi(2))
        .sum::<f64>()
        / (n - 1.0);
    let threshold = mean + params.std_ratio * variance.sqrt();
    let inliers = (0..points.len() as u32)
        .filter(|&i| mean_distance[i as usize] <= threshold)
        .collect();
    if scale != 1.0 {
        for d in &mut mean_distance {
            *d /= scale;
        }
    }
    Ok(Some((inliers, mean_distance)))
}

/// Beyond this many neighbours the k-d tree answers (see `mean_knn_distances`).
const LARGE_K: usize = 256;

/// Every point's mean distance to its `k` nearest neighbours (itself excluded).
///
/// Points are bucketed in a dense grid of cubic cells (`CellGrid`). The candidates
/// of a point are the points of the (2r+1)³ cells around its own; every other point
/// lies beyond the nearest face of that block (a face on the grid's border has none
/// behind it), so when the k nearest candidates lie within that distance they are
/// the k nearest points. With cells about the k-th neighbour distance, r = 1 (one
/// block shared by all the points of a cell) settles nearly every point; the rest
/// widen r until their answer is proven. The cell edge is the 90th percentile of the
/// k-th neighbour distance of a sample, measured exactly on a first, coarser grid.
/// Clouds whose density a grid of at most 16 cells per point cannot resolve (far
/// apart clusters, heaps of duplicates) go to a k-d tree instead.
fn mean_knn_distances(
    points: &[[f64; 3]],
    k: usize,
    interrupt: &mut threads::Interrupt<'_>,
) -> Option<Vec<f64>> {
    let n = points.len();
    let (lo, hi) = crate::geometry::bounds(points);
    let extent = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
    if extent == 0.0 {
        return Some(vec![0.0; n]); // every point is the same point
    }
    if k > LARGE_K {
        // Neighbourhoods that large span most of the cloud: the grid's cells would hold
        // thousands of points each (one cell a round of minutes); the k-d tree's rounds
        // are a few points each.
        return kd_tree_means(points, k, interrupt);
    }
    let (Some(first_cell), Some(finest_cell)) = (
        coarse_cell(lo, hi, extent, 4 * n),
        coarse_cell(lo, hi, extent, 16 * n),
    ) else {
        return kd_tree_means(points, k, interrupt);
    };
    let Some(first) = CellGrid::new(points, first_cell, lo, hi) else {
        return kd_tree_means(points, k, interrupt);
    };
    let mut search = Searcher::new(first_cell);
    let step = (n / 64).max(1);
    let mut sample: Vec<f64> = Vec::with_capacity(n / step + 1);
    for i in (0..n).step_by(step) {
        let c = first.cell_of(&points[i]);
        sample.push(search.nearest(&first, points[i], c, k, 1).1.sqrt());
        if interrupt() {
            return None; // with k near N each of these searches is long
        }
    }
    sample.sort_unstable_by(f64::total_cmp);
    let typical = sample[(sample.len() * 9 / 10).min(sample.len() - 1)];
    if typical < finest_cell / 4.0 {
        return kd_tree_means(points, k, interrupt);
    }
    let cell = typical.max(finest_cell);
    let grid = if cell > first_cell / 1.5 && cell < first_cell * 1.5 {
        first
    } else {
        match CellGrid::new(points, cell, lo, hi) {
            Some(grid) => grid,
            None => return kd_tree_means(points, k, interrupt),
        }
    };
    let occupied: Vec<u32> = (0..grid.cells() as u32)
        .filter(|&j| grid.starts[j as usize] < grid.starts[j as usize + 1])
        .collect();
    let chunks: Vec<&[u32]> = occupied
        .chunks(threads::items_per_part(k, 16384, 256))
        .collect();
    let parts = threads::map_parts_interruptible(
        &chunks,
        |chunk| {
            let mut search = Searcher::new(grid.cell);
            let mut results: Vec<(u32, f64)> = Vec::new();
            for &j in chunk.iter() {
                let c = grid.coords_of(j as usize);
                grid.gather(c, 1, &mut search.block);
                let (s, e) = (grid.starts[j as usize], grid.starts[j as usize + 1]);
                for at in s as usize..e as usize {
                    let q = grid.position(at);
                    let sum = match search.settle(&grid, q, c, 1, k) {
                        Some((sum, _)) => sum,
                        None => search.nearest(&grid, q, c, k, 2).0,
                    };
                    results.push((grid.order[at], sum / k as f64));
                }
            }
            results
        },
        interrupt,
    )?;
    let mut mean_distance = vec![0.0; n];
    for (i, m) in parts.into_iter().flatten() {
        mean_distance[i as usize] = m;
    }
    Some(mean_distance)
}

/// The same answer from a k-d tree, for clouds a grid cannot serve.
fn kd_tree_means(
    points: &[[f64; 3]],
    k: usize,
    interrupt: &mut threads::Interrupt<'_>,
) -> Option<Vec<f64>> {
    let tree = KdTree::new(points);
    let indices: Vec<u32> = (0..points.len() as u32).collect();
    let chunks: Vec<&[u32]> = indices
        .chunks(threads::items_per_part(k, 65536, 1024))
        .collect();
    let parts = threads::map_parts_interruptible(
        &chunks,
        |chunk| {
            let mut nn = Vec::with_capacity(k);
            chunk
                .iter()
                .map(|&i| {
                    tree.knn(points[i as usize], k, Some(i), &mut nn);
                    nn.iter().map(|&(d2, _)| d2.sqrt()).sum::<f64>() / k as f64
                })
                .collect::<Vec<f64>>()
        },
        interrupt,
    )?;
    Some(parts.concat())
}

/// The smallest cell edge (the box's longest side halved again and again) for which
/// the box needs at most `max_cells` cells; `None` when cells that small cannot be
/// told apart in floating point at the box's coordinates.
fn coarse_cell(lo: [f64; 3], hi: [f64; 3], extent: f64, max_cells: usize) -> Option<f64> {
    let mut cell = extent;
    while cell_count(lo, hi, cell / 2.0).is_some_and(|c| c <= max_cells) {
        cell /= 2.0;
    }
    cell_count(lo, hi, cell).map(|_| cell)
}

/// Cells of edge `cell` spanning the box, `None` beyond exact floor range.
fn cell_count(lo: [f64; 3], hi: [f64; 3], cell: f64) -> Option<usize> {
    let inv = 1.0 / cell;
    let mut count = 1usize;
    for a in 0..3 {
        let (l, h) = (lo[a] * inv, hi[a] * inv);
        // Beyond 2^50 cell coordinates a cell is a few ulps wide: no proof holds there.
        if !(l.abs() < 1e15 && h.abs() < 1e15) {
            return None;
        }
        let span = (floor_i64(h) - floor_i64(l) + 1) as usize;
        count = count.saturating_mul(span);
    }
    Some(count)
}

/// Points bucketed in a dense box of cubic cells: the points of cell `j` are
/// `order[starts[j]..starts[j + 1]]`, their positions `coords[..][starts[j]..]`
/// (one array per axis). Cells are numbered with z fastest, so the cells of a
/// z-column are one contiguous run of points.
struct CellGrid {
    cell: f64,
    inv: f64,
    /// Cell coordinates of the box's first cell.
    origin: [i64; 3],
    dims: [i64; 3],
    starts: Vec<u32>,
    order: Vec<u32>,
    coords: [Vec<f64>; 3],
}

impl CellGrid {
    /// Counting sort of the points into cells of edge `cell` over the box `[lo, hi]`
    /// that holds them all; `None` when that box would need more than 16 cells per
    /// point.
    fn new(points: &[[f64; 3]], cell: f64, lo: [f64; 3], hi: [f64; 3]) -> Option<Self> {
        if !(cell.is_finite() && cell > 0.0) {
            return None;
        }
        if cell_count(lo, hi, cell)? > 16 * points.len() + 64 {
            return None;
        }
        let inv = 1.0 / cell;
        let origin = lo.map(|l| floor_i64(l * inv));
        let top = hi.map(|h| floor_i64(h * inv));
        let dims = [0, 1, 2].map(|a| top[a] - origin[a] + 1);
        let mut grid = CellGrid {
            cell,
            inv,
            origin,
            dims,
            starts: vec![0; (dims[0] * dims[1] * dims[2]) as usize + 1],
            order: vec![0; points.len()],
            coords: Default::default(),
        };
        let slots: Vec<u32> = points
            .iter()
            .map(|p| grid.index(grid.cell_of(p)) as u32)
            .collect();
        for &j in &slots {
            grid.starts[j as usize] += 1;
        }
        let mut end = 0;
        for s in grid.starts.iter_mut() {
            end += *s;
            *s = end;
        }
        // Filling from the back leaves every `starts[j]` at its cell's first point.
        for (i, &j) in slots.iter().enumerate().rev() {
            grid.starts[j as usize] -= 1;
            grid.order[grid.starts[j as usize] as usize] = i as u32;
        }
        grid.coords =
            [0, 1, 2].map(|a| grid.order.iter().map(|&i| points[i as usize][a]).collect());
        Some(grid)
    }

    fn cells(&self) -> usize {
        self.starts.len() - 1
    }

    /// The cell of a point of the box, relative to the box's first cell.
    fn cell_of(&self, p: &[f64; 3]) -> [i64; 3] {
        [0, 1, 2].map(|a| floor_i64(p[a] * self.inv) - self.origin[a])
    }

    fn index(&self, c: [i64; 3]) -> usize {
        ((c[0] * self.dims[1] + c[1]) * self.dims[2] + c[2]) as usize
    }

    fn coords_of(&self, j: usize) -> [i64; 3] {
        let j = j as i64;
        let column = j / self.dims[2];
        [
            column / self.dims[1],
            column % self.dims[1],
            j % self.dims[2],
        ]
    }

    fn position(&self, at: usize) -> [f64; 3] {
        [self.coords[0][at], self.coords[1][at], self.coords[2][at]]
    }

    /// The positions of the points within `r` cells of cell `c`.
    fn gather(&self, c: [i64; 3], r: i64, out: &mut Block) {
        for a in &mut out.coords {
            a.clear();
        }
        let lo = c.map(|x| (x - r).max(0));
        let hi = [0, 1, 2].map(|a| (c[a] + r).min(self.dims[a] - 1));
        for x in lo[0]..=hi[0] {
            for y in lo[1]..=hi[1] {
                let s = self.starts[self.index([x, y, lo[2]])] as usize;
                let e = self.starts[self.index([x, y, hi[2]]) + 1] as usize;
                for a in 0..3 {
                    out.coords[a].extend_from_slice(&self.coords[a][s..e]);
                }
            }
        }
    }

    /// How far `q` (in cell `c`) is from every point outside the cells within `r`
    /// of `c`, at least (a side on the box's border has no points behind it).
    fn reach(&self, q: [f64; 3], c: [i64; 3], r: i64) -> f64 {
        let mut reach = f64::INFINITY;
        for a in 0..3 {
            if c[a] - r > 0 {
                reach = reach.min(q[a] - (self.origin[a] + c[a] - r) as f64 * self.cell);
            }
            if c[a] + r < self.dims[a] - 1 {
                reach = reach.min((self.origin[a] + c[a] + r + 1) as f64 * self.cell - q[a]);
            }
        }
        // A point's cell comes from a rounded product: allow for a few ulps.
        let slack = 8.0 * f64::EPSILON * (q.iter().fold(self.cell, |m, x| m.max(x.abs())));
        (reach - slack).max(0.0)
    }
}

/// Scratch space for k-nearest searches in a `CellGrid`.
struct Searcher {
    block: Block,
    /// Squared distances as bit patterns, the first few of them the wanted ones.
    near: Vec<u64>,
    /// The last k-th squared distance: a neighbour's is a good first guess.
    guess: f64,
    floor: f64,
}

impl Searcher {
    fn new(cell: f64) -> Self {
        Searcher {
            block: Block::default(),
            near: Vec::new(),
            guess: cell * cell,
            floor: 1e-4 * cell * cell,
        }
    }

    /// With `block` holding the points within `r` cells of `q`'s cell `c`: the sum of
    /// the k + 1 smallest distances (`q`'s own 0 among them) and the largest squared
    /// one, when the block proves them the nearest.
    fn settle(
        &mut self,
        grid: &CellGrid,
        q: [f64; 3],
        c: [i64; 3],
        r: i64,
        k: usize,
    ) -> Option<(f64, f64)> {
        if self.block.len() <= k {
            return None;
        }
        let reach = grid.reach(q, c, r);
        let proven = reach * reach;
        // The floor keeps the widening going after a guess of 0 (a point with k
        // copies of itself).
        let mut t = self.guess.max(self.floor).min(proven);
        let mut found;
        loop {
            found = self.block.within(q, t, &mut self.near);
            if found > k || t >= proven {
                break;
            }
            t = (t * 1.25).min(proven);
        }
        if found <= k {
            return None;
        }
        let (sum, kth_d2) = smallest_roots(&mut self.near[..found], k + 1);
        self.guess = kth_d2 * 1.1;
        Some((sum, kth_d2))
    }

    /// Like `settle`, gathering blocks from radius `r` on until one proves the answer:
    /// the next radius is the one whose reach covers the best k-th distance so far,
    /// so a point rarely needs more than two blocks.
    fn nearest(
        &mut self,
        grid: &CellGrid,
        q: [f64; 3],
        c: [i64; 3],
        k: usize,
        mut r: i64,
    ) -> (f64, f64) {
        let widest = grid.dims.iter().copied().max().unwrap_or(1);
        loop {
            grid.gather(c, r, &mut self.block);
            if let Some(found) = self.settle(grid, q, c, r, k) {
                return found;
            }
            // A block reaching past every side holds all points and proves anything.
            debug_assert!(r < widest);
            r = if self.block.len() > k {
                // The block's (k+1)-th smallest squared distance bounds the answer;
                // a block reaching that far settles it.
                let all = self.block.within(q, f64::INFINITY, &mut self.near);
                let (_, bound, _) = self.near[..all].select_nth_unstable(k);
                let bound = f64::from_bits(*bound).sqrt();
                ((bound * grid.inv).ceil() as i64).saturating_add(1)
            } else {
                2 * r
            }
            .max(r + 1)
            .min(widest);
        }
    }
}

/// Candidate positions, one array per axis (the distance loop vectorises).
#[derive(Default)]
struct Block {
    coords: [Vec<f64>; 3],
}

impl Block {
    fn len(&self) -> usize {
        self.coords[0].len()
    }

    /// Puts the squared distances from `q` that are at most `t` at the front of
    /// `out` (as bit patterns) and returns how many there are. This loop is most of
    /// the work: where the CPU has AVX2 it runs four candidates at a time, with the
    /// same operations in the same order (so the same bits) as the scalar loop.
    fn within(&self, q: [f64; 3], t: f64, out: &mut Vec<u64>) -> usize {
        let len = self.len();
        if out.len() < len {
            out.resize(len, 0);
        }
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("popcnt")
        {
            // SAFETY: the CPU has the features the function is compiled for.
            return unsafe { avx2::within(&self.coords, q, t, &mut out[..len]) };
        }
        within_from(&self.coords, q, t, &mut out[..len], 0, 0)
    }
}

/// The scalar loop of `Block::within` over candidates `start..`, `n` of them kept so far.
#[inline(never)] // keeps `t` in a register: inlined, it was reloaded after every store
fn within_from(
    coords: &[Vec<f64>; 3],
    q: [f64; 3],
    t: f64,
    out: &mut [u64],
    start: usize,
    mut n: usize,
) -> usize {
    let [xs, ys, zs] = coords;
    let len = out.len();
    let (xs, ys, zs) = (&xs[..len], &ys[..len], &zs[..len]);
    for i in start..len {
        let (dx, dy, dz) = (xs[i] - q[0], ys[i] - q[1], zs[i] - q[2]);
        let d = dx * dx + dy * dy + dz * dz;
        // Branch-free compaction: write always, advance only when it counts.
        out[n] = d.to_bits();
        n += usize::from(d <= t);
    }
    n
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;

    /// For each 4-bit mask of kept lanes, the 32-bit lane indices that move the kept
    /// doubles to the front, in order.
    const COMPACT: [[i32; 8]; 16] = {
        let mut table = [[0i32; 8]; 16];
        let mut mask = 0;
        while mask < 16 {
            let (mut slot, mut lane) = (0, 0i32);
            while lane < 4 {
                if (mask >> lane) & 1 == 1 {
                    table[mask][2 * slot] = 2 * lane;
                    table[mask][2 * slot + 1] = 2 * lane + 1;
                    slot += 1;
                }
                lane += 1;
            }
            mask += 1;
        }
        table
    };

    /// `Block::within` four candidates at a time; `out` has one slot per candidate.
    #[target_feature(enable = "avx2,popcnt")]
    pub(super) fn within(coords: &[Vec<f64>; 3], q: [f64; 3], t: f64, out: &mut [u64]) -> usize {
        let len = out.len();
        let [xs, ys, zs] = coords;
        let (xs, ys, zs) = (&xs[..len], &ys[..len], &zs[..len]);
        let (qx, qy, qz) = (
            _mm256_set1_pd(q[0]),
            _mm256_set1_pd(q[1]),
            _mm256_set1_pd(q[2]),
        );
        let limit = _mm256_set1_pd(t);
        let (mut i, mut n) = (0, 0);
        while i + 4 <= len {
            // SAFETY: i + 4 <= len, the length of all three slices.
            let (x, y, z) = unsafe {
                (
                    _mm256_loadu_pd(xs.as_ptr().add(i)),
                    _mm256_loadu_pd(ys.as_ptr().add(i)),
                    _mm256_loadu_pd(zs.as_ptr().add(i)),
                )
            };
            let (dx, dy, dz) = (
                _mm256_sub_pd(x, qx),
                _mm256_sub_pd(y, qy),
                _mm256_sub_pd(z, qz),
            );
            let d = _mm256_add_pd(
                _mm256_add_pd(_mm256_mul_pd(dx, dx), _mm256_mul_pd(dy, dy)),
                _mm256_mul_pd(dz, dz),
            );
            let mask = _mm256_movemask_pd(_mm256_cmp_pd::<_CMP_LE_OQ>(d, limit)) as usize;
            let lanes = &COMPACT[mask];
            // SAFETY: `lanes` is 8 i32s (32 bytes).
            let order = unsafe { _mm256_loadu_si256(lanes.as_ptr().cast()) };
            let packed = _mm256_permutevar8x32_epi32(_mm256_castpd_si256(d), order);
            // SAFETY: n <= i, so the four slots n..n + 4 lie within out[..i + 4].
            unsafe { _mm256_storeu_si256(out.as_mut_ptr().add(n).cast(), packed) };
            n += mask.count_ones() as usize;
            i += 4;
        }
        super::within_from(coords, q, t, out, i, n)
    }

    /// `super::smallest_roots` after its selection, four values at a time and
    /// without moving any: the values above the n-th smallest are found level by
    /// level from the top (the largest, then the largest below it...), counting
    /// ties, and left out of the sum. (Moving values between passes stalled every
    /// pass: a wide load waits for the narrow stores into it.)
    #[target_feature(enable = "avx2,popcnt")]
    pub(super) fn smallest_roots(v: &[u64], n: usize) -> (f64, f64) {
        let mut drop = v.len() - n;
        let mut limit = f64::INFINITY;
        loop {
            let (top, count) = largest_below(v, limit);
            if count > drop {
                // `top` is the n-th smallest; `count - drop` of its copies stay.
                let kept = (count - drop) as f64;
                return (root_sum_below(v, top) + kept * top.sqrt(), top);
            }
            drop -= count;
            limit = top;
        }
    }

    /// The largest value below `limit` and how many times it occurs (values are
    /// non-negative doubles' bit patterns; 0 and its count when none is below).
    #[target_feature(enable = "avx2,popcnt")]
    fn largest_below(v: &[u64], limit: f64) -> (f64, usize) {
        let below = |x: f64| if x < limit { x } else { 0.0 };
        let bound = _mm256_set1_pd(limit);
        let chunks = v.chunks_exact(4);
        let tail = chunks.remainder();
        let mut top = _mm256_setzero_pd();
        for c in chunks.clone() {
            // SAFETY: `c` holds four u64s, read as four doubles.
            let x = unsafe { _mm256_loadu_pd(c.as_ptr().cast()) };
            let keep = _mm256_cmp_pd::<_CMP_LT_OQ>(x, bound);
            top = _mm256_max_pd(top, _mm256_and_pd(x, keep));
        }
        let mut lanes = [0.0; 4];
        // SAFETY: `lanes` holds four doubles.
        unsafe { _mm256_storeu_pd(lanes.as_mut_ptr(), top) };
        let top = (lanes.iter().copied())
            .chain(tail.iter().map(|&b| below(f64::from_bits(b))))
            .fold(0.0f64, f64::max);
        let wanted = _mm256_set1_pd(top);
        let mut count = 0;
        for c in chunks {
            // SAFETY: as above.
            let x = unsafe { _mm256_loadu_pd(c.as_ptr().cast()) };
            count +=
                _mm256_movemask_pd(_mm256_cmp_pd::<_CMP_EQ_OQ>(x, wanted)).count_ones() as usize;
        }
        count += tail.iter().filter(|&&b| f64::from_bits(b) == top).count();
        (top, count)
    }

    /// The sum of the square roots of the values below `limit`.
    #[target_feature(enable = "avx2,popcnt")]
    fn root_sum_below(v: &[u64], limit: f64) -> f64 {
        let bound = _mm256_set1_pd(limit);
        let mut sum = _mm256_setzero_pd();
        let chunks = v.chunks_exact(4);
        let tail = chunks.remainder();
        for c in chunks {
            // SAFETY: `c` holds four u64s, read as four doubles.
            let x = unsafe { _mm256_loadu_pd(c.as_ptr().cast()) };
            let keep = _mm256_cmp_pd::<_CMP_LT_OQ>(x, bound);
            sum = _mm256_add_pd(sum, _mm256_sqrt_pd(_mm256_and_pd(x, keep)));
        }
        let mut lanes = [0.0; 4];
        // SAFETY: `lanes` holds four doubles.
        unsafe { _mm256_storeu_pd(lanes.as_mut_ptr(), sum) };
        let tail: f64 = tail
            .iter()
            .map(|&b| f64::from_bits(b))
            .filter(|&x| x < limit)
            .map(f64::sqrt)
            .sum();
        lanes.iter().sum::<f64>() + tail
    }
}

/// Of the `n` smallest values of `v` (squared distances as bit patterns: non-negative
/// doubles order as their bits), the sum of their square roots and the largest.
/// Usually only a few values are too many: dropping the largest one at a time beats
/// a general selection there.
fn smallest_roots(v: &mut [u64], n: usize) -> (f64, f64) {
    let v = if v.len() > n + 12 {
        v.select_nth_unstable(n - 1);
        &mut v[..n]
    } else {
        v
    };
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("popcnt")
    {
        // SAFETY: the CPU has the features the function is compiled for.
        return unsafe { avx2::smallest_roots(v, n) };
    }
    smallest_roots_scalar(v, n)
}

/// `smallest_roots` after its selection, one value at a time.
fn smallest_roots_scalar(v: &mut [u64], n: usize) -> (f64, f64) {
    let mut len = v.len();
    while len > n {
        let (at, _) =
            v[..len].iter().enumerate().fold(
                (0, 0),
                |best, (i, &x)| if x >= best.1 { (i, x) } else { best },
            );
        v.swap(at, len - 1);
        len -= 1;
    }
    let kept = &v[..n];
    let sum = kept.iter().map(|&b| f64::from_bits(b).sqrt()).sum();
    (sum, f64::from_bits(kept.iter().copied().max().unwrap_or(0)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::Rng;

    /// Every point's mean distance to its k nearest others, by sorting all distances.
    fn brute_force(points: &[[f64; 3]], k: usize) -> Vec<f64> {
        points
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let mut d: Vec<f64> = points
                    .iter()
                    .enumerate()
                    .filter(|&(j, _)| j != i)
                    .map(|(_, o)| crate::geometry::distance_squared(p, o).sqrt())
                    .collect();
                d.sort_by(f64::total_cmp);
                d[..k].iter().sum::<f64>() / k as f64
            })
            .collect()
    }

    fn assert_same(points: &[[f64; 3]], k: usize, what: &str) {
        let got = mean_knn_distances(points, k, &mut || false).unwrap();
        let want = brute_force(points, k);
        for (i, (g, w)) in got.iter().zip(&want).enumerate() {
            assert!(
                (g - w).abs() <= 1e-12 * (1.0 + w.abs()),
                "{what}: point {i}: {g} vs {w}"
            );
        }
    }

    /// A scanned-looking scene: two noisy planes meeting at an edge, a sparse
    /// scatter of stray points and a few far ones.
    fn surfaces(rng: &mut Rng, n: usize) -> Vec<[f64; 3]> {
        let mut points = Vec::with_capacity(n);
        for i in 0..n {
            let (u, v) = (rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0));
            let noise = 0.003 * rng.normal();
            points.push(match i % 50 {
                0 => [
                    rng.uniform(-1.5, 1.5),
                    rng.uniform(-1.5, 1.5),
                    rng.uniform(-0.5, 1.5),
                ],
                1 if i % 1000 == 1 => [rng.uniform(5.0, 9.0), -7.0, rng.uniform(0.0, 3.0)],
                _ if i % 2 == 0 => [u, v, noise],
                _ => [u, 1.0 + noise, (v + 1.0) * 0.5],
            });
        }
        points
    }

    #[test]
    fn grid_search_equals_brute_force() {
        let mut rng = Rng::new(11);
        let scene = surfaces(&mut rng, 3000);
        for k in [1, 5, 20] {
            assert_same(&scene, k, "surfaces");
        }
        let cube: Vec<[f64; 3]> = (0..2000)
            .map(|_| [rng.unit(), rng.unit(), rng.unit()])
            .collect();
        assert_same(&cube, 20, "uniform cube");
        // Beyond LARGE_K the k-d tree answers, up to k = N - 1.
        assert_same(&cube[..700], LARGE_K + 1, "large k");
        assert_same(&cube[..700], 699, "k = N - 1");
        let flat: Vec<[f64; 3]> = (0..1500).map(|_| [rng.unit(), rng.unit(), 0.25]).collect();
        assert_same(&flat, 20, "one plane");
        let line: Vec<[f64; 3]> = (0..800).map(|_| [rng.unit(), 2.0, -1.0]).collect();
        assert_same(&line, 10, "one line");
        // Far from the origin the cells are many ulps wide still.
        let far: Vec<[f64; 3]> = scene
            .iter()
            .map(|p| [p[0] + 1e6, p[1] - 3e5, p[2] + 1e5])
            .collect();
        assert_same(&far, 20, "far from the origin");
    }

    #[test]
    fn awkward_clouds_equal_brute_force() {
        let mut rng = Rng::new(12);
        // Two tight clusters a kilometre apart: no grid resolves both (k-d tree).
        let clusters: Vec<[f64; 3]> = (0..1200)
            .map(|i| {
                let base = if i % 2 == 0 { 0.0 } else { 1000.0 };
                [
                    base + 0.01 * rng.unit(),
                    0.01 * rng.unit(),
                    0.01 * rng.unit(),
                ]
            })
            .collect();
        assert_same(&clusters, 20, "far clusters");
        // Heaps of exact duplicates, so many k-th distances are 0.
        let heaps: Vec<[f64; 3]> = (0..900)
            .map(|i| {
                let j = (i % 30) as f64;
                [j * 0.1, (j * 0.37).sin(), 0.0]
            })
            .collect();
        assert_same(&heaps, 20, "duplicates");
        // Grid-aligned points tie at equal distances everywhere.
        let lattice: Vec<[f64; 3]> = (0..1000)
            .map(|i| {
                [
                    (i % 10) as f64 * 0.05,
                    (i / 10 % 10) as f64 * 0.05,
                    (i / 100) as f64 * 0.05,
                ]
            })
            .collect();
        assert_same(&lattice, 26, "lattice");
        let few: Vec<[f64; 3]> = (0..21)
            .map(|_| [rng.unit(), rng.unit(), rng.unit()])
            .collect();
        assert_same(&few, 20, "k + 1 points");
        assert_eq!(
            mean_knn_distances(&[[0.5, 0.5, 0.5]; 30], 20, &mut || false),
            Some(vec![0.0; 30])
        );
        // Squared distances beyond f64's range (the review's case) or below it.
        for spacing in [1e153, 1e-160] {
            let line: Vec<[f64; 3]> = (0..200).map(|i| [i as f64 * spacing, 0.0, 0.0]).collect();
            let unit: Vec<[f64; 3]> = (0..200).map(|i| [i as f64, 0.0, 0.0]).collect();
            let params = OutlierParams {
                k: 150,
                std_ratio: 2.0,
            };
            let (kept, means) = statistical_outliers(&line, params).unwrap();
            let (want_kept, want) = statistical_outliers(&unit, params).unwrap();
            assert_eq!(kept, want_kept, "spacing {spacing}");
            for (m, w) in means.iter().zip(&want) {
                assert!(
                    (m / spacing - w).abs() < 1e-9 * w,
                    "spacing {spacing}: {m} vs {w}"
                );
            }
        }
    }

    #[test]
    fn vector_filter_equals_scalar_filter() {
        let mut rng = Rng::new(13);
        let mut block = Block::default();
        let (mut fast, mut slow) = (Vec::new(), Vec::new());
        for len in 0..40 {
            for a in &mut block.coords {
                a.clear();
            }
            for _ in 0..len {
                // Coarse values, so that some distances equal the limit exactly.
                for a in &mut block.coords {
                    a.push((rng.uniform(-4.0, 4.0)).round() * 0.25);
                }
            }
            let q = [0.0, 0.25, -0.5];
            for t in [0.0, 0.5, 1.0, 2.5, f64::INFINITY] {
                let n = block.within(q, t, &mut fast);
                slow.resize(len, 0);
                let m = within_from(&block.coords, q, t, &mut slow[..len], 0, 0);
                assert_eq!(fast[..n], slow[..m], "len {len}, t {t}");
            }
        }
    }

    #[test]
    fn vector_sums_equal_scalar_sums() {
        let mut rng = Rng::new(14);
        for n in [1, 3, 4, 21, 22] {
            for extra in 0..=14 {
                let values: Vec<u64> = (0..n + extra)
                    .map(|_| ((rng.uniform(0.0, 8.0)).round() * 0.125).to_bits())
                    .collect();
                let mut sorted = values.clone();
                sorted.sort_unstable();
                let want: f64 = sorted[..n].iter().map(|&b| f64::from_bits(b).sqrt()).sum();
                let (sum, kth) = smallest_roots(&mut values.clone(), n);
                let (slow_sum, slow_kth) = smallest_roots_scalar(&mut values.clone(), n);
                assert_eq!(kth, f64::from_bits(sorted[n - 1]));
                assert_eq!(slow_kth, kth);
                assert!((sum - want).abs() < 1e-12 && (slow_sum - want).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn an_interrupt_stops_outlier_removal_between_rounds() {
        let mut rng = crate::synthetic::Rng::new(7);
        let points: Vec<[f64; 3]> = (0..20_000)
            .map(|_| [rng.unit(), rng.unit(), rng.unit()])
            .collect();
        let params = OutlierParams {
            k: 20,
            std_ratio: 2.0,
        };
        let mut asked = 0;
        let stopped = statistical_outliers_interruptible(&points, params, &mut || {
            asked += 1;
            true
        })
        .unwrap();
        assert!(stopped.is_none() && asked == 1);
        let whole = statistical_outliers_interruptible(&points, params, &mut || false)
            .unwrap()
            .unwrap();
        assert_eq!(whole, statistical_outliers(&points, params).unwrap());
    }
}
