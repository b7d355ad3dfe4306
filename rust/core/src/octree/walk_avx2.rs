//! The exact ray walk of [`super::ray::walk_from`] (OctoMap's `computeRayKeys`), eight
//! rays at a time in AVX2 lanes, planned and walked in one go.
//!
//! The scalar walk spends most of its time on mispredicted branches: which axis to step
//! next is as unpredictable as the ray's slope. Here every lane takes its axis by masks,
//! so nothing is predicted, and four rays share each instruction. The arithmetic is the
//! scalar code's, in the same precisions and operations (no fused multiply-add), so the
//! cells are the same bit for bit.
//!
//! What keeps the loop short:
//! - A ray reaches its end cell after exactly `n = Σ|end − origin|` steps (each step moves
//!   one axis one cell towards the end), so rays are grouped by `n` and a group's lanes
//!   finish together; there is no key comparison in the loop.
//! - A walk that rounding carries one cell past its end on some axis (possible when the
//!   end point lies on a cell border) never meets the end cell; the scalar walk then goes
//!   on until it passes the end's distance. Such rays are rare and are handed back to the
//!   scalar walk, which marks the rest of their cells.
//! - Cells are bytes of a box in plain x-fastest order ([`CellBytes`]), so a lane keeps
//!   its cell's index instead of its key (a step adds ±1, ±X or ±XY) and marks it with a
//!   byte store: no read-modify-write that the next step's store to the same word would
//!   wait on. The bytes are folded into the octree's bricks of bits once per scan.
//! - Two groups of four lanes are interleaved: one group's step waits on its previous
//!   one (compare, mask, add), two keep the core busy.
//! - Rays are planned (direction, length, first crossings) four at a time right before
//!   they are walked, straight into the lanes.

// Off x86-64 no batched walk runs: the lanes' buffers and the dispatch compile but
// stay unused there.
#![cfg_attr(
    not(target_arch = "x86_64"),
    allow(dead_code, unused_variables, unused_mut)
)]

use super::key::{KeyConverter, OcTreeKey};
use super::ray::Point3f;

/// One byte per cell of a key box (non-zero: a ray crossed the cell), x fastest, plus
/// a spare byte at the end that idle lanes write to.
#[derive(Clone, Debug)]
pub(crate) struct CellBytes {
    pub bytes: Vec<u8>,
    /// Lowest key of the box.
    pub lo: [u16; 3],
    /// Box size in cells.
    pub dims: [usize; 3],
    /// The lanes' buffers, kept from one batch of rays to the next.
    lanes: LaneRays,
}

impl CellBytes {
    /// All clear. The allocation is zeroed lazily by the OS (`calloc`), so only the
    /// pages rays touch cost anything.
    pub fn new(lo: [u16; 3], dims: [usize; 3]) -> Self {
        CellBytes {
            bytes: vec![0; dims.iter().product::<usize>() + 1],
            lo,
            dims,
            lanes: LaneRays::default(),
        }
    }

    /// Index of the spare byte (after the box's cells).
    #[inline]
    pub fn spare(&self) -> usize {
        self.bytes.len() - 1
    }

    /// Index of a key in the box (the caller checked it is inside).
    #[inline]
    fn index(&self, key: OcTreeKey) -> usize {
        let k = |a: usize| usize::from(key.0[a] - self.lo[a]);
        k(0) + self.dims[0] * (k(1) + self.dims[1] * k(2))
    }
}

/// Which batched walk a CPU runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Batch {
    /// Two vectors of four rays.
    Avx2,
    /// Two vectors of eight rays.
    Avx512,
}

/// The batched walks this CPU can run, the fastest last.
pub(crate) fn supported() -> Vec<Batch> {
    let mut out = Vec::new();
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            out.push(Batch::Avx2);
        }
        if std::arch::is_x86_feature_detected!("avx512f") {
            out.push(Batch::Avx512);
        }
    }
    out
}

/// The batched walk this CPU runs, if any. `EARCORE_NO_AVX2` (any value) forces the
/// scalar walk, `EARCORE_NO_AVX512` the AVX2 one: for comparisons, and for tests of
/// the fallbacks on machines that have both.
pub(crate) fn batch() -> Option<Batch> {
    static CHOICE: std::sync::OnceLock<Option<Batch>> = std::sync::OnceLock::new();
    *CHOICE.get_or_init(|| {
        let off = |name: &str| std::env::var_os(name).is_some();
        let mut supported = supported();
        if off("EARCORE_NO_AVX512") {
            supported.retain(|&b| b != Batch::Avx512);
        }
        if off("EARCORE_NO_AVX2") {
            supported.clear();
        }
        supported.last().copied()
    })
}

/// Whether this CPU runs a batched walk.
pub(crate) fn available() -> bool {
    batch().is_some()
}

/// The rays the batched walk takes, ready to load into lanes: end points by axis, end
/// cells (indices into the box), step counts and the rays' indices in the scan. The
/// first `len` are rays; idle ones after them fill the last group.
#[derive(Clone, Debug, Default)]
struct LaneRays {
    x: Vec<f32>,
    y: Vec<f32>,
    z: Vec<f32>,
    end: Vec<i64>,
    steps: Vec<i64>,
    ray: Vec<u32>,
    len: usize,
}

impl LaneRays {
    /// Empty, with room for `n` rays and a group of idle ones (earlier contents beyond
    /// `len` are left: every lane read is written first).
    fn reset(&mut self, n: usize) {
        let n = n + 16;
        if self.x.len() < n {
            for v in [&mut self.x, &mut self.y, &mut self.z] {
                v.resize(n, 0.0);
            }
            self.end.resize(n, 0);
            self.steps.resize(n, 0);
            self.ray.resize(n, 0);
        }
        self.len = 0;
    }

