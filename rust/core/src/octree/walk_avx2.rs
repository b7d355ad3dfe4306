//! The exact ray walk of [`super::ray::walk_from`], four rays at a time in AVX2 lanes.
//!
//! The scalar walk spends most of its time on mispredicted branches: which axis to step
//! next is as unpredictable as the ray's slope. Here every lane takes its axis by masks,
//! so nothing is predicted, and four rays share each instruction. The arithmetic is the
//! scalar walk's, in the same double-precision operations (no fused multiply-add), so
//! the cells are the same bit for bit.
//!
//! What keeps the loop short:
//! - A ray reaches its end cell after exactly `n = Σ|end − origin|` steps (each step moves
//!   one axis one cell towards the end), so rays are grouped by `n` and a group runs
//!   until its longest ray is done; there is no key comparison in the loop.
//! - A walk that rounding carries one cell past its end on some axis (possible when the
//!   end point lies on a cell border) never meets the end cell; the scalar walk then goes
//!   on until it passes the end's distance. Such rays are rare and are handed back to the
//!   scalar walk, which marks the rest of their cells.
//! - Cells are bytes of a box in plain x-fastest order ([`CellBytes`]), so a lane keeps
//!   its cell's index instead of its key (a step adds ±1, ±X or ±XY) and marks it with a
//!   byte store: no read-modify-write that the next step's store to the same word would
//!   wait on. The bytes are folded into the octree's bricks of bits once per scan.

use super::key::{KeyConverter, OcTreeKey};
use super::ray::{plan_ray, Point3f, RayPlan, RayStart};

/// One byte per cell of a key box (non-zero: a ray crossed the cell), x fastest, plus
/// a spare byte at the end that idle lanes write to.
#[derive(Clone, Debug)]
pub(crate) struct CellBytes {
    pub bytes: Vec<u8>,
    /// Lowest key of the box.
    pub lo: [u16; 3],
    /// Box size in cells.
    pub dims: [usize; 3],
}

impl CellBytes {
    /// All clear. The allocation is zeroed lazily by the OS (`calloc`), so only the
    /// pages rays touch cost anything.
    pub fn new(lo: [u16; 3], dims: [usize; 3]) -> Self {
        CellBytes {
            bytes: vec![0; dims.iter().product::<usize>() + 1],
            lo,
            dims,
        }
    }

    /// Index of the spare byte (after the box's cells).
    #[inline]
    pub fn spare(&self) -> usize {
        self.bytes.len() - 1
    }

    /// Index of a key in the box (the caller checked it is inside).
    #[inline]
    fn index(&self, key: [u16; 3]) -> usize {
        let k = [0, 1, 2].map(|a| usize::from(key[a] - self.lo[a]));
        k[0] + self.dims[0] * (k[1] + self.dims[1] * k[2])
    }

    /// Whether every cell the ray can visit lies in the box: its two end cells' box,
    /// one cell wider on every side, since rounding can carry a walk one cell past its
    /// end on an axis but never two (the next border is a whole cell beyond the end).
    #[inline]
    fn holds(&self, r: &RayStart) -> bool {
        (0..3).all(|a| {
            let (o, e) = (r.key_origin.0[a], r.key_end.0[a]);
            let (lo, hi) = (i64::from(o.min(e)) - 1, i64::from(o.max(e)) + 1);
            lo >= i64::from(self.lo[a]) && hi < i64::from(self.lo[a]) + self.dims[a] as i64
        })
    }
}

/// Steps from the origin cell to the end cell.
#[inline]
fn steps(r: &RayStart) -> u32 {
    (0..3)
        .map(|a| u32::from(r.key_origin.0[a].abs_diff(r.key_end.0[a])))
        .sum()
}

