//! Point-to-plane ICP (Chen & Medioni; NOctoSLAM Eqs. 6-7): minimise
//! Σ ρ((T·p_i − q_i)·n_i) over rigid T (ρ the square, or Huber's kernel) by Gauss-Newton
//! (under Huber's kernel, Newton) steps on the small-angle pose, re-orthonormalised
//! (exponential map) after every step.

use super::kdtree::KdTree;
use crate::error::{Error, Result};
use crate::na::{Matrix4, Matrix6, Rotation3, SymmetricEigen, Translation3, Vector3, Vector6};
use crate::threads;

/// Stopping rules and robustness of [`icp_point_to_plane`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IcpParams {
    /// At most this many Gauss-Newton steps.
    pub max_iterations: usize,
    /// Pairs farther apart than this (metres) are ignored.
    pub max_correspondence_distance: f64,
    /// Stop when a step moves less than this (metres) ...
    pub translation_tolerance: f64,
    /// ... and turns less than this (radians): small_gicp's and Open3D's step
    /// epsilons (0 turns this test off).
    pub rotation_tolerance: f64,
    /// Stop when a step is shorter than this many standard deviations of the pose
    /// estimate: its Mahalanobis length under the covariance σ²·H⁻¹, σ² the pairs'
    /// residual variance and H the normal equations' matrix (for a Newton step under a
    /// Huber kernel, about Huber's: H of the pairs within the width, σ² = Σψ² / (their
    /// number − 6), ψ the residual clipped to the width; for a reweighted step, both
    /// weighted by the kernel).
    /// A step the data cannot tell from noise changes nothing a user can measure (0
    /// turns this test off).
    pub sigma_tolerance: f64,
    /// How the pairs' residuals are weighted.
    pub kernel: Kernel,
}

/// The robust kernel of [`icp_point_to_plane`]: how much a pair's residual counts.
/// Under Huber's kernel each step is Newton's on the kernel's loss where that provably
/// lowers the loss, else reweighted least squares' (see `gauss_newton_step`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Kernel {
    /// Plain least squares: every pair counts with the square of its residual.
    Squared,
    /// Huber's kernel of this width (metres): residuals beyond it count linearly.
    Huber(f64),
    /// Least squares until a step passes the stopping test, then Huber's kernel whose
    /// width follows the data: this many robust standard deviations (1.4826 × the
    /// median |residual|, over about 2048 pairs spread through the source) of the
    /// previous iteration's residuals, at least [`MIN_ADAPTIVE_WIDTH`], until a step
    /// passes the test again (converged only then). With no stopping test it never
    /// starts. Far from the answer every pair's pull is needed (least squares keeps its
    /// basin); once there, the width is the noise's, so that pairs on surfaces the
    /// target never saw (partial overlap) stop pulling the result off.
    AdaptiveHuber(f64),
}

/// The adaptive kernel's narrowest width (m): noise-free data would drive it to zero.
pub const MIN_ADAPTIVE_WIDTH: f64 = 1e-6;

/// [`Kernel::AdaptiveHuber`]'s width in robust standard deviations by default.
pub const ADAPTIVE_HUBER_SIGMAS: f64 = 1.0;

impl IcpParams {
    /// Positive distances and tolerances (zero tolerances: run every iteration).
    pub fn validate(&self) -> Result<()> {
        let fail = |what: &str, v: f64| {
            Err(Error::InvalidArgument(format!(
                "ICP {what} must be {}, got {v}",
                if what.ends_with("tolerance") {
                    "finite and >= 0"
                } else {
                    "finite and > 0"
                }
            )))
        };
        if self.max_iterations == 0 {
            return Err(Error::InvalidArgument(
                "ICP max_iterations must be at least 1".into(),
            ));
        }
        let d = self.max_correspondence_distance;
        if !(d.is_finite() && d > 0.0) {
            return fail("max_correspondence_distance", d);
        }
        for (what, v) in [
            ("translation_tolerance", self.translation_tolerance),
            ("rotation_tolerance", self.rotation_tolerance),
            ("sigma_tolerance", self.sigma_tolerance),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return fail(what, v);
            }
        }
        match self.kernel {
            Kernel::Huber(h) if !(h.is_finite() && h > 0.0) => return fail("huber_delta", h),
            Kernel::AdaptiveHuber(s) if !(s.is_finite() && s > 0.0) => {
                return fail("adaptive Huber width (robust standard deviations)", s)
            }
            _ => {}
        }
        Ok(())
    }
}

impl Default for IcpParams {
    fn default() -> Self {
        IcpParams {
            max_iterations: 50,
            max_correspondence_distance: 0.2,
            translation_tolerance: 0.0,
            rotation_tolerance: 0.0,
            sigma_tolerance: 1.0,
            kernel: Kernel::AdaptiveHuber(ADAPTIVE_HUBER_SIGMAS),
        }
    }
}

/// What [`icp_point_to_plane`] found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IcpResult {
    /// `target_from_source`.
    pub transform: Matrix4<f64>,
    /// Root mean square point-to-plane distance of the pairs at `transform` (once
    /// converged: of the pairs the last step, below the tolerances, was found from).
    pub rmse: f64,
    /// Fraction of source points with a pair within the correspondence distance, as
    /// `rmse` counts them.
    pub fitness: f64,
    /// Gauss-Newton steps taken.
    pub iterations: usize,
    /// A step fell below both step tolerances, or below `sigma_tolerance`, before
    /// `max_iterations`.
    pub converged: bool,
    /// The pairs cannot fix all six degrees of freedom (e.g. a single plane).
    pub degenerate: bool,
    /// Smallest / largest eigenvalue of the (scale-balanced) normal equations.
    pub conditioning: f64,
}

/// What ICP aligns to: for a (moved) source point, a reference point and unit normal.
pub trait IcpTarget: Sync {
    /// State a thread carries from one source point to the next and from one
    /// iteration to the next, for one fixed run of source points (they come in Morton
    /// order, so a lookup can start where the last one ended).
    type Cursor: Default + Send;
    /// A pair found but not read yet: ICP finds the pairs of a few source points before
    /// it reads them, so that a target can fetch them in the meantime.
    type Pair: Copy;
    /// `max_distance` bounds how far the pair may be from `p`; `index` is the point's
    /// place in the cursor's run (the same point keeps its index every iteration).
    fn pair(
        &self,
        p: [f64; 3],
        max_distance: f64,
        cursor: &mut Self::Cursor,
        index: usize,
    ) -> Option<Self::Pair>;

    /// The pair's reference point and unit normal.
    fn resolve(&self, pair: Self::Pair) -> ([f64; 3], [f64; 3]);

    /// Whether ICP should first align a subset of a large source (cheap pairs far from
    /// the answer matter less for a target whose lookups cost the same anywhere).
    fn coarse_to_fine(&self) -> bool {
        true
    }

    /// Pass on what `from` knows of its point `from_index` to `to`'s point `to_index`,
    /// the same source point in a later stage (the coarse stage's points in the fine
    /// stage). By default nothing is passed on.
    fn hand_on(_from: &Self::Cursor, _from_index: usize, _to: &mut Self::Cursor, _to_index: usize) {
    }
}

/// Per source point, what its last search found: where the point was, its
/// [`CANDIDATES`] nearest target points within the search's reach and the distance
/// beyond which every other target point lay.
#[derive(Clone, Copy)]
pub struct PlaneMemo {
    at: [f64; 3],
    candidates: [u32; CANDIDATES],
    count: u8,
    beyond: f64,
}

/// How many source points ahead [`PlaneTarget`]'s pairing fetches remembered target
/// points into the cache.
const PREFETCH_AHEAD: usize = 8;

/// Ask the CPU to bring `*at` (both cache lines a point and its normal may span) into
/// the cache; a hint, with no effect on results.
#[inline(always)]
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_variables))]
fn prefetch<T>(at: *const T) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let bytes = at as *const i8;
        // SAFETY: prefetching is a hint that never faults, whatever the address.
        unsafe {
            _mm_prefetch(bytes, _MM_HINT_T0);
            _mm_prefetch(
                bytes.wrapping_add(std::mem::size_of::<T>().saturating_sub(1)),
                _MM_HINT_T0,
            );
        }
    }
}