    /// Take the rays from `origin` to `ends` whose walks stay in `cells`' box, with
    /// their end cells and step counts; the indices of
    /// the others go to `rest`. Rays that visit nothing (an end off the map, or in the
    /// origin's cell) are skipped. `reset` made room for every ray.
    fn gather(
        &mut self,
        origin: OcTreeKey,
        ends: &[Point3f],
        end_keys: &[Option<OcTreeKey>],
        cells: &CellBytes,
        rest: &mut Vec<usize>,
    ) {
        // Every cell a walk can visit lies in the box when the origin and the end each lie
        // a cell or more inside it on every axis: rounding can carry a walk one cell past
        // its end on an axis but never two (the next border is a whole cell beyond).
        let lo = cells.lo.map(i32::from);
        let dims = cells.dims.map(|d| d as i32);
        let o = origin.0.map(i32::from);
        let within = |k: [i32; 3]| (0..3).all(|a| k[a] > lo[a] && k[a] < lo[a] + dims[a] - 1);
        let origin_within = within(o);
        let [nx, ny, _] = cells.dims.map(|d| d as i64);
        let n = ends.len().min(end_keys.len());
        // Slices of the rays' length, so that their stores need no bounds check.
        let (x, y, z) = (&mut self.x[..n], &mut self.y[..n], &mut self.z[..n]);
        let (end, steps, ray) = (&mut self.end[..n], &mut self.steps[..n], &mut self.ray[..n]);
        let mut len = 0;
        for (i, (point, key)) in ends[..n].iter().zip(&end_keys[..n]).enumerate() {
            let Some(key) = *key else { continue };
            if key == origin {
                continue;
            }
            let k = key.0.map(i32::from);
            if !(origin_within && within(k)) {
                rest.push(i);
                continue;
            }
            // At most one ray per point, so `len` ≤ i < n.
            let j = len.min(n - 1);
            x[j] = point[0];
            y[j] = point[1];
            z[j] = point[2];
            end[j] = i64::from(k[0] - lo[0])
                + nx * (i64::from(k[1] - lo[1]) + ny * i64::from(k[2] - lo[2]));
            // A ray reaches its end cell after one step per cell border crossed.
            steps[j] = i64::from((k[0] - o[0]).abs() + (k[1] - o[1]).abs() + (k[2] - o[2]).abs());
            ray[j] = i as u32;
            len += 1;
        }
        self.len = len;
    }

    /// Idle rays (at the origin, ending on the spare byte, no steps) after the rays,
    /// up to a whole number of groups of `width` (at most 16).
    fn pad(&mut self, origin: Point3f, spare: i64, width: usize) {
        let whole = self.len.div_ceil(width) * width;
        for j in self.len..whole {
            self.x[j] = origin[0];
            self.y[j] = origin[1];
            self.z[j] = origin[2];
            self.end[j] = spare;
            self.steps[j] = 0;
        }
    }

    /// How many of lanes `start..start + width` are rays (the rest are idle).
    #[inline]
    fn present(&self, start: usize, width: usize) -> usize {
        self.len.saturating_sub(start).min(width)
    }

    /// Fewest and most steps of the rays among lanes `start..start + width`.
    #[inline]
    fn step_range(&self, start: usize, width: usize) -> (u32, u32) {
        let rays = &self.steps[start..start + self.present(start, width)];
        let fewest = rays.iter().copied().min().unwrap_or(i64::from(u32::MAX));
        let most = rays.iter().copied().max().unwrap_or(0);
        (fewest as u32, most as u32)
    }
}

/// Walk the rays from `origin` to every point of `ends` (`end_keys[i]` is the key of
/// `ends[i]`, `None` off the map) and mark their cells in `cells`: the origin cell
/// included, the end cell excluded, as OctoMap's `computeRayKeys`. Rays that visit
/// nothing (an end off the map, or in the origin's cell) are skipped. Returns the
/// indices of the rays left to the scalar walk: those whose cells may leave the box,
/// and those rounding carried past their end. Without a batched walk ([`batch`] is
/// `None`) every ray is left.
pub(crate) fn walk_rays(
    conv: &KeyConverter,
    origin: Point3f,
    ends: &[Point3f],
    end_keys: &[Option<OcTreeKey>],
    cells: &mut CellBytes,
) -> Vec<usize> {
    walk_rays_with(batch(), conv, origin, ends, end_keys, cells)
}