/// Whether this CPU runs the batched walk.
pub(crate) fn available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        // `EARCORE_NO_AVX2` (any value) forces the scalar walk: for comparisons, and
        // for tests of the fallback on machines that have AVX2.
        static OFF: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
        std::arch::is_x86_feature_detected!("avx2")
            && !*OFF.get_or_init(|| std::env::var_os("EARCORE_NO_AVX2").is_some())
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Walk `rays` (the origin cell included, the end cell excluded, as the scalar walk)
/// and mark their cells in `cells`. Returns the indices of the rays the scalar walk
/// must (re)do: those whose cells may leave the box, and those rounding carried past
/// their end. Without AVX2 ([`available`] is false) every ray is returned.
pub(crate) fn walk_rays(rays: &[RayStart], cells: &mut CellBytes) -> Vec<usize> {
    if !available() {
        return (0..rays.len()).collect();
    }
    let mut redo = Vec::new();
    // Rays by step count (a counting sort), so that the lanes of a group finish
    // together.
    let mut order: Vec<(u32, u32)> = Vec::with_capacity(rays.len());
    let mut count: Vec<u32> = Vec::new();
    let mut origin = None;
    for (i, r) in rays.iter().enumerate() {
        if !cells.holds(r) {
            redo.push(i);
            continue;
        }
        // The walk visits its origin cell first (rays of a scan share it).
        if origin != Some(r.key_origin) {
            origin = Some(r.key_origin);
            let at = cells.index(r.key_origin.0);
            cells.bytes[at] = 1;
        }
        let n = steps(r);
        if count.len() <= n as usize {
            count.resize(n as usize + 1, 0);
        }
        count[n as usize] += 1;
        order.push((n, i as u32));
    }
    let mut ends: Vec<u32> = Vec::with_capacity(count.len() + 1);
    ends.push(0);
    for c in &count {
        ends.push(ends[ends.len() - 1] + c);
    }
    let mut sorted = vec![0u32; order.len()];
    let mut next = ends.clone();
    for &(n, i) in &order {
        sorted[next[n as usize] as usize] = i;
        next[n as usize] += 1;
    }
    for (n, bounds) in ends.windows(2).enumerate() {
        let n = n as u32;
        let group = &sorted[bounds[0] as usize..bounds[1] as usize];
        for eight in group.chunks(8) {
            let pick = [0, 1, 2, 3, 4, 5, 6, 7].map(|lane| eight.get(lane).copied());
            #[cfg(target_arch = "x86_64")]
            {
                let lanes = pick.map(|i| i.map(|i| &rays[i as usize]));
                // SAFETY: `available()` checked for AVX2; `holds` checked every lane;
                // the lanes share a step count.
                let back = unsafe { avx2::walk_group(lanes, n, cells) };
                for (lane, i) in pick.into_iter().enumerate() {
                    if let (true, Some(i)) = (back[lane], i) {
                        redo.push(i as usize);
                    }
                }
            }
        }
    }
    redo
}