/// Target points remembered per source point.
const CANDIDATES: usize = 4;

/// How far beyond the correspondence distance a search looks (as a fraction of it),
/// so that a point with nothing in reach keeps knowing so while it moves that much.
const SEARCH_SLACK: f64 = 0.25;

/// A [`PlaneTarget`] lookup's state: per source point what its last search found.
#[derive(Default)]
pub struct PlaneCursor {
    memo: Vec<PlaneMemo>,
}

impl PlaneCursor {
    /// Keep `m` for the point `index` (points not yet searched stay unset).
    fn remember(&mut self, index: usize, m: PlaneMemo) {
        if index >= self.memo.len() {
            let unset = PlaneMemo {
                at: [f64::NAN; 3],
                ..m
            };
            self.memo.resize(index + 1, unset);
        }
        self.memo[index] = m;
    }
}

impl IcpTarget for PlaneTarget {
    type Cursor = PlaneCursor;
    /// The target point's number, its point and normal on their way into the cache.
    type Pair = u32;

    /// A remembered search stays true wherever the point goes (its use checks how far
    /// it moved), so the coarse stage's last searches spare the fine stage theirs.
    fn hand_on(from: &PlaneCursor, from_index: usize, to: &mut PlaneCursor, to_index: usize) {
        if let Some(&m) = from.memo.get(from_index).filter(|m| m.at[0].is_finite()) {
            to.remember(to_index, m);
        }
    }

    #[inline]
    fn resolve(&self, pair: u32) -> ([f64; 3], [f64; 3]) {
        self.surface[pair as usize]
    }

    /// The nearest target point within `max_distance`, exactly as a fresh search finds
    /// it. A point remembers its nearest few target points; while it has moved less
    /// than the gap between the nearest of them and every other target point, the
    /// nearest is among them (or nothing lies within reach), and no search is needed:
    /// once ICP settles, most iterations search for almost no point.
    fn pair(
        &self,
        p: [f64; 3],
        max_distance: f64,
        cursor: &mut PlaneCursor,
        index: usize,
    ) -> Option<u32> {
        let surface = &self.surface;
        let limit = max_distance * max_distance;
        // ICP reads the pair a few points later: fetch it meanwhile.
        let found = |(d, j): (f64, u32)| {
            (d <= limit).then(|| {
                prefetch(surface.as_ptr().wrapping_add(j as usize));
                j
            })
        };
        // The points a few steps on will check their remembered target points: fetch
        // those into the cache now, while this one computes (they lie anywhere in
        // memory; waiting for them was most of a settled iteration).
        if let Some(ahead) = cursor.memo.get(index + PREFETCH_AHEAD) {
            for &j in &ahead.candidates[..(ahead.count as usize).min(2)] {
                prefetch(surface.as_ptr().wrapping_add(j as usize));
            }
        }
        let known = cursor.memo.get(index).filter(|m| m.at[0].is_finite());
        if let Some(m) = known {
            let moved = crate::geometry::distance_squared(&p, &m.at).sqrt();
            // Ties go to the lower index, as in a fresh search.
            let best =
                m.candidates[..m.count as usize]
                    .iter()
                    .fold((f64::INFINITY, u32::MAX), |b, &j| {
                        let d = crate::geometry::distance_squared(&p, &surface[j as usize].0);
                        if d < b.0 || (d == b.0 && j < b.1) {
                            (d, j)
                        } else {
                            b
                        }
                    });
            let others = m.beyond - moved;
            // A margin far above rounding (which grows with the coordinates' size), far
            // below any gap that matters.
            let size = p
                .iter()
                .chain(&m.at)
                .fold(m.beyond.min(f64::MAX), |a, v| a.max(v.abs()));
            let margin = 1e-9 * (1.0 + m.beyond.min(1e6)) + 1e-12 * size;
            if best.0.sqrt() + margin < others {
                return found(best);
            }
            if best.0 > limit && others > max_distance + margin {
                return None;
            }
        }
        let reach = max_distance * (1.0 + SEARCH_SLACK);
        // Two candidates at first (the cheapest search that can prove a nearest); a point
        // whose two did not last, typically far from the target where distances
        // crowd together, gets all of them.
        let k = if known.is_some() { CANDIDATES } else { 2 };
        // The previous point's search bounds this one's: its k nearest lay within
        // `beyond` of where it was, so within that plus the gap of this point.
        let mut limit = reach * reach;
        if let Some(prev) = index
            .checked_sub(1)
            .and_then(|i| cursor.memo.get(i))
            .filter(|m| m.at[0].is_finite() && m.count as usize >= k)
        {
            let gap = crate::geometry::distance_squared(&p, &prev.at).sqrt();
            let bound = (prev.beyond + gap) * (1.0 + 1e-9) + 1e-12;
            limit = limit.min(bound * bound);
        }
        let (nearest, m) = if k == 2 {
            self.search::<2>(p, limit, reach)
        } else {
            self.search::<CANDIDATES>(p, limit, reach)
        };
        cursor.remember(index, m);
        nearest.and_then(found)
    }
}

/// A SurfaceMap lookup's state: the last descent, and per source point the leaf key
/// it fell in last iteration with the pair found there.
#[derive(Default)]
pub struct SurfaceCursor {
    descent: crate::octree::Descent,
    memo: Vec<PairMemo>,
}

/// A pair as the map stores it (single precision), for one leaf key.
#[derive(Clone, Copy)]
struct PairMemo {
    key: crate::octree::OcTreeKey,
    found: bool,
    position: [f32; 3],
    normal: [f32; 3],
}

impl IcpTarget for crate::octree::SurfaceMap {
    type Cursor = SurfaceCursor;
    type Pair = ([f64; 3], [f64; 3]);

    fn resolve(&self, pair: Self::Pair) -> ([f64; 3], [f64; 3]) {
        pair
    }

    /// A descent costs about the same near the answer and far from it.
    fn coarse_to_fine(&self) -> bool {
        false
    }

    /// NOctoSLAM's descent (resumed below the node shared with the previous point);
    /// the depth of the node found bounds the distance: a node larger than
    /// `max_distance` is too coarse to pair with (then a leaf beside is asked:
    /// `SurfaceMap::associate_within`). The pair depends only on the leaf
    /// key, and once ICP settles most points stay in their leaf from one iteration to
    /// the next: those reuse last iteration's pair without descending.
    fn pair(
        &self,
        p: [f64; 3],
        max_distance: f64,
        cursor: &mut Self::Cursor,
        index: usize,
    ) -> Option<([f64; 3], [f64; 3])> {
        let key = self.key_converter().coord_to_key_checked_f64(p)?;
        let memo = match cursor.memo.get(index) {
            Some(m) if m.key == key => *m,
            _ => {
                let found = self.associate_within(key, max_distance, &mut cursor.descent);
                // The map's values are single precision: nothing is lost.
                let (q, n) = found.map_or(([0.0; 3], [0.0; 3]), |(q, n, _)| (q, n));
                let m = PairMemo {
                    key,
                    found: found.is_some(),
                    position: q.map(|v| v as f32),
                    normal: n.map(|v| v as f32),
                };
                if index >= cursor.memo.len() {
                    cursor.memo.resize(index + 1, m);
                }
                cursor.memo[index] = m;
                m
            }
        };
        memo.found
            .then(|| (memo.position.map(f64::from), memo.normal.map(f64::from)))
    }
}

/// Target points with unit normals and their k-d tree, built once and reused.
#[derive(Clone, Debug)]
pub struct PlaneTarget {
    tree: KdTree,
    /// Each point with its unit normal, side by side (adjacent in memory), in the
    /// tree's numbering.
    surface: Vec<([f64; 3], [f64; 3])>,
}