/// [`walk_rays`] with a given batched walk (`None`: none, every ray is left).
pub(crate) fn walk_rays_with(
    batch: Option<Batch>,
    conv: &KeyConverter,
    origin: Point3f,
    ends: &[Point3f],
    end_keys: &[Option<OcTreeKey>],
    cells: &mut CellBytes,
) -> Vec<usize> {
    let key_origin = conv.coord_to_key_checked(origin);
    let (Some(batch), Some(key_origin)) = (batch, key_origin) else {
        return (0..ends.len()).collect();
    };
    let mut rest = Vec::new();
    // The rays to walk, in the order given: neighbouring pixels take nearly the same
    // number of steps, so consecutive rays walk together with little waiting.
    let mut lanes = std::mem::take(&mut cells.lanes);
    lanes.reset(ends.len());
    lanes.gather(key_origin, ends, end_keys, cells, &mut rest);
    if lanes.len == 0 {
        cells.lanes = lanes;
        return rest;
    }
    // Every walk visits the origin cell first.
    let origin_cell = cells.index(key_origin);
    cells.bytes[origin_cell] = 1;
    #[cfg(target_arch = "x86_64")]
    {
        let plan = avx2::Plan::new(conv, origin, key_origin, cells);
        let width = match batch {
            Batch::Avx2 => 8,
            Batch::Avx512 => 16,
        };
        lanes.pad(origin, cells.spare() as i64, width);
        for start in (0..lanes.len).step_by(width) {
            // SAFETY: `batch` is supported by this CPU (`supported`); `holds` checked
            // every ray (so each stays in the box); `pad` filled the last group.
            let astray = unsafe {
                match batch {
                    Batch::Avx2 => avx2::walk_eight(&plan, &lanes, start, cells),
                    Batch::Avx512 => avx512::walk_sixteen(&plan, &lanes, start, cells),
                }
            };
            for lane in 0..width.min(lanes.len - start) {
                if (astray >> lane) & 1 == 1 {
                    rest.push(lanes.ray[start + lane] as usize);
                }
            }
        }
    }
    cells.lanes = lanes;
    rest
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{CellBytes, LaneRays};
    use crate::octree::key::{KeyConverter, OcTreeKey};
    use crate::octree::ray::{to_first_border, Point3f};
    use std::arch::x86_64::*;

    /// What every ray of a scan shares: its origin and what OctoMap's planning derives
    /// from it.
    pub(super) struct Plan {
        pub(super) origin: Point3f,
        pub(super) resolution: f64,
        /// (cell border − origin) for a step of +1 (`[0]`) and of −1 (`[1]`) on each
        /// axis, as `computeRayKeys` computes it (`ray::to_first_border`).
        pub(super) numerators: [[f64; 3]; 2],
        /// What a step of +1 on each axis adds to a cell's index.
        pub(super) strides: [i64; 3],
        pub(super) origin_cell: i64,
        pub(super) spare: i64,
    }

    impl Plan {
        pub(super) fn new(
            conv: &KeyConverter,
            origin: Point3f,
            key_origin: OcTreeKey,
            cells: &CellBytes,
        ) -> Self {
            let towards = |step: i32| {
                [0, 1, 2].map(|a| to_first_border(conv, key_origin.0[a], origin[a], step, true))
            };
            let [nx, ny, _] = cells.dims.map(|d| d as i64);
            Plan {
                origin,
                resolution: conv.resolution(),
                numerators: [towards(1), towards(-1)],
                strides: [1, nx, nx * ny],
                origin_cell: cells.index(key_origin) as i64,
                spare: cells.spare() as i64,
            }
        }
    }

    /// The first crossings of four rays, as OctoMap's `computeRayKeys` sets them up.
    pub(super) struct Planned {
        /// Distance to the first cell border on each axis (f64::MAX if the ray does
        /// not move on the axis).
        pub t_max: [__m256d; 3],
        /// Distance between borders on each axis (f64::MAX likewise).
        pub t_delta: [__m256d; 3],
        /// Lanes moving up (all ones) and down on each axis.
        pub up: [__m256d; 3],
        pub down: [__m256d; 3],
        /// Ray length (float, widened).
        pub length: __m256d,
    }

    /// Plan four rays from `plan`'s origin to `ends` (x, y, z of the four end points):
    /// OctoMap's arithmetic, float
    /// direction and length (`Vector3::norm`: squares summed in float left to right,
    /// root in double), double crossings.
    #[target_feature(enable = "avx2")]
    #[inline]
    pub(super) fn plan_four(plan: &Plan, ends: [__m128; 3]) -> Planned {
        let origin = plan.origin;
        let v = [0, 1, 2].map(|a| _mm_sub_ps(ends[a], _mm_set1_ps(origin[a])));
        let squares = _mm_add_ps(
            _mm_add_ps(_mm_mul_ps(v[0], v[0]), _mm_mul_ps(v[1], v[1])),
            _mm_mul_ps(v[2], v[2]),
        );
        let length = _mm256_cvtpd_ps(_mm256_sqrt_pd(_mm256_cvtps_pd(squares)));
        let zero = _mm256_setzero_pd();
        let most = _mm256_set1_pd(f64::MAX);
        let magnitude = _mm256_castsi256_pd(_mm256_set1_epi64x(i64::MAX));
        let resolution = _mm256_set1_pd(plan.resolution);
        let per_axis = |a: usize| {
            let d = _mm256_cvtps_pd(_mm_div_ps(v[a], length));
            let up = _mm256_cmp_pd::<_CMP_GT_OQ>(d, zero);
            let down = _mm256_cmp_pd::<_CMP_LT_OQ>(d, zero);
            let moving = _mm256_or_pd(up, down);
            let numerator = _mm256_blendv_pd(
                _mm256_set1_pd(plan.numerators[1][a]),
                _mm256_set1_pd(plan.numerators[0][a]),
                up,
            );
            let t_max = _mm256_blendv_pd(most, _mm256_div_pd(numerator, d), moving);
            let t_delta = _mm256_blendv_pd(
                most,
                _mm256_div_pd(resolution, _mm256_and_pd(d, magnitude)),
                moving,
            );
            (t_max, t_delta, up, down)
        };
        let (x, y, z) = (per_axis(0), per_axis(1), per_axis(2));
        Planned {
            t_max: [x.0, y.0, z.0],
            t_delta: [x.1, y.1, z.1],
            up: [x.2, y.2, z.2],
            down: [x.3, y.3, z.3],
            length: _mm256_cvtps_pd(length),
        }
    }

    /// Four rays' walks, one per lane.
    struct Four {
        t: [__m256d; 3],
        delta: [__m256d; 3],
        /// What a step on each axis adds to the cell index.
        moves: [__m256d; 3],
        length: __m256d,
        cell: __m256i,
        end: __m256i,
        /// Lanes still walking (all ones) or stopped or idle (zero).
        active: __m256i,
        /// Steps each lane takes to its end cell (0 for idle lanes).
        steps: __m256i,
        /// Fewest and most steps of the present lanes.
        fewest: u32,
        most: u32,
    }

    impl Four {
        /// Lanes `start..start + 4` of `rays`, at their origin cell, planned; idle lanes
        /// sit on the spare byte and never walk.
        #[target_feature(enable = "avx2")]
        #[inline]
        fn new(plan: &Plan, rays: &LaneRays, start: usize) -> Self {
            let four = start..start + 4;
            // Slicing checks that four lanes are there.
            let (x, y, z) = (
                &rays.x[four.clone()],
                &rays.y[four.clone()],
                &rays.z[four.clone()],
            );
            let (end, steps) = (&rays.end[four.clone()], &rays.steps[four]);
            let points = [
                _mm_setr_ps(x[0], x[1], x[2], x[3]),
                _mm_setr_ps(y[0], y[1], y[2], y[3]),
                _mm_setr_ps(z[0], z[1], z[2], z[3]),
            ];
            let (fewest, most) = rays.step_range(start, 4);
            let present = _mm256_cmpgt_epi64(
                _mm256_set1_epi64x(rays.present(start, 4) as i64),
                _mm256_setr_epi64x(0, 1, 2, 3),
            );
            let live = _mm256_castsi256_pd(present);
            let planned = plan_four(plan, points);
            let moves = [0, 1, 2].map(|a| {
                let stride = plan.strides[a];
                let up = _mm256_and_pd(
                    planned.up[a],
                    _mm256_castsi256_pd(_mm256_set1_epi64x(stride)),
                );
                let down = _mm256_and_pd(
                    planned.down[a],
                    _mm256_castsi256_pd(_mm256_set1_epi64x(-stride)),
                );
                _mm256_and_pd(_mm256_or_pd(up, down), live)
            });
            Four {
                t: planned.t_max,
                delta: planned.t_delta,
                moves,
                // A negative length stops idle lanes at once, and rays of zero length
                // after their origin cell (`ray::walk_length`).
                length: _mm256_blendv_pd(
                    _mm256_set1_pd(-1.0),
                    planned.length,
                    _mm256_and_pd(
                        live,
                        _mm256_cmp_pd::<_CMP_GT_OQ>(planned.length, _mm256_setzero_pd()),
                    ),
                ),
                cell: _mm256_blendv_epi8(
                    _mm256_set1_epi64x(plan.spare),
                    _mm256_set1_epi64x(plan.origin_cell),
                    present,
                ),
                end: _mm256_setr_epi64x(end[0], end[1], end[2], end[3]),
                active: present,
                steps: _mm256_setr_epi64x(steps[0], steps[1], steps[2], steps[3]),
                fewest,
                most,
            }
        }

        /// One step of every lane, OctoMap's axis choice: x if tx < ty and tx < tz,
        /// else y if ty < tz, else z. Returns the lanes not yet past the end's distance
        /// (`std::min(std::min(tx, ty), tz) > length` stops OctoMap's walk). Stopped
        /// lanes step on (nothing marks their cells), so that the next step does not
        /// wait for the stop test.
        #[target_feature(enable = "avx2")]
        #[inline]
        fn step(&mut self) -> __m256i {
            let [tx, ty, tz] = self.t;
            let x_lt_y = _mm256_cmp_pd::<_CMP_LT_OQ>(tx, ty);
            let mx = _mm256_and_pd(x_lt_y, _mm256_cmp_pd::<_CMP_LT_OQ>(tx, tz));
            let my = _mm256_andnot_pd(x_lt_y, _mm256_cmp_pd::<_CMP_LT_OQ>(ty, tz));
            let tx = _mm256_add_pd(tx, _mm256_and_pd(mx, self.delta[0]));
            let ty = _mm256_add_pd(ty, _mm256_and_pd(my, self.delta[1]));
            let tz = _mm256_add_pd(tz, _mm256_andnot_pd(_mm256_or_pd(mx, my), self.delta[2]));
            self.t = [tx, ty, tz];
            let [sx, sy, sz] = self.moves;
            let moved = _mm256_blendv_pd(_mm256_blendv_pd(sz, sy, my), sx, mx);
            self.cell = _mm256_add_epi64(self.cell, _mm256_castpd_si256(moved));
            let nearest = _mm256_min_pd(_mm256_min_pd(tx, ty), tz);
            _mm256_castpd_si256(_mm256_cmp_pd::<_CMP_LE_OQ>(nearest, self.length))
        }

        /// Where the lanes mark this step: their cells, or `spare` for lanes not walking.
        #[target_feature(enable = "avx2")]
        #[inline]
        fn targets(&self, spare: __m256d) -> __m256d {
            _mm256_blendv_pd(
                spare,
                _mm256_castsi256_pd(self.cell),
                _mm256_castsi256_pd(self.active),
            )
        }

        /// Step `step` of lanes that take different numbers of steps: lanes short of
        /// their end cell mark (their targets are returned, `spare` for the others),
        /// lanes reaching it now report whether they are astray (bits).
        #[target_feature(enable = "avx2")]
        #[inline]
        fn step_apart(&mut self, step: u32, spare: __m256d) -> (__m256d, i32) {
            let within = self.step();
            let now = _mm256_set1_epi64x(i64::from(step));
            let reaching = _mm256_and_si256(self.active, _mm256_cmpeq_epi64(self.steps, now));
            let astray = self.astray(reaching, within);
            self.active = _mm256_and_si256(self.active, within);
            let short = _mm256_and_si256(self.active, _mm256_cmpgt_epi64(self.steps, now));
            let targets = _mm256_blendv_pd(
                spare,
                _mm256_castsi256_pd(self.cell),
                _mm256_castsi256_pd(short),
            );
            (targets, astray)
        }

        /// Of `lanes` after their last step: those not at their end cells though still
        /// walking (rounding carried them past the end on some axis; the scalar walk
        /// would go on), as bits.
        #[target_feature(enable = "avx2")]
        #[inline]
        fn astray(&self, lanes: __m256i, within: __m256i) -> i32 {
            let walking = _mm256_and_si256(lanes, within);
            let astray = _mm256_andnot_si256(_mm256_cmpeq_epi64(self.cell, self.end), walking);
            _mm256_movemask_pd(_mm256_castsi256_pd(astray))
        }
    }

    /// Plan and walk lanes `start..start + 8` of `rays`. Returns the lanes the scalar
    /// walk must redo, as bits (see [`Four::astray`]).
    ///
    /// # Safety
    /// AVX2 must be available, `cells` must hold every ray ([`CellBytes::holds`]) and
    /// `rays` must have eight lanes from `start` on.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn walk_eight(
        plan: &Plan,
        rays: &LaneRays,
        start: usize,
        cells: &mut CellBytes,
    ) -> u32 {
        // Two named groups, not an array: LLVM keeps their state in registers then.
        let mut a = Four::new(plan, rays, start);
        let mut b = Four::new(plan, rays, start + 4);
        let last = _mm256_set1_epi64x(plan.spare);
        let spare = _mm256_castsi256_pd(last);
        debug_assert_eq!(plan.spare as usize, cells.spare());
        let bytes = cells.bytes.as_mut_ptr();
        let mut at = [0u64; 8];
        // Indices are cells of the box (`holds`) or the spare byte; clamping them to the
        // spare byte (each 32-bit half: valid ones fit in the low half) keeps the
        // stores in the buffer whatever happens.
        let mut mark = |ta: __m256d, tb: __m256d| {
            _mm256_storeu_si256(
                at.as_mut_ptr().cast(),
                _mm256_min_epu32(_mm256_castpd_si256(ta), last),
            );
            _mm256_storeu_si256(
                at[4..].as_mut_ptr().cast(),
                _mm256_min_epu32(_mm256_castpd_si256(tb), last),
            );
            for &i in &at {
                // SAFETY: at most the spare byte's index, by the clamp.
                *bytes.add(i as usize) = 1;
            }
        };
        // An idle group (no rays) has no fewest: the other group's counts rule.
        let fewest = a.fewest.min(b.fewest);
        let most = a.most.max(b.most);
        macro_rules! targets {
            ($group:expr) => {{
                $group.active = _mm256_and_si256($group.active, $group.step());
                $group.targets(spare)
            }};
        }
        // Steps before any lane reaches its end cell mark every lane's cell.
        for _ in 1..fewest {
            let (ta, tb) = (targets!(a), targets!(b));
            mark(ta, tb);
        }
        // From the first lane's end cell on, each lane marks until its own.
        let mut astray = 0;
        for step in fewest..=most {
            let (ta, astray_a) = a.step_apart(step, spare);
            let (tb, astray_b) = b.step_apart(step, spare);
            astray |= astray_a | (astray_b << 4);
            if step < most {
                mark(ta, tb);
            }
        }
        astray as u32
    }

    #[cfg(test)]
    pub(super) mod tests {
        use super::*;

        /// A planned lane as `plan_ray` reports it: step, t_max, t_delta, length.
        pub(in crate::octree::walk_avx2) type Lane = ([i32; 3], [f64; 3], [f64; 3], f64);

        /// `plan_four`'s lanes.
        #[target_feature(enable = "avx2")]
        pub(in crate::octree::walk_avx2) fn lanes(plan: &Plan, ends: [Point3f; 4]) -> [Lane; 4] {
            let axis = |a: usize| _mm_setr_ps(ends[0][a], ends[1][a], ends[2][a], ends[3][a]);
            let p = plan_four(plan, [axis(0), axis(1), axis(2)]);
            let get = |v: __m256d| {
                let mut out = [0.0; 4];
                // SAFETY: four doubles into an array of four.
                unsafe { _mm256_storeu_pd(out.as_mut_ptr(), v) };
                out
            };
            let (t_max, t_delta, length) = (p.t_max.map(get), p.t_delta.map(get), get(p.length));
            let (up, down) = (p.up.map(get), p.down.map(get));
            [0, 1, 2, 3].map(|l| {
                let step = [0, 1, 2].map(|a| {
                    i32::from(up[a][l].to_bits() != 0) - i32::from(down[a][l].to_bits() != 0)
                });
                (
                    step,
                    [0, 1, 2].map(|a| t_max[a][l]),
                    [0, 1, 2].map(|a| t_delta[a][l]),
                    length[l],
                )
            })
        }
    }
}