/// [`plan_ray`] for many rays from one origin, the float work four rays at a time
/// (same operations in the same precisions, so the same bits). Returns each walking
/// ray's start in `starts` and its index in `ends` in `index` (both cleared first).
/// `end_keys[i]` is `ends[i]`'s key (`None` off the map).
pub(crate) fn plan_rays(
    conv: &KeyConverter,
    origin: Point3f,
    ends: &[Point3f],
    end_keys: &[Option<OcTreeKey>],
    starts: &mut Vec<RayStart>,
    index: &mut Vec<u32>,
) {
    starts.clear();
    index.clear();
    #[cfg(target_arch = "x86_64")]
    if available() {
        if let Some(key_origin) = conv.coord_to_key_checked(origin) {
            // OctoMap's numerator of t_max, (cell border − origin), for a step of +1
            // and of −1 on each axis: the border is the origin cell's centre plus half
            // a cell cast to float.
            let half = f64::from((conv.resolution() * 0.5) as f32);
            let centre = key_origin.0.map(|k| conv.key_to_coord_axis(k));
            let towards =
                |sign: f64| [0, 1, 2].map(|a| (centre[a] + sign * half) - f64::from(origin[a]));
            let numerators = [towards(1.0), towards(-1.0)];
            for (four, chunk) in ends.chunks(4).enumerate() {
                let mut lanes = [origin; 4];
                lanes[..chunk.len()].copy_from_slice(chunk);
                // SAFETY: AVX2 was detected.
                let float =
                    unsafe { avx2::plan_four(origin, numerators, conv.resolution(), lanes) };
                for lane in 0..chunk.len() {
                    let Some(key_end) = end_keys[4 * four + lane] else {
                        continue;
                    };
                    if key_end == key_origin {
                        continue;
                    }
                    let axes = |v: &[[f64; 4]; 3]| [v[0][lane], v[1][lane], v[2][lane]];
                    let length = f64::from(float.length[lane]);
                    starts.push(RayStart {
                        key_origin,
                        key_end,
                        step: [
                            float.step[0][lane],
                            float.step[1][lane],
                            float.step[2][lane],
                        ],
                        t_max: axes(&float.t_max),
                        t_delta: axes(&float.t_delta),
                        length,
                    });
                    index.push((4 * four + lane) as u32);
                }
            }
            return;
        }
    }
    for (i, &end) in ends.iter().enumerate() {
        if let RayPlan::Walk(start) = plan_ray(conv, origin, end) {
            starts.push(start);
            index.push(i as u32);
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::CellBytes;
    use crate::octree::ray::{Point3f, RayStart};
    use std::arch::x86_64::*;

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
    }

    impl Four {
        /// The lanes' walks at their origin cells; idle lanes (`None`) never walk.
        #[target_feature(enable = "avx2")]
        #[inline]
        fn new(lanes: &[Option<&RayStart>], cells: &CellBytes) -> Self {
            let [nx, ny, _] = cells.dims.map(|d| d as i64);
            let stride = [1, nx, nx * ny];
            // Lane by lane, then loaded as vectors. Idle lanes get a negative length,
            // which stops them at once.
            let (mut t, mut delta, mut moves) = ([[0.0; 4]; 3], [[0.0; 4]; 3], [[0i64; 4]; 3]);
            // Idle lanes sit on the spare byte and never move.
            let spare = cells.spare() as i64;
            let (mut length, mut cell, mut end) = ([-1.0; 4], [spare; 4], [spare; 4]);
            for (lane, r) in lanes.iter().enumerate().take(4) {
                let Some(r) = r else { continue };
                for a in 0..3 {
                    t[a][lane] = r.t_max[a];
                    delta[a][lane] = r.t_delta[a];
                    moves[a][lane] = i64::from(r.step[a]) * stride[a];
                }
                length[lane] = r.length;
                cell[lane] = cells.index(r.key_origin.0) as i64;
                end[lane] = cells.index(r.key_end.0) as i64;
            }
            let pd = |v: [f64; 4]| _mm256_setr_pd(v[0], v[1], v[2], v[3]);
            let epi = |v: [i64; 4]| _mm256_setr_epi64x(v[0], v[1], v[2], v[3]);
            let length = pd(length);
            Four {
                t: t.map(pd),
                delta: delta.map(pd),
                moves: moves.map(|m| _mm256_castsi256_pd(epi(m))),
                length,
                cell: epi(cell),
                end: epi(end),
                active: _mm256_castpd_si256(_mm256_cmp_pd::<_CMP_GE_OQ>(
                    length,
                    _mm256_setzero_pd(),
                )),
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

        /// After the last step: the lanes not at their end cells though still walking
        /// (rounding carried them past the end on some axis; the scalar walk would go
        /// on), as bits.
        #[target_feature(enable = "avx2")]
        #[inline]
        fn astray(&self, within: __m256i) -> i32 {
            let walking = _mm256_and_si256(self.active, within);
            let astray = _mm256_andnot_si256(_mm256_cmpeq_epi64(self.cell, self.end), walking);
            _mm256_movemask_pd(_mm256_castsi256_pd(astray))
        }
    }

    /// Walk up to eight rays (empty lanes stay idle) that all take `steps` steps to
    /// their end cells, in two interleaved groups of four (one group's step waits on
    /// its previous one; two keep the core busy). Returns, per lane, whether the scalar
    /// walk must redo the ray (see [`Four::astray`]).
    ///
    /// # Safety
    /// AVX2 must be available, `cells` must hold every lane's ray
    /// ([`CellBytes::holds`]), and every lane's ray must take `steps` steps.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn walk_group(
        lanes: [Option<&RayStart>; 8],
        steps: u32,
        cells: &mut CellBytes,
    ) -> [bool; 8] {
        // Two named groups, not an array: LLVM keeps their state in registers then.
        let (mut a, mut b) = (Four::new(&lanes[..4], cells), Four::new(&lanes[4..], cells));
        let spare = _mm256_castsi256_pd(_mm256_set1_epi64x(cells.spare() as i64));
        let bytes = cells.bytes.as_mut_ptr();
        let mut at = [0u64; 8];
        macro_rules! targets {
            ($group:expr) => {{
                $group.active = _mm256_and_si256($group.active, $group.step());
                $group.targets(spare)
            }};
        }
        // Steps 1 to n − 1 reach the cells before the end cell: mark them.
        for _ in 1..steps {
            let (ta, tb) = (targets!(a), targets!(b));
            _mm256_storeu_pd(at.as_mut_ptr().cast(), ta);
            _mm256_storeu_pd(at[4..].as_mut_ptr().cast(), tb);
            for &i in &at {
                // SAFETY: a cell of the box (`holds`) or the spare byte.
                *bytes.add(i as usize) = 1;
            }
        }
        // Step n reaches the end cell.
        let (within_a, within_b) = (a.step(), b.step());
        let astray = a.astray(within_a) | (b.astray(within_b) << 4);
        [0, 1, 2, 3, 4, 5, 6, 7].map(|lane| lanes[lane].is_some() && (astray >> lane) & 1 == 1)
    }

    /// What `plan_four` computes, axis by axis for four lanes (`step[axis][lane]`).
    pub(super) struct FourStarts {
        pub step: [[i32; 4]; 3],
        pub t_max: [[f64; 4]; 3],
        pub t_delta: [[f64; 4]; 3],
        pub length: [f32; 4],
    }

    /// The float part of `plan_ray` for four rays from `origin`: per ray its steps,
    /// t_max, t_delta and length. `numerators[0]` and `[1]` are (border − origin) for
    /// steps of +1 and −1.
    #[target_feature(enable = "avx2")]
    pub(super) fn plan_four(
        origin: Point3f,
        numerators: [[f64; 3]; 2],
        resolution: f64,
        ends: [Point3f; 4],
    ) -> FourStarts {
        let axis = |a: usize| {
            let v = _mm_setr_ps(ends[0][a], ends[1][a], ends[2][a], ends[3][a]);
            _mm_sub_ps(v, _mm_set1_ps(origin[a]))
        };
        let v = [axis(0), axis(1), axis(2)];
        // `Vector3::norm`: squares summed in float, left to right, root in double.
        let squares = _mm_add_ps(
            _mm_add_ps(_mm_mul_ps(v[0], v[0]), _mm_mul_ps(v[1], v[1])),
            _mm_mul_ps(v[2], v[2]),
        );
        let length = _mm256_cvtpd_ps(_mm256_sqrt_pd(_mm256_cvtps_pd(squares)));
        let zero = _mm256_setzero_pd();
        let most = _mm256_set1_pd(f64::MAX);
        let magnitude = _mm256_castsi256_pd(_mm256_set1_epi64x(i64::MAX));
        let mut t_max = [[0.0; 4]; 3];
        let mut t_delta = [[0.0; 4]; 3];
        let mut step = [[0i32; 4]; 3];
        for a in 0..3 {
            let d = _mm256_cvtps_pd(_mm_div_ps(v[a], length));
            let up = _mm256_cmp_pd::<_CMP_GT_OQ>(d, zero);
            let down = _mm256_cmp_pd::<_CMP_LT_OQ>(d, zero);
            let moving = _mm256_or_pd(up, down);
            let numerator = _mm256_blendv_pd(
                _mm256_set1_pd(numerators[1][a]),
                _mm256_set1_pd(numerators[0][a]),
                up,
            );
            let tm = _mm256_blendv_pd(most, _mm256_div_pd(numerator, d), moving);
            let td = _mm256_blendv_pd(
                most,
                _mm256_div_pd(_mm256_set1_pd(resolution), _mm256_and_pd(d, magnitude)),
                moving,
            );
            // SAFETY: four doubles into arrays of four.
            unsafe {
                _mm256_storeu_pd(t_max[a].as_mut_ptr(), tm);
                _mm256_storeu_pd(t_delta[a].as_mut_ptr(), td);
            }
            let (up, down) = (_mm256_movemask_pd(up), _mm256_movemask_pd(down));
            for (lane, s) in step[a].iter_mut().enumerate() {
                *s = ((up >> lane) & 1) - ((down >> lane) & 1);
            }
        }
        let mut lengths = [0f32; 4];
        // SAFETY: four floats into an array of four.
        unsafe { _mm_storeu_ps(lengths.as_mut_ptr(), length) };
        FourStarts {
            step,
            t_max,
            t_delta,
            length: lengths,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::octree::ray::walk_from;
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
    /// the origin's axes and planes, and in the origin's own cell.
    fn awkward_ends(rng: &mut Rng, origin: Point3f, res: f64, count: usize) -> Vec<Point3f> {
        (0..count)
            .map(|i| {
                let mut p = [0f32; 3];
                for a in 0..3 {
                    let off = rng.within(-2.0, 2.0);
                    p[a] = match i % 5 {
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
    fn planned_rays_are_plan_rays_bit_for_bit() {
        let mut rng = Rng(0x9E37_79B9_7F4A_7C15);
        for &res in &[0.05, 0.02, 0.1, 0.013] {
            let conv = KeyConverter::new(res);
            for _ in 0..20 {
                let origin = [0, 1, 2].map(|_| rng.within(-3.0, 3.0) as f32);
                let ends = awkward_ends(&mut rng, origin, res, 501);
                let (mut starts, mut index) = (Vec::new(), Vec::new());
                let keys: Vec<_> = ends.iter().map(|&e| conv.coord_to_key_checked(e)).collect();
                plan_rays(&conv, origin, &ends, &keys, &mut starts, &mut index);
                let expected: Vec<(u32, RayStart)> = ends
                    .iter()
                    .enumerate()
                    .filter_map(|(i, &e)| match plan_ray(&conv, origin, e) {
                        RayPlan::Walk(s) => Some((i as u32, s)),
                        _ => None,
                    })
                    .collect();
                assert_eq!(index, expected.iter().map(|e| e.0).collect::<Vec<_>>());
                for (got, (_, want)) in starts.iter().zip(&expected) {
                    assert_eq!(got.key_origin, want.key_origin);
                    assert_eq!(got.key_end, want.key_end);
                    assert_eq!(got.step, want.step);
                    assert_eq!(got.length.to_bits(), want.length.to_bits());
                    for a in 0..3 {
                        assert_eq!(
                            got.t_max[a].to_bits(),
                            want.t_max[a].to_bits(),
                            "t_max {a} of {got:?}"
                        );
                        assert_eq!(
                            got.t_delta[a].to_bits(),
                            want.t_delta[a].to_bits(),
                            "t_delta {a}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn batched_walk_marks_the_scalar_walks_cells() {
        let mut rng = Rng(0x0123_4567_89AB_CDEF);
        let mut astray = 0;
        for &res in &[0.05, 0.02, 0.1] {
            let conv = KeyConverter::new(res);
            for _ in 0..10 {
                let origin = [0, 1, 2].map(|_| rng.within(-3.0, 3.0) as f32);
                let ends = awkward_ends(&mut rng, origin, res, 2000);
                let (mut starts, mut index) = (Vec::new(), Vec::new());
                let keys: Vec<_> = ends.iter().map(|&e| conv.coord_to_key_checked(e)).collect();
                plan_rays(&conv, origin, &ends, &keys, &mut starts, &mut index);
                // A box around everything, one cell wider, as `trace` builds it.
                let keys: Vec<OcTreeKey> = starts
                    .iter()
                    .flat_map(|s| [s.key_origin, s.key_end])
                    .collect();
                let lo = [0, 1, 2].map(|a| keys.iter().map(|k| k.0[a]).min().unwrap_or(0) - 1);
                let hi = [0, 1, 2].map(|a| keys.iter().map(|k| k.0[a]).max().unwrap_or(0) + 1);
                let dims = [0, 1, 2].map(|a| usize::from(hi[a] - lo[a]) + 1);
                let mut cells = CellBytes::new(lo, dims);
                let redo = walk_rays(&starts, &mut cells);
                assert!(cells.bytes[cells.spare()] <= 1);
                let mut got = BTreeSet::new();
                for x in 0..dims[0] {
                    for y in 0..dims[1] {
                        for z in 0..dims[2] {
                            let key = [x, y, z].map(|c| c as u16);
                            let key = [0, 1, 2].map(|a| key[a] + lo[a]);
                            if cells.bytes[cells.index(key)] != 0 {
                                got.insert(OcTreeKey(key));
                            }
                        }
                    }
                }
                for &i in &redo {
                    got.extend(scalar_cells(&starts[i]));
                }
                astray += redo.len();
                let want: BTreeSet<OcTreeKey> = starts.iter().flat_map(scalar_cells).collect();
                assert_eq!(got.len(), want.len(), "res {res}, origin {origin:?}");
                assert!(got == want, "res {res}, origin {origin:?}");
            }
        }
        // The scalar hand-back must have been exercised by the border ends.
        assert!(astray > 0, "no ray was handed back");
    }
}