impl PlaneTarget {
    /// A target of `points` (metres) with one normal each (any length; normalised here).
    ///
    /// Errors when the counts differ, with fewer than 3 points, or on a non-finite point
    /// or a zero / non-finite normal.
    pub fn new(points: &[[f64; 3]], normals: &[[f64; 3]]) -> Result<Self> {
        if points.len() != normals.len() {
            return Err(Error::InvalidArgument(format!(
                "target needs one normal per point ({} points, {} normals)",
                points.len(),
                normals.len()
            )));
        }
        if points.len() < 3 {
            return Err(Error::InvalidArgument(format!(
                "target needs at least 3 points, got {}",
                points.len()
            )));
        }
        let mut unit = Vec::with_capacity(normals.len());
        for (i, (p, n)) in points.iter().zip(normals).enumerate() {
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            if !(p.iter().all(|c| c.is_finite()) && len.is_finite() && len > 1e-12) {
                return Err(Error::InvalidArgument(format!(
                    "target point {i} or its normal is not finite / zero"
                )));
            }
            unit.push(n.map(|c| c / len));
        }
        // Numbered in leaf order, the target points that neighbouring source points
        // pair with lie near each other in memory.
        let (tree, order) = KdTree::new(points).into_leaf_order();
        let surface = order
            .iter()
            .map(|&i| (points[i as usize], unit[i as usize]))
            .collect();
        Ok(PlaneTarget { tree, surface })
    }

    /// The `K` nearest target points to `p` within squared distance `limit` (in a
    /// fixed array: no allocation), and what a point there remembers of them (`reach`:
    /// how far the search looked).
    #[inline]
    fn search<const K: usize>(
        &self,
        p: [f64; 3],
        limit: f64,
        reach: f64,
    ) -> (Option<(f64, u32)>, PlaneMemo) {
        let best = self.tree.nearest_k::<K>(&p, limit);
        let count = best.iter().filter(|b| b.1 != u32::MAX).count();
        let mut m = PlaneMemo {
            at: p,
            candidates: [0; CANDIDATES],
            count: count as u8,
            beyond: if count == K {
                best[K - 1].0.sqrt()
            } else {
                reach
            },
        };
        for (slot, &(_, j)) in m.candidates.iter_mut().zip(&best[..count]) {
            *slot = j;
        }
        ((count > 0).then_some(best[0]), m)
    }

    /// Number of target points.
    pub fn len(&self) -> usize {
        self.surface.len()
    }

    /// Whether the target has no points.
    pub fn is_empty(&self) -> bool {
        self.surface.is_empty()
    }
}

/// Align `source` to `target` starting from `initial` (`target_from_source`).
///
/// Errors on fewer than 6 source points, a non-finite point, an `initial` that is not
/// a rigid transform, or invalid `params`.
///
/// ```
/// use earcore_core::cloud::{icp_point_to_plane, IcpParams, PlaneTarget};
/// use earcore_core::na::Matrix4;
///
/// // Target: the corner of three walls (x = 0, y = 0, z = 0) on a 5 cm grid.
/// let (mut points, mut normals) = (Vec::new(), Vec::new());
/// for i in 1..10 {
///     for j in 1..10 {
///         let (u, v) = (0.05 * i as f64, 0.05 * j as f64);
///         points.extend([[0.0, u, v], [u, 0.0, v], [u, v, 0.0]]);
///         normals.extend([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
///     }
/// }
/// let target = PlaneTarget::new(&points, &normals)?;
/// // The source: the same corner seen 2 cm further along x and 1 cm back along y.
/// let source: Vec<[f64; 3]> = points.iter().map(|p| [p[0] + 0.02, p[1] - 0.01, p[2]]).collect();
/// let fit = icp_point_to_plane(&source, &target, &Matrix4::identity(), IcpParams::default())?;
/// assert!(fit.converged && !fit.degenerate);
/// // target_from_source moves the source back.
/// assert!((fit.transform[(0, 3)] + 0.02).abs() < 1e-6);
/// assert!((fit.transform[(1, 3)] - 0.01).abs() < 1e-6);
/// assert!(fit.transform[(2, 3)].abs() < 1e-6);
/// # Ok::<(), earcore_core::Error>(())
/// ```
pub fn icp_point_to_plane(
    source: &[[f64; 3]],
    target: &impl IcpTarget,
    initial: &Matrix4<f64>,
    params: IcpParams,
) -> Result<IcpResult> {
    let result = icp_point_to_plane_interruptible(source, target, initial, params, &mut || false)?;
    // Never asked to stop, so always a result.
    result.ok_or_else(|| Error::InvalidArgument("ICP was interrupted".into()))
}

/// [`icp_point_to_plane`], asking `interrupt` on the calling thread after every
/// iteration (one pass over the source, O(N) pair lookups); `Ok(None)` when it asked
/// to stop. What `max_iterations` allows is thus stoppable however large it is.
pub fn icp_point_to_plane_interruptible<T: IcpTarget>(
    source: &[[f64; 3]],
    target: &T,
    initial: &Matrix4<f64>,
    params: IcpParams,
    interrupt: &mut threads::Interrupt<'_>,
) -> Result<Option<IcpResult>> {
    crate::geometry::check_rigid(initial, "initial")?;
    if source.len() < 6 {
        return Err(Error::InvalidArgument(format!(
            "ICP needs at least 6 source points, got {}",
            source.len()
        )));
    }
    crate::geometry::check_finite(source, "source point")?;
    params.validate()?;
    // Steps rotate about the moved source's centroid (far from the origin, rotations
    // about it would be nearly translations), and the rotation columns are scaled by the
    // source's RMS radius, so that the conditioning compares metres with metres.
    let centroid = source
        .iter()
        .fold(Vector3::zeros(), |a, p| a + Vector3::from(*p))
        / source.len() as f64;
    let radius = (source
        .iter()
        .map(|p| (Vector3::from(*p) - centroid).norm_squared())
        .sum::<f64>()
        / source.len() as f64)
        .sqrt()
        .max(1e-9);
    let order = crate::geometry::morton_order(source);
    let source: Vec<[f64; 3]> = order.iter().map(|&i| source[i as usize]).collect();
    let mut transform = *initial;
    let mut result = IcpResult {
        transform,
        rmse: 0.0,
        fitness: 0.0,
        iterations: 0,
        converged: false,
        degenerate: false,
        conditioning: 0.0,
    };
    let mut width = None;
    let fine_runs = runs::<T>(source.len());
    // Coarse to fine: with many source points, a spread subset (a stride through the
    // Morton order) first, until its steps are within a standard deviation of what it
    // can resolve, with at most half the iterations; then every point from there.
    // Far from the answer each iteration costs most (every pair searched afresh, far
    // away), so those iterations run on few points.
    if target.coarse_to_fine() && source.len() >= 2 * COARSE_POINTS && params.max_iterations > 1 {
        let stride = source.len() / (source.len() / COARSE_SHARE).max(COARSE_POINTS);
        let coarse: Vec<[f64; 3]> = source.iter().step_by(stride).copied().collect();
        let coarse_runs = runs::<T>(coarse.len());
        // With no stopping test an adaptive kernel never starts, so neither may the
        // coarse stage's (whose own test is fixed).
        let testless = params.sigma_tolerance == 0.0
            && params.translation_tolerance == 0.0
            && params.rotation_tolerance == 0.0;
        let coarse_params = IcpParams {
            max_iterations: params.max_iterations / 2,
            translation_tolerance: 0.0,
            rotation_tolerance: 0.0,
            sigma_tolerance: 1.0,
            kernel: if testless {
                Kernel::Squared
            } else {
                params.kernel
            },
            ..params
        };
        let mut trial = result;
        let mut at = transform;
        let mut coarse_width = None;
        match iterate(
            &coarse,
            target,
            &mut at,
            coarse_params,
            (centroid, radius),
            &mut trial,
            &mut coarse_width,
            interrupt,
            &coarse_runs,
        ) {
            Ok(false) => return Ok(None),
            // Too few of the subset's points paired to decide anything: every point does.
            Err(_) => {}
            Ok(true) if trial.fitness * coarse.len() as f64 >= COARSE_MIN_PAIRS as f64 => {
                transform = at;
                result.iterations = trial.iterations;
                // The subset's residuals speak for the whole source's.
                width = coarse_width;
            }
            Ok(true) => {}
        }
        // What the subset's points last found, for their first fine iteration.
        for (start, from) in &coarse_runs {
            let from = from.lock().unwrap_or_else(|e| e.into_inner());
            for i in 0..RUN.min(coarse.len() - start) {
                let at = (start + i) * stride;
                let mut to = fine_runs[at / RUN]
                    .1
                    .lock()
                    .unwrap_or_else(|e| e.into_inner());
                T::hand_on(&from, i, &mut to, at % RUN);
            }
        }
    }
    let fine_params = IcpParams {
        max_iterations: params
            .max_iterations
            .saturating_sub(result.iterations)
            .max(1),
        ..params
    };
    let coarse_iterations = result.iterations;
    if !iterate(
        &source,
        target,
        &mut transform,
        fine_params,
        (centroid, radius),
        &mut result,
        &mut width,
        interrupt,
        &fine_runs,
    )? {
        return Ok(None);
    }
    result.iterations += coarse_iterations;
    // Re-orthonormalise the accumulated rotation (products drift by rounding).
    let rotation = Rotation3::from_matrix(&transform.fixed_view::<3, 3>(0, 0).into_owned());
    transform
        .fixed_view_mut::<3, 3>(0, 0)
        .copy_from(rotation.matrix());
    result.transform = transform;
    if !result.converged {
        // Stopped by the iteration limit (or a degenerate system) after a step of any
        // size: measure the pose returned, not the one before it.
        // (Only the pairs are read: the Jacobian's centre does not matter.)
        let system = normal_equations(
            &source,
            target,
            &transform,
            centroid,
            params,
            None,
            source.len(),
            &fine_runs,
        );
        record_fit(&mut result, &system, source.len());
    }
    Ok(Some(result))
}