/// The batched walk with AVX-512: eight rays a vector, lanes chosen by mask registers
/// instead of blends; two vectors (sixteen rays) walk interleaved. The same arithmetic
/// as [`avx2`], lane for lane.
#[cfg(target_arch = "x86_64")]
mod avx512 {
    use super::avx2::Plan;
    use super::{CellBytes, LaneRays};
    use std::arch::x86_64::*;

    /// Eight rays' walks, one per lane (see `avx2::Four`).
    struct Eight {
        t: [__m512d; 3],
        delta: [__m512d; 3],
        moves: [__m512i; 3],
        length: __m512d,
        cell: __m512i,
        end: __m512i,
        active: __mmask8,
        steps: __m512i,
        fewest: u32,
        most: u32,
    }

    impl Eight {
        /// Lanes `start..start + 8` of `rays` planned as `avx2::plan_four` does, at
        /// their origin cell; idle lanes never walk.
        #[target_feature(enable = "avx512f")]
        #[inline]
        fn new(plan: &Plan, rays: &LaneRays, start: usize) -> Self {
            let eight = start..start + 8;
            // Slicing checks that eight lanes are there.
            let (x, y, z) = (
                &rays.x[eight.clone()],
                &rays.y[eight.clone()],
                &rays.z[eight.clone()],
            );
            let (end, steps) = (&rays.end[eight.clone()], &rays.steps[eight]);
            let (fewest, most) = rays.step_range(start, 8);
            let present = ((1u32 << rays.present(start, 8)) - 1) as __mmask8;
            let v = [
                _mm256_sub_ps(
                    _mm256_setr_ps(x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7]),
                    _mm256_set1_ps(plan.origin[0]),
                ),
                _mm256_sub_ps(
                    _mm256_setr_ps(y[0], y[1], y[2], y[3], y[4], y[5], y[6], y[7]),
                    _mm256_set1_ps(plan.origin[1]),
                ),
                _mm256_sub_ps(
                    _mm256_setr_ps(z[0], z[1], z[2], z[3], z[4], z[5], z[6], z[7]),
                    _mm256_set1_ps(plan.origin[2]),
                ),
            ];
            // `Vector3::norm`: squares summed in float left to right, root in double.
            let squares = _mm256_add_ps(
                _mm256_add_ps(_mm256_mul_ps(v[0], v[0]), _mm256_mul_ps(v[1], v[1])),
                _mm256_mul_ps(v[2], v[2]),
            );
            let length = _mm512_cvtpd_ps(_mm512_sqrt_pd(_mm512_cvtps_pd(squares)));
            let zero = _mm512_setzero_pd();
            let most_t = _mm512_set1_pd(f64::MAX);
            let resolution = _mm512_set1_pd(plan.resolution);
            let mut t = [zero; 3];
            let mut delta = [zero; 3];
            let mut moves = [_mm512_setzero_si512(); 3];
            for a in 0..3 {
                let d = _mm512_cvtps_pd(_mm256_div_ps(v[a], length));
                let up = _mm512_cmp_pd_mask::<_CMP_GT_OQ>(d, zero);
                let down = _mm512_cmp_pd_mask::<_CMP_LT_OQ>(d, zero);
                let moving = up | down;
                let numerator = _mm512_mask_blend_pd(
                    up,
                    _mm512_set1_pd(plan.numerators[1][a]),
                    _mm512_set1_pd(plan.numerators[0][a]),
                );
                t[a] = _mm512_mask_div_pd(most_t, moving, numerator, d);
                delta[a] = _mm512_mask_div_pd(most_t, moving, resolution, _mm512_abs_pd(d));
                let stride = plan.strides[a];
                moves[a] = _mm512_mask_mov_epi64(
                    _mm512_maskz_mov_epi64(present & down, _mm512_set1_epi64(-stride)),
                    present & up,
                    _mm512_set1_epi64(stride),
                );
            }
            let length = _mm512_cvtps_pd(length);
            let walks = present & _mm512_cmp_pd_mask::<_CMP_GT_OQ>(length, zero);
            Eight {
                t,
                delta,
                moves,
                // A negative length stops idle lanes at once, and rays of zero length
                // after their origin cell (`ray::walk_length`).
                length: _mm512_mask_mov_pd(_mm512_set1_pd(-1.0), walks, length),
                cell: _mm512_mask_mov_epi64(
                    _mm512_set1_epi64(plan.spare),
                    present,
                    _mm512_set1_epi64(plan.origin_cell),
                ),
                end: _mm512_setr_epi64(
                    end[0], end[1], end[2], end[3], end[4], end[5], end[6], end[7],
                ),
                active: present,
                steps: _mm512_setr_epi64(
                    steps[0], steps[1], steps[2], steps[3], steps[4], steps[5], steps[6], steps[7],
                ),
                fewest,
                most,
            }
        }

