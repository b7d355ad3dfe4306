//! Ray traversal through cells, replicating OctoMap's `computeRayKeys` and `castRay`
//! (Amanatides & Woo's 3D DDA) with OctoMap's mix of float and double arithmetic, so
//! that both visit exactly the same cells.

use super::key::{KeyConverter, OcTreeKey, TREE_MAX_VAL};

/// OctoMap's `point3d`: three floats.
pub type Point3f = [f32; 3];

#[inline]
pub fn sub(a: Point3f, b: Point3f) -> Point3f {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// `Vector3::norm`: squares summed in float, square root in double.
#[inline]
pub fn norm(v: Point3f) -> f64 {
    f64::from(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

/// `Vector3::normalized`: divide by the float-cast norm (unchanged if zero).
#[inline]
pub fn normalized(v: Point3f) -> Point3f {
    let len = norm(v);
    if len > 0.0 {
        let l = len as f32;
        [v[0] / l, v[1] / l, v[2] / l]
    } else {
        v
    }
}

/// `origin + direction * (float) range`.
#[inline]
pub fn point_at(origin: Point3f, direction: Point3f, range: f32) -> Point3f {
    [
        origin[0] + direction[0] * range,
        origin[1] + direction[1] * range,
        origin[2] + direction[2] * range,
    ]
}

/// OctoMap's numerator of a ray's first crossing on one axis: (the border of the
/// origin's cell in the direction of `step`) − origin, the border being the cell's
/// centre plus half a cell, that half cast to float when `half_step_as_float`.
#[inline]
pub(crate) fn to_first_border(
    conv: &KeyConverter,
    key: u16,
    origin: f32,
    step: i32,
    half_step_as_float: bool,
) -> f64 {
    let half = f64::from(step) * conv.resolution() * 0.5;
    let half = if half_step_as_float {
        f64::from(half as f32)
    } else {
        half
    };
    (conv.key_to_coord_axis(key) + half) - f64::from(origin)
}

/// DDA state shared by both traversals.
struct Dda {
    step: [i32; 3],
    t_max: [f64; 3],
    t_delta: [f64; 3],
}

impl Dda {
    /// `half_step` is how OctoMap offsets the cell centre to its border:
    /// computeRayKeys casts `step·res/2` to float, castRay keeps it double.
    #[inline]
    fn new(
        conv: &KeyConverter,
        key: OcTreeKey,
        origin: Point3f,
        direction: Point3f,
        half_step_as_float: bool,
    ) -> Self {
        let res = conv.resolution();
        let mut dda = Dda {
            step: [0; 3],
            t_max: [f64::MAX; 3],
            t_delta: [f64::MAX; 3],
        };
        for i in 0..3 {
            let d = direction[i];
            dda.step[i] = if d > 0.0 {
                1
            } else if d < 0.0 {
                -1
            } else {
                0
            };
            if dda.step[i] != 0 {
                let to_border =
                    to_first_border(conv, key.0[i], origin[i], dda.step[i], half_step_as_float);
                dda.t_max[i] = to_border / f64::from(d);
                dda.t_delta[i] = res / f64::from(d.abs());
            }
        }
        dda
    }

    /// Axis of the next cell boundary (OctoMap's tie-breaking).
    #[inline]
    fn next_axis(&self) -> usize {
        let t = &self.t_max;
        if t[0] < t[1] {
            if t[0] < t[2] {
                0
            } else {
                2
            }
        } else if t[1] < t[2] {
            1
        } else {
            2
        }
    }
}

/// Receives the cells of a ray in order. `moved` is the axis (0, 1, 2) whose key
/// changed since the previous cell, or 3 for the first cell, so that a receiver can
/// update per-axis state instead of recomputing everything from the key.
pub trait RayCells {
    /// Called once per cell, in the order the ray crosses them.
    fn cell(&mut self, key: OcTreeKey, moved: usize);
}

impl<F: FnMut(OcTreeKey)> RayCells for F {
    #[inline(always)]
    fn cell(&mut self, key: OcTreeKey, _moved: usize) {
        self(key)
    }
}

/// Call `visit` for every cell a ray from `origin` to `end` crosses, the origin's cell
/// included and the end cell excluded (OctoMap's `computeRayKeys`). Returns `false`
/// (visiting nothing) when either point is off the map.
#[inline]
pub fn compute_ray_keys(
    conv: &KeyConverter,
    origin: Point3f,
    end: Point3f,
    mut visit: impl FnMut(OcTreeKey),
) -> bool {
    walk_ray(conv, origin, end, &mut visit)
}

/// The state a ray's walk starts from (OctoMap's initialisation phase).
#[derive(Clone, Copy, Debug)]
pub(crate) struct RayStart {
    pub key_origin: OcTreeKey,
    pub key_end: OcTreeKey,
    pub step: [i32; 3],
    pub t_max: [f64; 3],
    pub t_delta: [f64; 3],
    /// Ray length (float, widened).
    pub length: f64,
}

/// What walking a ray involves.
pub(crate) enum RayPlan {
    /// An end is off the map: OctoMap visits nothing (and reports failure).
    OffMap,
    /// Both ends in one cell: nothing to visit.
    SameCell,
    Walk(RayStart),
}

#[inline(always)]
pub(crate) fn plan_ray(conv: &KeyConverter, origin: Point3f, end: Point3f) -> RayPlan {
    let (Some(key_origin), Some(key_end)) = (
        conv.coord_to_key_checked(origin),
        conv.coord_to_key_checked(end),
    ) else {
        return RayPlan::OffMap;
    };
    if key_origin == key_end {
        return RayPlan::SameCell;
    }
    let mut direction = sub(end, origin);
    let length = norm(direction) as f32;
    direction = [
        direction[0] / length,
        direction[1] / length,
        direction[2] / length,
    ];
    let dda = Dda::new(conv, key_origin, origin, direction, true);
    RayStart {
        key_origin,
        key_end,
        step: dda.step,
        t_max: dda.t_max,
        t_delta: dda.t_delta,
        length: walk_length(length),
    }
    .into()
}

/// The length a walk tests against. An end within ~1e-22 of the origin (the squares
/// underflow) but across a cell border gives a zero length and an infinite or NaN
/// direction, all of whose crossings lie at 0: OctoMap's walk then never ends. Such a
/// ray visits the origin cell alone here: a negative length stops its walk after that
/// cell.
#[inline(always)]
pub(crate) fn walk_length(length: f32) -> f64 {
    if length > 0.0 {
        f64::from(length)
    } else {
        -1.0
    }
}

impl From<RayStart> for RayPlan {
    fn from(r: RayStart) -> Self {
        RayPlan::Walk(r)
    }
}

/// [`compute_ray_keys`] for any [`RayCells`] receiver.
#[inline(always)]
pub fn walk_ray<V: RayCells>(
    conv: &KeyConverter,
    origin: Point3f,
    end: Point3f,
    cells: &mut V,
) -> bool {
    match plan_ray(conv, origin, end) {
        RayPlan::OffMap => false,
        RayPlan::SameCell => true,
        RayPlan::Walk(start) => {
            walk_from(&start, cells);
            true
        }
    }
}

/// The incremental phase of OctoMap's `computeRayKeys`, origin cell included.
#[inline(always)]
pub(crate) fn walk_from<V: RayCells>(start: &RayStart, cells: &mut V) {
    let RayStart {
        key_origin,
        key_end,
        step: dda_step,
        t_max,
        t_delta,
        length,
    } = *start;
    cells.cell(key_origin, 3);
    let dda = Dda {
        step: dda_step,
        t_max,
        t_delta,
    };
    // Everything in scalars so the loop lives in registers (an indexed u16 key array
    // made every step wait on a store-to-load forward). The axis choice stays a
    // branch: prediction runs ahead of the float dependency chain, which a
    // branchless select would serialise (measured 3x slower).
    let [sx, sy, sz] = dda.step;
    let [dx, dy, dz] = dda.t_delta;
    let [mut tx, mut ty, mut tz] = dda.t_max;
    let (mut kx, mut ky, mut kz) = (
        i32::from(key_origin.0[0]),
        i32::from(key_origin.0[1]),
        i32::from(key_origin.0[2]),
    );
    let (ex, ey, ez) = (
        i32::from(key_end.0[0]),
        i32::from(key_end.0[1]),
        i32::from(key_end.0[2]),
    );
    // After a step on `$axis`: stop at the end cell, or once past the end point's
    // distance without reaching its cell (rounding); else report the cell.
    macro_rules! arrive {
        ($axis:expr) => {{
            if kx == ex && ky == ey && kz == ez {
                break;
            }
            if min3(tx, ty, tz) > length {
                break;
            }
            // Keys stay in range for in-range end points; the casts cannot panic regardless.
            cells.cell(OcTreeKey([kx as u16, ky as u16, kz as u16]), $axis);
        }};
    }
    loop {
        // OctoMap's tie-breaking: strict `<`, later axis on ties.
        if tx < ty {
            if tx < tz {
                kx += sx;
                tx += dx;
                arrive!(0);
            } else {
                kz += sz;
                tz += dz;
                arrive!(2);
            }
        } else if ty < tz {
            ky += sy;
            ty += dy;
            arrive!(1);
        } else {
            kz += sz;
            tz += dz;
            arrive!(2);
        }
    }
}

/// `std::min(std::min(a, b), c)` as C++ evaluates it (no NaN handling needed here).
#[inline(always)]
fn min3(a: f64, b: f64, c: f64) -> f64 {
    let ab = if b < a { b } else { a };
    if c < ab {
        c
    } else {
        ab
    }
}

/// Outcome of [`cast_ray`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RayHit {
    /// An occupied cell was reached.
    pub hit: bool,
    /// Centre of the occupied cell, or of the last cell visited when nothing was hit.
    pub end: [f64; 3],
}

/// OctoMap's `castRay`: walk from `origin` along `direction` until an occupied cell
/// (hit), an unknown cell (miss, unless `ignore_unknown`), `max_range` (if > 0) or the
/// map's edge. `occupancy(key)` returns `None` for unknown, `Some(occupied)` otherwise.
pub fn cast_ray(
    conv: &KeyConverter,
    origin: Point3f,
    direction: Point3f,
    ignore_unknown: bool,
    max_range: f64,
    occupancy: impl Fn(OcTreeKey) -> Option<bool>,
) -> Option<RayHit> {
    let centre = |k: OcTreeKey| {
        let p = conv.key_to_point(k);
        [f64::from(p[0]), f64::from(p[1]), f64::from(p[2])]
    };
    // Where the walk ends at `key`: an occupied cell (hit), or unknown space (miss).
    let stop_at = |key: OcTreeKey| match occupancy(key) {
        Some(true) => Some(RayHit {
            hit: true,
            end: centre(key),
        }),
        None if !ignore_unknown => Some(RayHit {
            hit: false,
            end: centre(key),
        }),
        _ => None,
    };
    let mut key = conv.coord_to_key_checked(origin)?;
    if let Some(stop) = stop_at(key) {
        return Some(stop);
    }
    let direction = normalized(direction);
    let dda_init = Dda::new(conv, key, origin, direction, false);
    if dda_init.step == [0, 0, 0] {
        return None;
    }
    let mut dda = dda_init;
    let max_range_set = max_range > 0.0;
    let max_range_sq = max_range * max_range;
    loop {
        let dim = dda.next_axis();
        let k = i32::from(key.0[dim]);
        if (dda.step[dim] < 0 && k == 0) || (dda.step[dim] > 0 && k == 2 * TREE_MAX_VAL - 1) {
            return Some(RayHit {
                hit: false,
                end: centre(key),
            });
        }
        key.0[dim] = (k + dda.step[dim]) as u16;
        dda.t_max[dim] += dda.t_delta[dim];
        let end = conv.key_to_point(key);
        if max_range_set {
            let mut dist_sq = 0.0f64;
            for j in 0..3 {
                let d = end[j] - origin[j];
                dist_sq += f64::from(d * d); // float product, double sum, as in OctoMap
            }
            if dist_sq > max_range_sq {
                return Some(RayHit {
                    hit: false,
                    end: centre(key),
                });
            }
        }
        if let Some(stop) = stop_at(key) {
            return Some(stop);
        }
    }
}

impl super::occupancy::OcTree {
    /// Cast a ray through the map (see [`cast_ray`]); `max_range` of `None` is unlimited.
    pub fn cast_ray(
        &self,
        origin: [f64; 3],
        direction: [f64; 3],
        max_range: Option<f64>,
        ignore_unknown: bool,
    ) -> crate::Result<RayHit> {
        use crate::geometry::{fmt_num, fmt_point};
        use crate::Error;
        if !direction.iter().all(|c| c.is_finite()) || direction == [0.0; 3] {
            return Err(Error::InvalidArgument(format!(
                "direction {} must be finite and non-zero",
                fmt_point(&direction)
            )));
        }
        if let Some(r) = max_range {
            if !(r.is_finite() && r > 0.0) {
                return Err(Error::InvalidArgument(format!(
                    "max_range must be a positive distance in metres, got {}",
                    fmt_num(r)
                )));
            }
        }
        self.key_of("origin", origin)?;
        let o = [origin[0] as f32, origin[1] as f32, origin[2] as f32];
        let d = [
            direction[0] as f32,
            direction[1] as f32,
            direction[2] as f32,
        ];
        let occupancy = |k: OcTreeKey| self.search(k, 0).map(|l| self.is_occupied_log_odds(l));
        cast_ray(
            self.key_converter(),
            o,
            d,
            ignore_unknown,
            max_range.unwrap_or(-1.0),
            occupancy,
        )
        .ok_or_else(|| {
            Error::InvalidArgument(format!(
                "cannot cast a ray from {} along {} (off the map or zero in float precision)",
                fmt_point(&origin),
                fmt_point(&direction)
            ))
        })
    }
}