/// Source points of the coarse stage, at least (when the source has at least twice as
/// many)...
const COARSE_POINTS: usize = 1024;

/// ...and at least this share of the source: a large source's fine stage starts where
/// its coarse stage ended, and a coarser start costs it more searches.
const COARSE_SHARE: usize = 30;

/// Pairs the coarse stage must end with for its pose to be kept (fewer fit noise).
const COARSE_MIN_PAIRS: usize = 256;

/// Gauss-Newton steps on `source` (Morton-ordered) from `transform` until `params` say
/// stop, recording the last step's statistics in `result` (`iterations` counts this
/// call's steps); `Ok(false)` when `interrupt` asked to stop. Steps rotate about where
/// `transform` moves the source's `centroid` (`radius`: its RMS distance from it).
/// `width` carries an adaptive kernel's width from one iteration (and stage) to the
/// next (`None`: plain least squares for the first).
#[allow(clippy::too_many_arguments)]
fn iterate<T: IcpTarget>(
    source: &[[f64; 3]],
    target: &T,
    transform: &mut Matrix4<f64>,
    params: IcpParams,
    (centroid, radius): (Vector3<f64>, f64),
    result: &mut IcpResult,
    width: &mut Option<f64>,
    interrupt: &mut threads::Interrupt<'_>,
    runs: &Runs<T>,
) -> Result<bool> {
    result.converged = false;
    let mut sample = (source.len() / MEDIAN_SAMPLES).max(1);
    for iteration in 1..=params.max_iterations {
        let current = match params.kernel {
            Kernel::Squared => None,
            Kernel::Huber(delta) => Some(delta),
            Kernel::AdaptiveHuber(_) => *width,
        };
        let centre =
            transform.fixed_view::<3, 3>(0, 0) * centroid + transform.fixed_view::<3, 1>(0, 3);
        let system = normal_equations(
            source, target, transform, centre, params, current, sample, runs,
        );
        // The next median from about MEDIAN_SAMPLES pairs, however few points pair.
        sample = (system.pairs / MEDIAN_SAMPLES).max(1);
        let robust_width = match (params.kernel, system.median) {
            (Kernel::AdaptiveHuber(sigmas), Some(median)) => {
                Some((sigmas * 1.4826 * median).max(MIN_ADAPTIVE_WIDTH))
            }
            _ => None,
        };
        if width.is_some() {
            *width = robust_width;
        }
        result.iterations = iteration;
        record_fit(result, &system, source.len());
        if system.pairs < 6 {
            return Err(Error::InvalidArgument(format!(
                "only {} source points have a target within {} m: give a closer initial pose or a larger max_correspondence_distance",
                system.pairs, params.max_correspondence_distance
            )));
        }
        let mut balanced = system.reweighted();
        for r in 0..6 {
            for c in 0..6 {
                balanced[(r, c)] /=
                    if r < 3 { radius } else { 1.0 } * if c < 3 { radius } else { 1.0 };
            }
        }
        let eig = SymmetricEigen::new(balanced).eigenvalues;
        let (lo, hi) = eig.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        });
        result.conditioning = if hi > 0.0 { lo.max(0.0) / hi } else { 0.0 };
        result.degenerate = result.conditioning < 1e-6;
        let Some(Step {
            delta: step,
            variance,
        }) = gauss_newton_step(&system, current.is_some())
        else {
            result.degenerate = true;
            break;
        };
        let omega = Vector3::new(step[0], step[1], step[2]);
        let delta_t = Vector3::new(step[3], step[4], step[5]);
        // Rotate by ω about the centre, then move it by t.
        let delta = Translation3::from(centre + delta_t).to_homogeneous()
            * Rotation3::new(omega).to_homogeneous()
            * Translation3::from(-centre).to_homogeneous();
        *transform = delta * *transform;
        // δᵀHδ = −δᵀg for the undamped step.
        let sigmas = (-step.dot(&system.g)).max(0.0) / variance;
        // The step test with the tolerances given (a zero one is not part of it), on
        // the step's rotation and its translation of the origin, as the peers test it.
        let (tt, rt) = (params.translation_tolerance, params.rotation_tolerance);
        let moved_origin = delta.fixed_view::<3, 1>(0, 3).norm();
        let small_step = (tt > 0.0 || rt > 0.0)
            && (tt == 0.0 || moved_origin < tt)
            && (rt == 0.0 || omega.norm() < rt);
        if small_step || sigmas < params.sigma_tolerance * params.sigma_tolerance {
            // An adaptive kernel starts once least squares has settled: far from the
            // answer every pair's pull is needed to get there.
            // (Started on the last iteration allowed, it has not settled: not converged.)
            if width.is_none() && robust_width.is_some() {
                *width = robust_width;
            } else {
                result.converged = true;
                break;
            }
        }
        if interrupt() {
            return Ok(false);
        }
    }
    Ok(true)
}

/// The fit's `fitness` and `rmse` from the pairs of `system` (of `len` source points).
fn record_fit(result: &mut IcpResult, system: &NormalEquations, len: usize) {
    result.fitness = system.pairs as f64 / len as f64;
    result.rmse = if system.pairs > 0 {
        (system.squared / system.pairs as f64).sqrt()
    } else {
        f64::INFINITY
    };
}

/// A Gauss-Newton step (ω, t) and the residual variance that measures it.
struct Step {
    delta: Vector6<f64>,
    /// σ² of the covariance σ²·H⁻¹ under which the stopping test measures the step.
    variance: f64,
}

/// The step from `system`, or `None` when none can be solved for. Least squares: the
/// Gauss-Newton step. Under Huber's kernel (`newton` allowed): Newton's step on the
/// kernel's loss, whose curvature is the inlier pairs' alone, when the reweighted
/// curvature of all pairs along it is under [`OUTLIER_CURVATURE`] times the inliers':
/// then it provably lowers the loss for the pairs it was found with, as the reweighted
/// (IRLS) step, taken otherwise, always does.
/// Newton's steps converge in two or three iterations where the reweighted ones shrink
/// by a constant factor each (to a quarter to a half at one standard deviation's width).
fn gauss_newton_step(system: &NormalEquations, newton: bool) -> Option<Step> {
    // Damped slightly so a degenerate system still gives a finite (minimum-norm-ish) step.
    let solve = |h: Matrix6<f64>| {
        let damped = h + Matrix6::identity() * (1e-12 * h.trace().max(1e-300));
        damped.cholesky().map(|c| c.solve(&-system.g))
    };
    let reweighted = system.reweighted();
    if newton && system.inliers > 6 {
        if let Some(delta) = solve(system.h_inliers) {
            // δᵀ H_inliers δ = −δᵀg.
            let inlier_curvature = -delta.dot(&system.g);
            if delta.dot(&(reweighted * delta)) < OUTLIER_CURVATURE * inlier_curvature {
                // About Huber's covariance of the estimate: σ²·H⁻¹, H the inliers' and
                // σ² = Σψ² / (inliers − 6), ψ the residual clipped to the width.
                let variance = system.clipped / (system.inliers - 6) as f64;
                return Some(Step {
                    delta,
                    variance: variance.max(VARIANCE_FLOOR),
                });
            }
        }
    }
    // The residual variance weighted as H and g are (a Huber kernel's).
    let variance = system.weighted / (system.pairs - 6).max(1) as f64;
    solve(reweighted).map(|delta| Step {
        delta,
        variance: variance.max(VARIANCE_FLOOR),
    })
}