        /// One step of every lane (OctoMap's axis choice, as `avx2::Four::step`);
        /// returns the lanes not yet past the end's distance.
        #[target_feature(enable = "avx512f")]
        #[inline]
        fn step(&mut self) -> __mmask8 {
            let [tx, ty, tz] = self.t;
            let x_lt_y = _mm512_cmp_pd_mask::<_CMP_LT_OQ>(tx, ty);
            let mx = _mm512_mask_cmp_pd_mask::<_CMP_LT_OQ>(x_lt_y, tx, tz);
            let my = _mm512_mask_cmp_pd_mask::<_CMP_LT_OQ>(!x_lt_y, ty, tz);
            let mz = !(mx | my);
            let tx = _mm512_mask_add_pd(tx, mx, tx, self.delta[0]);
            let ty = _mm512_mask_add_pd(ty, my, ty, self.delta[1]);
            let tz = _mm512_mask_add_pd(tz, mz, tz, self.delta[2]);
            self.t = [tx, ty, tz];
            let [sx, sy, sz] = self.moves;
            let moved = _mm512_mask_blend_epi64(mx, _mm512_mask_blend_epi64(my, sz, sy), sx);
            self.cell = _mm512_add_epi64(self.cell, moved);
            let nearest = _mm512_min_pd(_mm512_min_pd(tx, ty), tz);
            _mm512_cmp_pd_mask::<_CMP_LE_OQ>(nearest, self.length)
        }