/// How many times the inliers' curvature along Newton's step the reweighted curvature
/// (all pairs) may be for the step to be taken: below 2 the reweighted quadratic, which
/// lies above the loss, is lower at the step's end than at its start. Up to 4 was faster
/// on the benchmark's regimes but diverged on noisy random rooms (8 mm noise, a fifth of
/// the points moved, a fixed width) where the reweighted steps converged.
const OUTLIER_CURVATURE: f64 = 2.0;

/// The residual variance's floor, (1 nm)²: noise-free data converges.
const VARIANCE_FLOOR: f64 = 1e-18;

/// One cursor per run of [`RUN`] source points (with the run's first index), kept
/// across iterations.
type Runs<T> = Vec<(usize, std::sync::Mutex<<T as IcpTarget>::Cursor>)>;

/// Fresh cursors for `len` source points.
fn runs<T: IcpTarget>(len: usize) -> Runs<T> {
    (0..len)
        .step_by(RUN)
        .map(|start| (start, std::sync::Mutex::new(Default::default())))
        .collect()
}

/// Source points whose pairs are found before the first of them is read.
const AHEAD: usize = 8;

/// Source points per parallel run (and cursor).
const RUN: usize = 2048;

/// About this many residuals make an adaptive kernel's median.
const MEDIAN_SAMPLES: usize = 2048;

#[derive(Default)]
struct NormalEquations {
    /// Σ JJᵀ over the pairs within the kernel's width (all of them, in least squares).
    h_inliers: Matrix6<f64>,
    /// Σ w JJᵀ over the pairs beyond it (w = width / |r|).
    h_outliers: Matrix6<f64>,
    g: Vector6<f64>,
    squared: f64,
    /// Σ w r²: the residual variance's numerator under the kernel's weights, as H and g.
    weighted: f64,
    /// Σ ψ², ψ the residual clipped to the kernel's width.
    clipped: f64,
    pairs: usize,
    /// Pairs within the kernel's width.
    inliers: usize,
    /// The median |residual| of a stride through the pairs (an adaptive kernel's only).
    median: Option<f64>,
}

impl NormalEquations {
    /// Σ w JJᵀ over all pairs: the reweighted (IRLS) normal equations' matrix.
    fn reweighted(&self) -> Matrix6<f64> {
        self.h_inliers + self.h_outliers
    }
}