        /// Step `step` of lanes that take different numbers of steps (as
        /// `avx2::Four::step_apart`): where lanes mark, and which lanes reaching their
        /// end cell now are astray (bits).
        #[target_feature(enable = "avx512f")]
        #[inline]
        fn step_apart(&mut self, step: u32, spare: __m512i) -> (__m512i, u32) {
            let within = self.step();
            let now = _mm512_set1_epi64(i64::from(step));
            let reaching = self.active & _mm512_cmpeq_epi64_mask(self.steps, now);
            let astray = reaching & within & !_mm512_cmpeq_epi64_mask(self.cell, self.end);
            self.active &= within;
            let short = self.active & _mm512_cmpgt_epi64_mask(self.steps, now);
            (
                _mm512_mask_mov_epi64(spare, short, self.cell),
                u32::from(astray),
            )
        }
    }

    /// Plan and walk lanes `start..start + 16` of `rays`, as `avx2::walk_eight`.
    /// Returns the lanes the scalar walk must redo, as bits.
    ///
    /// # Safety
    /// AVX-512F must be available, `cells` must hold every ray ([`CellBytes::holds`])
    /// and `rays` must have sixteen lanes from `start` on.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn walk_sixteen(
        plan: &Plan,
        rays: &LaneRays,
        start: usize,
        cells: &mut CellBytes,
    ) -> u32 {
        let mut a = Eight::new(plan, rays, start);
        let mut b = Eight::new(plan, rays, start + 8);
        let spare = _mm512_set1_epi64(plan.spare);
        debug_assert_eq!(plan.spare as usize, cells.spare());
        let bytes = cells.bytes.as_mut_ptr();
        let mut at = [0u64; 16];
        // Clamped to the spare byte, the stores stay in the buffer whatever happens.
        let mut mark = |ta: __m512i, tb: __m512i| {
            _mm512_storeu_si512(at.as_mut_ptr().cast(), _mm512_min_epu64(ta, spare));
            _mm512_storeu_si512(at[8..].as_mut_ptr().cast(), _mm512_min_epu64(tb, spare));
            // Read back through memory: extracting sixteen lanes from registers costs
            // more shuffles than the port that runs them can take.
            for slot in &at {
                let i = std::ptr::read_volatile(slot);
                // SAFETY: at most the spare byte's index, by the clamp.
                *bytes.add(i as usize) = 1;
            }
        };
        let fewest = a.fewest.min(b.fewest);
        let most = a.most.max(b.most);
        macro_rules! targets {
            ($group:expr) => {{
                $group.active &= $group.step();
                _mm512_mask_mov_epi64(spare, $group.active, $group.cell)
            }};
        }
        for _ in 1..fewest {
            let (ta, tb) = (targets!(a), targets!(b));
            mark(ta, tb);
        }
        let mut astray = 0;
        for step in fewest..=most {
            let (ta, astray_a) = a.step_apart(step, spare);
            let (tb, astray_b) = b.step_apart(step, spare);
            astray |= astray_a | (astray_b << 8);
            if step < most {
                mark(ta, tb);
            }
        }
        astray
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::octree::ray::{compute_ray_keys, plan_ray, walk_from, RayPlan, RayStart};
    use std::collections::BTreeSet;

    /// xorshift64*: deterministic test data without a dependency.
    struct Rng(u64);
    impl Rng {
        fn unit(&mut self) -> f64 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
        }
        fn within(&mut self, lo: f64, hi: f64) -> f64 {
            lo + (hi - lo) * self.unit()
        }
    }

    /// Ray ends of every awkward kind around `origin`: anywhere, on cell borders, on
    /// the origin's axes and planes, and near or in the origin's own cell.
    fn awkward_ends(rng: &mut Rng, origin: Point3f, res: f64, count: usize) -> Vec<Point3f> {
        (0..count)
            .map(|i| {
                let mut p = [0f32; 3];
                for (a, c) in p.iter_mut().enumerate() {
                    let off = rng.within(-2.0, 2.0);
                    *c = match i % 5 {
                        // On a cell border (an exact multiple of the resolution).
                        0 => ((f64::from(origin[a]) + off) / res).round() as f32 * res as f32,
                        // Level with the origin on some axes.
                        1 if a == i % 3 => origin[a],
                        2 if a != i % 3 => origin[a],
                        // Near the origin.
                        3 => origin[a] + (off * 0.01) as f32,
                        _ => origin[a] + off as f32,
                    };
                }
                p
            })
            .collect()
    }

    fn scalar_cells(start: &RayStart) -> Vec<OcTreeKey> {
        let mut cells = Vec::new();
        walk_from(start, &mut |k: OcTreeKey| cells.push(k));
        cells
    }

    #[test]
    fn planned_lanes_are_plan_ray_bit_for_bit() {
        if !available() {
            return;
        }
        let mut rng = Rng(0x9E37_79B9_7F4A_7C15);
        for &res in &[0.05, 0.02, 0.1, 0.013] {
            let conv = KeyConverter::new(res);
            for _ in 0..20 {
                let origin = [0, 1, 2].map(|_| rng.within(-3.0, 3.0) as f32);
                let Some(key_origin) = conv.coord_to_key_checked(origin) else {
                    continue;
                };
                let cells = CellBytes::new(key_origin.0, [1, 1, 1]);
                let plan = avx2::Plan::new(&conv, origin, key_origin, &cells);
                for four in awkward_ends(&mut rng, origin, res, 500).chunks_exact(4) {
                    let ends: [Point3f; 4] = [four[0], four[1], four[2], four[3]];
                    // SAFETY: AVX2 is available (checked above).
                    let lanes = unsafe { avx2::tests::lanes(&plan, ends) };
                    for (lane, &end) in ends.iter().enumerate() {
                        let RayPlan::Walk(want) = plan_ray(&conv, origin, end) else {
                            continue;
                        };
                        let (step, t_max, t_delta, length) = lanes[lane];
                        assert_eq!(step, want.step, "{end:?}");
                        assert_eq!(length.to_bits(), want.length.to_bits());
                        for a in 0..3 {
                            assert_eq!(
                                t_max[a].to_bits(),
                                want.t_max[a].to_bits(),
                                "t_max {a} of {end:?}"
                            );
                            assert_eq!(
                                t_delta[a].to_bits(),
                                want.t_delta[a].to_bits(),
                                "t_delta {a} of {end:?}"
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn rays_are_walked_in_the_box_only_when_their_walk_stays_in_it() {
        // A 6 × 5 × 4 box; origins inside it, on its faces and one cell in; ends on
        // every key from one cell outside the box to one cell beyond it.
        let lo = [100u16, 200, 300];
        let dims = [6usize, 5, 4];
        let cells = CellBytes::new(lo, dims);
        let span = |a: usize| (lo[a] - 1)..=(lo[a] + dims[a] as u16);
        let keys: Vec<OcTreeKey> = span(0)
            .flat_map(|x| span(1).flat_map(move |y| span(2).map(move |z| OcTreeKey([x, y, z]))))
            .collect();
        // The reference: every cell of the walk's box (the two end cells', one cell wider
        // on every side) lies in the box.
        let holds = |o: OcTreeKey, e: OcTreeKey| {
            (0..3).all(|a| {
                let (least, most) = (
                    i64::from(o.0[a].min(e.0[a])) - 1,
                    i64::from(o.0[a].max(e.0[a])) + 1,
                );
                least >= i64::from(lo[a]) && most < i64::from(lo[a]) + dims[a] as i64
            })
        };
        let ends: Vec<Point3f> = (0..keys.len()).map(|i| [i as f32, 0.0, 0.0]).collect();
        let mut end_keys: Vec<Option<OcTreeKey>> = keys.iter().copied().map(Some).collect();
        end_keys[3] = None; // off the map: skipped
        for origin in [
            keys[0],
            OcTreeKey([101, 201, 301]),
            OcTreeKey([102, 202, 301]),
            OcTreeKey([105, 202, 302]),
        ] {
            let mut lanes = LaneRays::default();
            lanes.reset(ends.len());
            let mut rest = Vec::new();
            lanes.gather(origin, &ends, &end_keys, &cells, &mut rest);
            let taken: Vec<usize> = lanes.ray[..lanes.len].iter().map(|&i| i as usize).collect();
            let want_taken: Vec<usize> = (0..keys.len())
                .filter(|&i| end_keys[i].is_some_and(|e| e != origin && holds(origin, e)))
                .collect();
            let want_rest: Vec<usize> = (0..keys.len())
                .filter(|&i| end_keys[i].is_some_and(|e| e != origin && !holds(origin, e)))
                .collect();
            assert_eq!(taken, want_taken, "origin {origin:?}");
            assert_eq!(rest, want_rest, "origin {origin:?}");
            for (j, &i) in taken.iter().enumerate() {
                let e = keys[i];
                assert_eq!(lanes.end[j], cells.index(e) as i64);
                let steps: u32 = (0..3)
                    .map(|a| u32::from(origin.0[a].abs_diff(e.0[a])))
                    .sum();
                assert_eq!(lanes.steps[j], i64::from(steps));
                assert_eq!(lanes.x[j], ends[i][0]);
            }
        }
    }

    #[test]
    fn a_ray_too_short_for_float_visits_its_origin_cell_alone() {
        // The end is 3e-45 from an origin on a cell border, across the border: the
        // squares underflow, the length is 0 and OctoMap's walk would never end.
        let conv = KeyConverter::new(0.05);
        let origin = [0.0f32, 0.0, 0.0];
        let ends = [[0.0f32, -3e-45, 3e-45], [-3e-45, -3e-45, 3e-45]];
        let key_origin = conv.coord_to_key_checked(origin).unwrap_or_default();
        for end in ends {
            let mut cells = Vec::new();
            // (A walk that never ends fails here instead of hanging the tests.)
            let visit = |k| {
                cells.push(k);
                assert!(cells.len() < 1000, "the walk of {end:?} does not end");
            };
            assert!(compute_ray_keys(&conv, origin, end, visit));
            assert_eq!(cells, vec![key_origin], "scalar walk of {end:?}");
        }
        let keys: Vec<_> = ends.iter().map(|&e| conv.coord_to_key_checked(e)).collect();
        for batch in supported() {
            let lo = key_origin.0.map(|k| k - 4);
            let mut box_ = CellBytes::new(lo, [8, 8, 8]);
            let rest = walk_rays_with(Some(batch), &conv, origin, &ends, &keys, &mut box_);
            assert!(rest.is_empty());
            let marked: Vec<usize> = (0..box_.spare()).filter(|&i| box_.bytes[i] != 0).collect();
            assert_eq!(marked, vec![box_.index(key_origin)], "{batch:?}");
        }
    }

    /// Cells the batched walk marks for `ends`, with those of the rays it hands back
    /// walked by the scalar walk; and how many it handed back.
    fn batched_cells(
        batch: Batch,
        conv: &KeyConverter,
        origin: Point3f,
        ends: &[Point3f],
    ) -> (BTreeSet<OcTreeKey>, usize) {
        let keys: Vec<_> = ends.iter().map(|&e| conv.coord_to_key_checked(e)).collect();
        // A box around everything, one cell wider, as `trace` builds it.
        let all: Vec<OcTreeKey> = keys
            .iter()
            .flatten()
            .copied()
            .chain(conv.coord_to_key_checked(origin))
            .collect();
        let lo = [0, 1, 2].map(|a| all.iter().map(|k| k.0[a]).min().unwrap_or(0) - 1);
        let hi = [0, 1, 2].map(|a| all.iter().map(|k| k.0[a]).max().unwrap_or(0) + 1);
        let dims = [0, 1, 2].map(|a| usize::from(hi[a] - lo[a]) + 1);
        let mut cells = CellBytes::new(lo, dims);
        let rest = walk_rays_with(Some(batch), conv, origin, ends, &keys, &mut cells);
        let mut got = BTreeSet::new();
        for x in 0..dims[0] {
            for y in 0..dims[1] {
                for z in 0..dims[2] {
                    let key = OcTreeKey([x, y, z].map(|c| c as u16)).0;
                    let key = OcTreeKey([0, 1, 2].map(|a| key[a] + lo[a]));
                    if cells.bytes[cells.index(key)] != 0 {
                        got.insert(key);
                    }
                }
            }
        }
        for &i in &rest {
            if let RayPlan::Walk(s) = plan_ray(conv, origin, ends[i]) {
                got.extend(scalar_cells(&s));
            }
        }
        (got, rest.len())
    }

    fn scalar_union(conv: &KeyConverter, origin: Point3f, ends: &[Point3f]) -> BTreeSet<OcTreeKey> {
        ends.iter()
            .filter_map(|&e| match plan_ray(conv, origin, e) {
                RayPlan::Walk(s) => Some(scalar_cells(&s)),
                _ => None,
            })
            .flatten()
            .collect()
    }

    #[test]
    fn batched_walk_marks_the_scalar_walks_cells() {
        let mut rng = Rng(0x0123_4567_89AB_CDEF);
        for batch in supported() {
            let mut astray = 0;
            for &res in &[0.05, 0.02, 0.1] {
                let conv = KeyConverter::new(res);
                for _ in 0..10 {
                    let origin = [0, 1, 2].map(|_| rng.within(-3.0, 3.0) as f32);
                    let ends = awkward_ends(&mut rng, origin, res, 2000);
                    let (got, rest) = batched_cells(batch, &conv, origin, &ends);
                    astray += rest;
                    let want = scalar_union(&conv, origin, &ends);
                    assert_eq!(
                        got.len(),
                        want.len(),
                        "{batch:?}: res {res}, origin {origin:?}"
                    );
                    assert!(got == want, "{batch:?}: res {res}, origin {origin:?}");
                }
            }
            // The scalar hand-back must have been exercised by the border ends.
            assert!(astray > 0, "{batch:?}: no ray was handed back");
        }
    }

    #[test]
    fn each_group_of_lanes_marks_its_own_rays_cells() {
        // Sixteen rays at a time (one call of the widest walk), of very different
        // lengths: a lane that marked past its end or stopped short would show here,
        // where few other rays cover for it.
        let mut rng = Rng(0x5151_7A7A_0F0F_3C3C);
        for batch in supported() {
            let conv = KeyConverter::new(0.1);
            for _ in 0..5 {
                let origin = [0, 1, 2].map(|_| rng.within(-3.0, 3.0) as f32);
                let ends = awkward_ends(&mut rng, origin, 0.1, 800);
                for group in ends.chunks(16) {
                    let (got, _) = batched_cells(batch, &conv, origin, group);
                    assert!(
                        got == scalar_union(&conv, origin, group),
                        "{batch:?}: {group:?}"
                    );
                }
            }
        }
    }
}