/// JᵀWJ and JᵀWr of the point-to-plane residuals at `transform`, with
/// r = (p' − q)·n and J = [(p' − c) × n, n] for the step (ω, t) applied on the left
/// about `centre` c, under Huber's kernel of width `huber` (`None`: least squares).
#[allow(clippy::too_many_arguments)]
fn normal_equations<T: IcpTarget>(
    source: &[[f64; 3]],
    target: &T,
    transform: &Matrix4<f64>,
    centre: Vector3<f64>,
    params: IcpParams,
    huber: Option<f64>,
    sample: usize,
    runs: &[(usize, std::sync::Mutex<T::Cursor>)],
) -> NormalEquations {
    let r = transform.fixed_view::<3, 3>(0, 0).into_owned();
    let t = transform.fixed_view::<3, 1>(0, 3).into_owned();
    // The median of every `sample`-th point's residual (about MEDIAN_SAMPLES of them)
    // estimates the scale as well as all of them, at a fraction of the selection's cost.
    let stride = match params.kernel {
        Kernel::AdaptiveHuber(_) => sample,
        _ => 0,
    };
    let parts = threads::map_parts(runs, |(start, cursor)| {
        let mut acc = NormalEquations::default();
        let mut magnitudes = Vec::new();
        // Each run's cursor is locked by one thread only: never contended.
        let mut cursor = cursor.lock().unwrap_or_else(|e| e.into_inner());
        let run = &source[*start..(start + RUN).min(source.len())];
        // The run's next point (by index in the run) whose residual is sampled: every
        // `stride`-th of the whole source.
        let mut sampled = if stride > 0 {
            start.next_multiple_of(stride) - start
        } else {
            usize::MAX
        };
        // A few points' pairs are found before the first of them is read (`IcpTarget::Pair`).
        let mut found: [(Vector3<f64>, Option<T::Pair>); AHEAD] = [(Vector3::zeros(), None); AHEAD];
        for (first, chunk) in (0..run.len()).step_by(AHEAD).zip(run.chunks(AHEAD)) {
            for (offset, (slot, p)) in found.iter_mut().zip(chunk).enumerate() {
                let moved = r * Vector3::from(*p) + t;
                let pair = target.pair(
                    [moved.x, moved.y, moved.z],
                    params.max_correspondence_distance,
                    &mut cursor,
                    first + offset,
                );
                *slot = (moved, pair);
            }
            for (offset, &(moved, pair)) in found[..chunk.len()].iter().enumerate() {
                let index = first + offset;
                let Some(pair) = pair else {
                    continue;
                };
                let (q, n) = target.resolve(pair);
                let (q, n) = (Vector3::from(q), Vector3::from(n));
                let residual = (moved - q).dot(&n);
                let (weight, inlier) = match huber {
                    Some(delta) if residual.abs() > delta => (delta / residual.abs(), false),
                    _ => (1.0, true),
                };
                // The residual clipped to the kernel's width: the loss's gradient.
                let psi = residual * weight;
                // (Points without a pair are passed over.)
                while sampled < index {
                    sampled += stride;
                }
                if index == sampled {
                    magnitudes.push(residual.abs());
                    sampled += stride;
                }
                let c = (moved - centre).cross(&n);
                let jac = Vector6::new(c.x, c.y, c.z, n.x, n.y, n.z);
                if inlier {
                    acc.h_inliers += jac * jac.transpose();
                    acc.inliers += 1;
                } else {
                    acc.h_outliers += jac * jac.transpose() * weight;
                }
                acc.g += jac * psi;
                acc.clipped += psi * psi;
                acc.squared += residual * residual;
                acc.weighted += weight * residual * residual;
                acc.pairs += 1;
            }
        }
        (acc, magnitudes)
    });
    let mut magnitudes = Vec::new();
    let mut sum = NormalEquations::default();
    // Summed in the runs' fixed order: the same result for any number of threads.
    for (b, m) in parts {
        sum.h_inliers += b.h_inliers;
        sum.h_outliers += b.h_outliers;
        sum.g += b.g;
        sum.squared += b.squared;
        sum.weighted += b.weighted;
        sum.clipped += b.clipped;
        sum.pairs += b.pairs;
        sum.inliers += b.inliers;
        magnitudes.extend(m);
    }
    if !magnitudes.is_empty() {
        let middle = magnitudes.len() / 2;
        let (_, median, _) = magnitudes.select_nth_unstable_by(middle, f64::total_cmp);
        sum.median = Some(*median);
    }
    sum
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::na::Point3;
    use crate::octree::{SurfaceMap, SurfaceParams};
    use crate::synthetic::Rng;

    /// A room's corner: `n` random points on each of the planes x = 0, y = 0 and z = 0
    /// over the unit square, with their normals.
    fn corner(rng: &mut Rng, n: usize) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
        let (mut points, mut normals) = (Vec::new(), Vec::new());
        for _ in 0..n {
            let (u, v) = (rng.uniform(0.0, 1.0), rng.uniform(0.0, 1.0));
            points.extend([[0.0, u, v], [u, 0.0, v], [u, v, 0.0]]);
            normals.extend([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
        }
        (points, normals)
    }

    /// NOctoSLAM's association done afresh for every point, every iteration.
    struct FreshDescents<'a>(&'a SurfaceMap);

    impl IcpTarget for FreshDescents<'_> {
        type Cursor = ();
        type Pair = ([f64; 3], [f64; 3]);

        fn resolve(&self, pair: Self::Pair) -> ([f64; 3], [f64; 3]) {
            pair
        }

        /// As the map it stands for.
        fn coarse_to_fine(&self) -> bool {
            false
        }

        fn pair(
            &self,
            p: [f64; 3],
            max_distance: f64,
            _: &mut (),
            _: usize,
        ) -> Option<([f64; 3], [f64; 3])> {
            let key = self.0.key_converter().coord_to_key_checked_f64(p)?;
            let (q, n, _) = self
                .0
                .associate_within(key, max_distance, &mut Default::default())?;
            Some((q, n))
        }
    }

    /// Reusing a point's pair while it stays in its leaf changes nothing: the same
    /// pairs, the same sums, bit for bit.
    #[test]
    fn pairs_kept_across_iterations_equal_fresh_descents() {
        let mut rng = Rng::new(5);
        let mut map = SurfaceMap::new(0.01, SurfaceParams::default()).unwrap();
        let mut points = Vec::new();
        for _ in 0..8000 {
            let (u, v) = (rng.uniform(-1.0, 1.0), rng.uniform(0.0, 1.0));
            points.push([u, 1.0 + rng.uniform(-0.002, 0.002), v]);
            points.push([1.0 + rng.uniform(-0.002, 0.002), u, v]);
            points.push([u, v, rng.uniform(-0.002, 0.002)]);
        }
        map.insert(&points).unwrap();
        map.insert(&points).unwrap();
        // 5000 source points, more than two parallel runs' worth.
        let source: Vec<[f64; 3]> = points.iter().step_by(4).take(5000).copied().collect();
        let mut initial = Matrix4::identity();
        initial[(0, 3)] = 0.02;
        initial[(2, 3)] = -0.01;
        let params = IcpParams {
            max_iterations: 15,
            sigma_tolerance: 0.0,
            ..IcpParams::default()
        };
        let kept = icp_point_to_plane(&source, &map, &initial, params).unwrap();
        let fresh = icp_point_to_plane(&source, &FreshDescents(&map), &initial, params).unwrap();
        assert_eq!(kept.transform, fresh.transform);
        assert_eq!(kept.rmse, fresh.rmse);
        assert_eq!(kept.fitness, fresh.fitness);
        assert!(kept.transform[(0, 3)].abs() < 1e-3, "{}", kept.transform);
    }
    /// One Gauss-Newton step against a `PlaneTarget` is the step the pairs found by brute
    /// force give: every source point paired and summed once, over runs and a last
    /// partial group of points.
    #[test]
    fn one_step_equals_brute_force_normal_equations() {
        let mut rng = Rng::new(21);
        let (points, normals) = corner(&mut rng, 1500);
        let target = PlaneTarget::new(&points, &normals).unwrap();
        // 2 × RUN + 13 points near the walls (some far from any, unpaired), moved.
        let source = near_walls(&mut rng, 2 * RUN + 13, [0.01, -0.008, 0.005], |rng, i| {
            if i % 97 == 0 {
                0.3
            } else {
                rng.uniform(-0.003, 0.003)
            }
        });
        let params = one_step(Kernel::Squared);
        let fit = icp_point_to_plane(&source, &target, &Matrix4::identity(), params).unwrap();
        let (mut h, mut g, mut squared, mut pairs) = (Matrix6::zeros(), Vector6::zeros(), 0.0, 0);
        let centre = centroid(&source);
        for p in &source {
            let (distance, r, jac) = brute_force_pair(&points, &normals, p, centre);
            if distance > 0.05 * 0.05 {
                continue;
            }
            h += jac * jac.transpose();
            g += jac * r;
            squared += r * r;
            pairs += 1;
        }
        let expected = step_transform(h.cholesky().unwrap().solve(&-g), centre);
        assert!(
            (fit.transform - expected).abs().max() < 1e-9,
            "{} {}",
            fit.transform,
            expected
        );
        assert!(pairs < source.len() && pairs > source.len() - 60, "{pairs}");
        // Stopped by the iteration limit: fitness and rmse are those of the pose
        // returned, not of the one the step was found from.
        assert!(!fit.converged);
        let (mut after_squared, mut after_pairs) = (0.0, 0);
        for p in &source {
            let moved = fit.transform.transform_point(&Point3::from(*p));
            let (distance, r, _) = brute_force_pair(&points, &normals, &moved.into(), centre);
            if distance <= 0.05 * 0.05 {
                after_squared += r * r;
                after_pairs += 1;
            }
        }
        assert_eq!(fit.fitness, after_pairs as f64 / source.len() as f64);
        assert!((fit.rmse - (after_squared / after_pairs as f64).sqrt()).abs() < 1e-12);
        assert!(
            fit.rmse < 0.5 * (squared / pairs as f64).sqrt(),
            "{}",
            fit.rmse
        );
    }

    /// The nearest of `points` to `p` by brute force (its squared distance), and the
    /// point-to-plane residual and Jacobian row [(p − centre) × n, n] of that pair.
    fn brute_force_pair(
        points: &[[f64; 3]],
        normals: &[[f64; 3]],
        p: &[f64; 3],
        centre: Vector3<f64>,
    ) -> (f64, f64, Vector6<f64>) {
        let (squared, j) = (0..points.len())
            .map(|j| (crate::geometry::distance_squared(p, &points[j]), j))
            .min_by(|a, b| a.partial_cmp(b).unwrap())
            .unwrap();
        let (p, q) = (Vector3::from(*p), Vector3::from(points[j]));
        let n = Vector3::from(normals[j]).normalize();
        let c = (p - centre).cross(&n);
        let jac = Vector6::new(c.x, c.y, c.z, n.x, n.y, n.z);
        (squared, (p - q).dot(&n), jac)
    }

    fn centroid(points: &[[f64; 3]]) -> Vector3<f64> {
        points
            .iter()
            .map(|p| Vector3::from(*p))
            .sum::<Vector3<f64>>()
            / points.len() as f64
    }

    /// `n` points near the corner's three walls (a third on each, in turn), wall `w`'s
    /// `shift[w]` plus `off(i)` off it.
    fn near_walls(
        rng: &mut Rng,
        n: usize,
        shift: [f64; 3],
        mut off: impl FnMut(&mut Rng, usize) -> f64,
    ) -> Vec<[f64; 3]> {
        (0..n)
            .map(|i| {
                let (u, v) = (rng.uniform(0.0, 1.0), rng.uniform(0.0, 1.0));
                let d = off(rng, i) + shift[i % 3];
                match i % 3 {
                    0 => [d, u, v],
                    1 => [u, d, v],
                    _ => [u, v, d],
                }
            })
            .collect()
    }

    /// One Gauss-Newton step under `kernel`, pairs within 5 cm, no stopping test.
    fn one_step(kernel: Kernel) -> IcpParams {
        IcpParams {
            max_iterations: 1,
            max_correspondence_distance: 0.05,
            sigma_tolerance: 0.0,
            kernel,
            ..IcpParams::default()
        }
    }

    /// The transform of the small-angle step (ω, t) applied on the left: a rotation by
    /// ω about `centre`, then a move by t.
    fn step_transform(step: Vector6<f64>, centre: Vector3<f64>) -> Matrix4<f64> {
        Translation3::from(centre + Vector3::new(step[3], step[4], step[5])).to_homogeneous()
            * Rotation3::new(Vector3::new(step[0], step[1], step[2])).to_homogeneous()
            * Translation3::from(-centre).to_homogeneous()
    }

    /// One step under Huber's kernel against normal equations built from brute-force
    /// nearest neighbours: Newton's (the inliers' curvature alone) where the inliers
    /// constrain it, the reweighted one where they do not (a wall seen only beyond the
    /// width, which leaves the inliers nothing along its normal).
    #[test]
    fn a_huber_step_is_newtons_where_the_inliers_constrain_it() {
        let mut rng = Rng::new(22);
        let (points, normals) = corner(&mut rng, 1500);
        let target = PlaneTarget::new(&points, &normals).unwrap();
        let width = 0.002;
        let damped = |h: Matrix6<f64>| h + Matrix6::identity() * (1e-12 * h.trace());
        for (first_wall, newton) in [(0.0, true), (0.012, false)] {
            let shift = [0.003 + first_wall, -0.002, 0.001];
            let source = near_walls(&mut rng, 3000, shift, |rng, _| rng.uniform(-0.004, 0.004));
            let params = one_step(Kernel::Huber(width));
            let fit = icp_point_to_plane(&source, &target, &Matrix4::identity(), params).unwrap();
            let (mut inliers, mut outliers, mut g) =
                (Matrix6::zeros(), Matrix6::zeros(), Vector6::zeros());
            let centre = centroid(&source);
            for p in &source {
                let (distance, r, jac) = brute_force_pair(&points, &normals, p, centre);
                assert!(distance < 0.05 * 0.05);
                if r.abs() <= width {
                    inliers += jac * jac.transpose();
                    g += jac * r;
                } else {
                    outliers += jac * jac.transpose() * (width / r.abs());
                    g += jac * (width * r.signum());
                }
            }
            let reweighted = inliers + outliers;
            let newtons = damped(inliers).cholesky().unwrap().solve(&-g);
            let ratio = newtons.dot(&(reweighted * newtons)) / -newtons.dot(&g);
            assert_eq!(ratio < OUTLIER_CURVATURE, newton, "{ratio}");
            let step = if newton {
                newtons
            } else {
                reweighted.cholesky().unwrap().solve(&-g)
            };
            let expected = step_transform(step, centre);
            assert!(
                (fit.transform - expected).abs().max() < 1e-9,
                "{} {}",
                fit.transform,
                expected
            );
        }
    }

    /// A fresh nearest-neighbour search for every point, every iteration.
    struct FreshSearches<'a>(&'a PlaneTarget);

    impl IcpTarget for FreshSearches<'_> {
        type Cursor = ();
        type Pair = u32;

        fn resolve(&self, pair: u32) -> ([f64; 3], [f64; 3]) {
            self.0.surface[pair as usize]
        }

        fn pair(&self, p: [f64; 3], max_distance: f64, _: &mut (), _: usize) -> Option<u32> {
            let (_, j) = self.0.tree.nearest_within(p, max_distance * max_distance)?;
            Some(j)
        }
    }

    /// Keeping a point's nearest neighbour while it provably stays the nearest changes
    /// nothing: the same transforms, bit for bit, for near and far correspondence
    /// distances, small and large offsets, with points that have no pair.
    #[test]
    fn kept_nearest_neighbours_equal_fresh_searches() {
        let mut rng = Rng::new(9);
        let (points, normals) = corner(&mut rng, 3000);
        let target = PlaneTarget::new(&points, &normals).unwrap();
        // Half of the source overlaps the target, half lies 0.3-0.8 m beyond it, and a
        // few hover 4-7 cm over the floor: they start out of the smallest reach (the
        // offset lifts them) and come into it.
        let mut source: Vec<[f64; 3]> = points.iter().step_by(3).take(3000).copied().collect();
        source.extend((0..500).map(|_| {
            [
                rng.uniform(0.1, 0.9),
                rng.uniform(0.1, 0.9),
                rng.uniform(0.045, 0.056),
            ]
        }));
        source.extend((0..3000).map(|_| {
            [
                rng.uniform(1.3, 1.8),
                rng.uniform(0.0, 1.0),
                rng.uniform(0.0, 1.0),
            ]
        }));
        for (offset, radius) in [(0.02, 0.05), (0.1, 0.2), (0.1, 1.0)] {
            let mut initial = Matrix4::identity();
            initial[(0, 3)] = offset;
            initial[(1, 3)] = -offset / 2.0;
            initial[(2, 3)] = offset;
            let params = IcpParams {
                max_iterations: 30,
                max_correspondence_distance: radius,
                sigma_tolerance: 0.0,
                ..IcpParams::default()
            };
            let kept = icp_point_to_plane(&source, &target, &initial, params).unwrap();
            let fresh =
                icp_point_to_plane(&source, &FreshSearches(&target), &initial, params).unwrap();
            assert_eq!(kept, fresh, "offset {offset}, radius {radius}");
        }
    }

    /// A source large enough for a coarse stage of several runs hands every coarse
    /// point's search on to the fine stage's right place: the same answer as fresh
    /// searches, bit for bit, with the defaults (the adaptive kernel).
    #[test]
    fn a_large_source_hands_its_coarse_searches_on() {
        let mut rng = Rng::new(23);
        let (points, normals) = corner(&mut rng, 3000);
        let target = PlaneTarget::new(&points, &normals).unwrap();
        // 3 × 24000 points: a coarse stage of a thirtieth, 2400, over two runs.
        let (source, _) = corner(&mut rng, 24000);
        let source: Vec<[f64; 3]> = source
            .iter()
            .map(|p| p.map(|c| c + rng.uniform(-0.002, 0.002)))
            .collect();
        assert!(source.len() / COARSE_SHARE > RUN);
        let mut initial = Matrix4::identity();
        initial[(0, 3)] = 0.03;
        initial[(1, 3)] = -0.02;
        let params = IcpParams {
            max_iterations: 20,
            ..IcpParams::default()
        };
        let kept = icp_point_to_plane(&source, &target, &initial, params).unwrap();
        let fresh = icp_point_to_plane(&source, &FreshSearches(&target), &initial, params).unwrap();
        assert_eq!(kept, fresh);
        assert!(
            kept.converged && kept.transform[(0, 3)].abs() < 1e-3,
            "{kept:?}"
        );
    }

    /// Whatever bounds its searches, every memo says what a search without bounds would:
    /// its candidates are the target points nearest to where it was (ties by index) and
    /// every other lies at least its distance away; and the pair is the nearest within
    /// reach. By brute force, on grids (equally near points everywhere) far from the
    /// origin too, along lines that put a point's k-th nearest exactly at the previous
    /// point's bound.
    #[test]
    fn memos_hold_what_brute_force_says() {
        let mut rng = Rng::new(17);
        let grids: Vec<(f64, f64)> = (0..40)
            .map(|i| {
                let spacing = 10f64.powf(rng.uniform(-5.0, -1.0));
                (
                    spacing,
                    [0.0, 1e3, -1e5, 3e7][i % 4] * rng.uniform(0.5, 1.0),
                )
            })
            .collect();
        for (spacing, origin) in grids {
            let mut points = Vec::new();
            for (i, j, k) in
                (0..14).flat_map(|i| (0..14).flat_map(move |j| (0..3).map(move |k| (i, j, k))))
            {
                points.push([i, j, k].map(|c| origin + spacing * c as f64));
            }
            let normals = vec![[0.0, 0.0, 1.0]; points.len()];
            let target = PlaneTarget::new(&points, &normals).unwrap();
            for max_distance in [0.7 * spacing, 3.0 * spacing] {
                // Along a grid line from half-way between two points, then a random walk.
                let mut path: Vec<[f64; 3]> = [0.25, 0.1, 0.3]
                    .into_iter()
                    .flat_map(|step| (0..20).map(move |i| [0.5 + step * i as f64, 3.0, 1.0]))
                    .map(|p: [f64; 3]| p.map(|c| origin + spacing * c))
                    .collect();
                let mut at = [origin + 7.0 * spacing, origin + 7.0 * spacing, origin];
                for _ in 0..120 {
                    at = at.map(|c| c + spacing * rng.uniform(-0.8, 0.8));
                    path.push(at);
                }
                let mut cursor = PlaneCursor::default();
                for iteration in 0..5 {
                    for (index, p) in path.iter().enumerate() {
                        let got = target
                            .pair(*p, max_distance, &mut cursor, index)
                            .map(|j| target.resolve(j));
                        let sorted = |from: &[f64; 3]| {
                            let mut all: Vec<(f64, u32)> = (0..target.surface.len())
                                .map(|j| {
                                    (
                                        crate::geometry::distance_squared(
                                            from,
                                            &target.surface[j].0,
                                        ),
                                        j as u32,
                                    )
                                })
                                .collect();
                            all.sort_by(|a, b| a.partial_cmp(b).unwrap());
                            all
                        };
                        let nearest = sorted(p)[0];
                        let expected = (nearest.0 <= max_distance * max_distance)
                            .then(|| target.surface[nearest.1 as usize]);
                        assert_eq!(
                            got, expected,
                            "{spacing} {max_distance} {iteration} {index}"
                        );
                        let m = cursor.memo[index];
                        let all = sorted(&m.at);
                        let count = m.count as usize;
                        let nearest: Vec<u32> = all[..count].iter().map(|e| e.1).collect();
                        assert_eq!(&m.candidates[..count], &nearest[..], "{spacing} {index}");
                        for &(d, j) in &all[count..] {
                            assert!(
                                d.sqrt() >= m.beyond * (1.0 - 1e-12),
                                "{spacing} {max_distance} {iteration} {index}: point {j} at {} inside {}",
                                d.sqrt(),
                                m.beyond
                            );
                        }
                    }
                    // A small step, as ICP's: most memos last, some do not.
                    for p in &mut path {
                        p[0] += spacing * 0.05 * (iteration as f64 - 1.5);
                    }
                }
            }
        }
    }

    /// An interrupt is asked after every iteration and stops the alignment there;
    /// one that never asks to stop changes nothing.
    #[test]
    fn an_interrupt_stops_icp_between_iterations() {
        let mut rng = Rng::new(6);
        let (points, normals) = corner(&mut rng, 600);
        let target = PlaneTarget::new(&points, &normals).unwrap();
        let source: Vec<[f64; 3]> = points.iter().map(|p| [p[0] + 0.02, p[1], p[2]]).collect();
        let params = IcpParams {
            max_iterations: 1_000_000_000,
            sigma_tolerance: 0.0,
            ..IcpParams::default()
        };
        let initial = Matrix4::identity();
        let mut asked = 0;
        let stopped =
            icp_point_to_plane_interruptible(&source, &target, &initial, params, &mut || {
                asked += 1;
                asked == 3
            });
        assert_eq!(stopped, Ok(None));
        assert_eq!(asked, 3);
        let few = IcpParams {
            max_iterations: 8,
            ..params
        };
        let mut asked = 0;
        let done = icp_point_to_plane_interruptible(&source, &target, &initial, few, &mut || {
            asked += 1;
            false
        });
        assert_eq!(asked, 8);
        let plain = icp_point_to_plane(&source, &target, &initial, few).unwrap();
        assert_eq!(done, Ok(Some(plain)));
        assert!((plain.transform[(0, 3)] + 0.02).abs() < 1e-9);
        // With the defaults the adaptive kernel starts once least squares settles: that
        // iteration is asked too; only the last, which stops, is not.
        let mut asked = 0;
        let settled = icp_point_to_plane_interruptible(
            &source,
            &target,
            &initial,
            IcpParams::default(),
            &mut || {
                asked += 1;
                false
            },
        )
        .unwrap()
        .unwrap();
        assert!(settled.converged);
        assert_eq!(asked, settled.iterations - 1);
    }

    /// A room's corner seen by the target, and by the source with 1 mm of noise plus a
    /// plate 4 cm in front of one wall that the target never saw: least squares pairs
    /// the plate with the wall and ends centimetres off; the adaptive kernel, once
    /// least squares has settled, stops the plate's pull (against the known truth).
    #[test]
    fn an_adaptive_kernel_keeps_an_unseen_surface_from_pulling_the_result() {
        let mut rng = Rng::new(21);
        let (points, normals) = corner(&mut rng, 4000);
        let target = PlaneTarget::new(&points, &normals).unwrap();
        // The truth: target_from_source undoes a 3 cm, 2° offset.
        let offset = Translation3::new(0.02, -0.015, 0.01).to_homogeneous()
            * Rotation3::from_axis_angle(&Vector3::z_axis(), 2f64.to_radians()).to_homogeneous();
        let truth = offset.try_inverse().unwrap();
        // 1800 and then 9000 corner points (the coarse stage runs on the larger).
        for seen_points in [1800, 9000] {
            let mut seen: Vec<[f64; 3]> = (0..seen_points)
                .map(|i| {
                    let (u, v) = (rng.uniform(0.05, 0.95), rng.uniform(0.05, 0.95));
                    let p = [[0.0, u, v], [u, 0.0, v], [u, v, 0.0]][i % 3];
                    [0, 1, 2].map(|a| p[a] + 0.001 * rng.normal())
                })
                .collect();
            seen.extend(
                (0..seen_points / 10).map(|_| [0.04, rng.uniform(0.2, 0.6), rng.uniform(0.2, 0.6)]),
            );
            let source: Vec<[f64; 3]> = seen
                .iter()
                .map(|p| {
                    let q = offset * crate::na::Vector4::new(p[0], p[1], p[2], 1.0);
                    [q.x, q.y, q.z]
                })
                .collect();
            let error = |kernel| {
                let params = IcpParams {
                    kernel,
                    ..IcpParams::default()
                };
                let found =
                    icp_point_to_plane(&source, &target, &Matrix4::identity(), params).unwrap();
                assert!(found.converged, "{kernel:?}");
                (found.transform - truth).fixed_view::<3, 1>(0, 3).norm()
            };
            let squared = error(Kernel::Squared);
            let adaptive = error(Kernel::AdaptiveHuber(ADAPTIVE_HUBER_SIGMAS));
            assert!(squared > 0.005, "{seen_points}: least squares {squared}");
            assert!(
                adaptive < 0.0015 && adaptive < 0.1 * squared,
                "{seen_points}: {adaptive} vs {squared}"
            );
        }
    }

    /// The adaptive kernel begins as least squares: until least squares settles, every
    /// step is the same, bit for bit.
    #[test]
    fn an_adaptive_kernel_starts_as_least_squares() {
        let mut rng = Rng::new(4);
        let (points, normals) = corner(&mut rng, 3000);
        let target = PlaneTarget::new(&points, &normals).unwrap();
        // Fewer points than the coarse stage needs, a third on each plane.
        let source: Vec<[f64; 3]> = points
            .iter()
            .take(2 * COARSE_POINTS - 2)
            .map(|p| [0, 1, 2].map(|a| p[a] + 0.002 * rng.normal() + [0.08, -0.05, 0.06][a]))
            .collect();
        for iterations in [1, 2, 3] {
            let run = |kernel| {
                let params = IcpParams {
                    max_iterations: iterations,
                    kernel,
                    ..IcpParams::default()
                };
                icp_point_to_plane(&source, &target, &Matrix4::identity(), params).unwrap()
            };
            let squared = run(Kernel::Squared);
            assert!(!squared.converged);
            assert_eq!(squared, run(Kernel::AdaptiveHuber(1.0)), "{iterations}");
        }
        // Least squares settling on the last iteration allowed starts the kernel, which
        // has not settled: the same pose, not converged.
        let settled =
            icp_point_to_plane(&source, &target, &Matrix4::identity(), IcpParams::default())
                .unwrap();
        let squared = |max_iterations| IcpParams {
            max_iterations,
            kernel: Kernel::Squared,
            ..IcpParams::default()
        };
        let plain = icp_point_to_plane(&source, &target, &Matrix4::identity(), squared(50));
        let plain = plain.unwrap();
        assert!(
            plain.converged && settled.converged && settled.iterations > plain.iterations,
            "{plain:?} {settled:?}"
        );
        let last = IcpParams {
            max_iterations: plain.iterations,
            ..IcpParams::default()
        };
        let cut = icp_point_to_plane(&source, &target, &Matrix4::identity(), last).unwrap();
        assert_eq!(cut.transform, plain.transform);
        assert!(!cut.converged);
        // With no stopping test the kernel never starts, for a source small or large
        // enough for the coarse stage.
        let many: Vec<[f64; 3]> = points
            .iter()
            .map(|p| [0, 1, 2].map(|a| p[a] + 0.002 * rng.normal() + [0.03, -0.02, 0.02][a]))
            .collect();
        for source in [&source, &many] {
            let testless = |kernel| IcpParams {
                max_iterations: 12,
                sigma_tolerance: 0.0,
                kernel,
                ..IcpParams::default()
            };
            let run = |kernel| {
                icp_point_to_plane(source, &target, &Matrix4::identity(), testless(kernel)).unwrap()
            };
            assert_eq!(run(Kernel::Squared), run(Kernel::AdaptiveHuber(1.0)));
        }
    }
}
