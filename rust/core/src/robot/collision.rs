//! Batched collision checks, clearance and the danger cost of a motion, for a robot
//! against a `VoxelIndex` of the map.

use crate::error::{Error, Result};
use crate::octree::OcTree;
use crate::robot::body::{Body, NearestContact};
use crate::robot::capsule::point_segment_distance_squared;
use crate::robot::chain::Frame;
use crate::robot::model::{LazyPlacement, PlacedBodies, RobotModel};
use crate::robot::voxel_index::{
    Clearance, ClearanceScratch, SampleVerdict, UndecidedRuns, VoxelIndex,
};
use crate::threads::map_parts;

/// What a configuration hits first.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Contact {
    /// Nothing is hit.
    Free,
    /// A body (by link index) overlaps an occupied voxel.
    Obstacle(usize),
    /// Two bodies (link indices) touch.
    SelfCollision(usize, usize),
}

impl Contact {
    /// Whether nothing is hit.
    pub fn is_free(&self) -> bool {
        *self == Contact::Free
    }

    /// The first link involved, if any.
    pub fn link(&self) -> Option<usize> {
        match *self {
            Contact::Free => None,
            Contact::Obstacle(l) | Contact::SelfCollision(l, _) => Some(l),
        }
    }
}

/// Options of the checks.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CheckParams {
    /// Also test the robot's link pairs against each other (default: true).
    pub self_collision: bool,
}

impl Default for CheckParams {
    fn default() -> Self {
        CheckParams {
            self_collision: true,
        }
    }
}

/// Configurations stored row-major, `dof` values each.
fn rows(qs: &[f64], dof: usize) -> Result<usize> {
    if dof == 0 || !qs.len().is_multiple_of(dof) {
        return Err(Error::InvalidArgument(format!(
            "configurations must have {dof} values each, got {} values in all",
            qs.len()
        )));
    }
    Ok(qs.len() / dof)
}

fn check_all(model: &RobotModel, qs: &[f64]) -> Result<usize> {
    let dof = model.dof();
    let k = rows(qs, dof)?;
    for (i, q) in qs.chunks(dof).enumerate() {
        model.chain().check_configuration(q, i)?;
    }
    Ok(k)
}

/// Per-thread scratch for placing bodies.
struct Scratch {
    frames: Vec<Frame>,
    placed: PlacedBodies,
    lazy: LazyPlacement,
    undecided: Vec<(usize, Body, UndecidedRuns)>,
    /// The order in which bodies meet the distance-field pass: a body that collides
    /// moves one place forward, so in a batch the bodies that usually collide come
    /// first and a colliding configuration ends after fewer samples.
    order: Vec<usize>,
}

impl Scratch {
    fn new(model: &RobotModel) -> Self {
        Scratch {
            frames: vec![Frame::identity(); model.chain().num_links()],
            placed: PlacedBodies::default(),
            lazy: model.lazy_placement(),
            undecided: Vec::new(),
            order: Vec::new(),
        }
    }
}

fn contact_of(
    model: &RobotModel,
    index: &VoxelIndex,
    params: CheckParams,
    q: &[f64],
    scratch: &mut Scratch,
) -> Result<Contact> {
    // Bodies are placed as the checks reach them: a collision found early spares the
    // rest of the forward kinematics.
    let lazy = &mut scratch.lazy;
    lazy.reset();
    // First the cheap distance-field pass over every body (a certain collision ends
    // it), then exact scans where it left doubt. The verdict does not depend on the
    // order; which colliding link is reported (or whether a body outside the index is
    // reported before a collision is found) does.
    scratch.undecided.clear();
    if scratch.order.is_empty() {
        scratch.order = (0..lazy.links.len()).filter(|&b| lazy.moving[b]).collect();
    }
    for at in 0..scratch.order.len() {
        let b = scratch.order[at];
        let (link, body) = (lazy.links[b], lazy.body(model, q, b));
        match index.body_samples(&body)? {
            SampleVerdict::Collides => {
                scratch.order.swap(at, at.saturating_sub(1));
                return Ok(Contact::Obstacle(link));
            }
            SampleVerdict::Free => {}
            SampleVerdict::Undecided(runs) => scratch.undecided.push((link, body, runs)),
        }
    }
    for (link, body, runs) in &scratch.undecided {
        if index.body_scan(body, runs) {
            return Ok(Contact::Obstacle(*link));
        }
    }
    if params.self_collision {
        scratch.lazy.fill(model, q, &mut scratch.placed);
        if let Some((a, b)) = model.self_collision(&scratch.placed, model.self_collision_pairs()) {
            return Ok(Contact::SelfCollision(a, b));
        }
    }
    Ok(Contact::Free)
}

/// Split K configurations into parallel chunks.
fn chunked<R: Send>(
    qs: &[f64],
    dof: usize,
    f: impl Fn(&[f64]) -> Result<Vec<R>> + Sync + Send,
) -> Result<Vec<R>> {
    const PER_CHUNK: usize = 256;
    let chunks: Vec<&[f64]> = qs.chunks(PER_CHUNK * dof).collect();
    let mut out = Vec::with_capacity(qs.len() / dof.max(1));
    for part in map_parts(&chunks, |c| f(c)) {
        out.extend(part?);
    }
    Ok(out)
}

/// What each configuration of `qs` (K × dof, row-major) touches first.
pub fn check_configurations(
    model: &RobotModel,
    index: &VoxelIndex,
    qs: &[f64],
    params: CheckParams,
) -> Result<Vec<Contact>> {
    check_all(model, qs)?;
    let dof = model.dof();
    chunked(qs, dof, |part| {
        let mut scratch = Scratch::new(model);
        part.chunks(dof)
            .map(|q| contact_of(model, index, params, q, &mut scratch))
            .collect()
    })
}

/// Configurations on the straight joint-space segment q0 → q1 with no joint moving
/// more than `resolution` between neighbours (both ends included).
pub fn interpolate(q0: &[f64], q1: &[f64], resolution: f64) -> Result<Vec<Vec<f64>>> {
    let steps = interpolate_steps(q0, q1, resolution)?;
    Ok((0..=steps)
        .map(|s| {
            let t = s as f64 / steps as f64;
            q0.iter().zip(q1).map(|(a, b)| a + t * (b - a)).collect()
        })
        .collect())
}

/// Is the straight motion q0 → q1 free at `resolution`? Returns the parameter t ∈ [0, 1]
/// of a colliding configuration on it, or None. Configurations are checked ends first,
/// then in bisection order (midpoint, quarter points, ...): a motion that collides
/// usually does so in a stretch of its middle, which this order finds after a few
/// checks instead of walking there from one end.
pub fn check_motion(
    model: &RobotModel,
    index: &VoxelIndex,
    q0: &[f64],
    q1: &[f64],
    resolution: f64,
    params: CheckParams,
) -> Result<Option<(f64, Contact)>> {
    model.chain().check_configuration(q0, 0)?;
    model.chain().check_configuration(q1, 1)?;
    let steps = interpolate_steps(q0, q1, resolution)?;
    let mut scratch = Scratch::new(model);
    let mut q = vec![0.0; q0.len()];
    for s in bisection_order(steps) {
        let t = s as f64 / steps as f64;
        for (j, v) in q.iter_mut().enumerate() {
            *v = q0[j] + t * (q1[j] - q0[j]);
        }
        let contact = contact_of(model, index, params, &q, &mut scratch)?;
        if !contact.is_free() {
            return Ok(Some((t, contact)));
        }
    }
    Ok(None)
}

/// Steps of `interpolate` (configurations = steps + 1).
fn interpolate_steps(q0: &[f64], q1: &[f64], resolution: f64) -> Result<usize> {
    if !(resolution.is_finite() && resolution > 0.0) {
        return Err(Error::InvalidArgument(format!(
            "resolution must be finite and > 0, got {resolution}"
        )));
    }
    if q0.len() != q1.len() {
        return Err(Error::InvalidArgument(format!(
            "q0 has {} values and q1 has {}",
            q0.len(),
            q1.len()
        )));
    }
    let largest = q0
        .iter()
        .zip(q1)
        .map(|(a, b)| (b - a).abs())
        .fold(0.0, f64::max);
    let steps = (largest / resolution).ceil().max(1.0);
    // A resolution far below any joint's precision would ask for more configurations
    // than memory holds (and `as usize` saturates, which skipped the middle).
    if steps.is_nan() || steps > MAX_MOTION_STEPS as f64 {
        return Err(Error::InvalidArgument(format!(
            "resolution {resolution} rad splits this motion ({largest} rad) into more than \
             {MAX_MOTION_STEPS} steps: use a coarser resolution"
        )));
    }
    Ok(steps as usize)
}

/// Most configurations one straight motion is split into (1 µrad over 2π is 6.3 M).
pub const MAX_MOTION_STEPS: usize = 1 << 24;

/// 0..=n with both ends first, then midpoints of ever finer halvings (each index once).
fn bisection_order(n: usize) -> Vec<usize> {
    let mut order = Vec::with_capacity(n + 1);
    order.push(0);
    if n > 0 {
        order.push(n);
    }
    let mut step = n.next_power_of_two();
    while step > 1 {
        let half = step / 2;
        order.extend((half..n).step_by(step));
        step = half;
    }
    order
}

/// Robot-to-obstacle clearance per configuration: the closest body and the closest
/// points (None where the index has no obstacle).
pub fn clearances(
    model: &RobotModel,
    index: &VoxelIndex,
    qs: &[f64],
) -> Result<Vec<Option<(usize, Clearance)>>> {
    check_all(model, qs)?;
    let dof = model.dof();
    chunked(qs, dof, |part| {
        let mut scratch = Scratch::new(model);
        let mut buffers = ClearanceScratch::default();
        let mut links = Vec::new();
        let mut bodies = Vec::new();
        part.chunks(dof)
            .map(|q| {
                model.place_into(q, &mut scratch.frames, &mut scratch.placed);
                let placed = &scratch.placed;
                links.clear();
                bodies.clear();
                for ((link, body), moving) in
                    placed.links.iter().zip(&placed.bodies).zip(&placed.moving)
                {
                    if *moving {
                        links.push(*link);
                        bodies.push(*body);
                    }
                }
                Ok(index
                    .bodies_clearance(&bodies, &mut buffers)?
                    .map(|(tag, c)| (links[tag], c)))
            })
            .collect()
    })
}

/// The arguments of the box queries: valid configurations, finite centres, finite
/// half sizes ≥ 0.
fn check_boxes(model: &RobotModel, qs: &[f64], centres: &[[f64; 3]], half: [f64; 3]) -> Result<()> {
    check_all(model, qs)?;
    if !half.iter().all(|h| h.is_finite() && *h >= 0.0) {
        return Err(Error::InvalidArgument(format!(
            "box half sizes must be finite and >= 0, got {half:?}"
        )));
    }
    if let Some(i) = centres
        .iter()
        .position(|c| !c.iter().all(|v| v.is_finite()))
    {
        return Err(Error::InvalidArgument(format!(
            "box centre {i} is not finite: {:?}",
            centres[i]
        )));
    }
    Ok(())
}

/// Whether each configuration's moving bodies meet any of the boxes (touching
/// counts; all with the same `half` size): the yes/no of `clearances_to_boxes`
/// (distance ≤ 0) in closed form, stopping at the first overlap. Cheaper than the
/// clearance where cylinders near a box would need iterative distance queries.
pub fn touches_boxes(
    model: &RobotModel,
    qs: &[f64],
    centres: &[[f64; 3]],
    half: [f64; 3],
) -> Result<Vec<bool>> {
    check_boxes(model, qs, centres, half)?;
    // The boxes' joint bounds: a body whose bounds miss them meets none (most bodies,
    // most configurations), so only bodies near the boxes test them one by one.
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for c in centres {
        for i in 0..3 {
            lo[i] = lo[i].min(c[i] - half[i]);
            hi[i] = hi[i].max(c[i] + half[i]);
        }
    }
    let dof = model.dof();
    chunked(qs, dof, |part| {
        let mut scratch = Scratch::new(model);
        Ok(part
            .chunks(dof)
            .map(|q| {
                model.place_into(q, &mut scratch.frames, &mut scratch.placed);
                let placed = &scratch.placed;
                placed
                    .bodies
                    .iter()
                    .zip(&placed.moving)
                    .filter(|(_, moving)| **moving)
                    .any(|(body, _)| {
                        let (a, b) = body.aabb();
                        (0..3).all(|i| a[i] <= hi[i] && b[i] >= lo[i])
                            && centres.iter().any(|c| body.overlaps_box(c, &half))
                    })
            })
            .collect())
    })
}

/// Robot-to-boxes clearance per configuration, for obstacles given as boxes rather
/// than a map (e.g. the voxels of one tracked obstacle, all with the same `half`
/// size): exact body-box distances (negative when overlapping), no index. A box is
/// skipped when a lower bound on its distance (centre to axis, less the box's half
/// diagonal and the body's radius) cannot beat the best found.
/// Of pairs exactly as near as each other (a link parallel to a column of voxels),
/// the one reported is the one met first, the smallest lower bound first.
pub fn clearances_to_boxes(
    model: &RobotModel,
    qs: &[f64],
    centres: &[[f64; 3]],
    half: [f64; 3],
) -> Result<Vec<Option<(usize, Clearance)>>> {
    check_boxes(model, qs, centres, half)?;
    let reach = (half[0] * half[0] + half[1] * half[1] + half[2] * half[2]).sqrt();
    let dof = model.dof();
    chunked(qs, dof, |part| {
        let mut scratch = Scratch::new(model);
        let mut nearest = NearestContact::default();
        // (lower bound, body, box) of every pair of a configuration.
        let mut bounds: Vec<(f64, usize, usize)> = Vec::new();
        part.chunks(dof)
            .map(|q| {
                model.place_into(q, &mut scratch.frames, &mut scratch.placed);
                let placed = &scratch.placed;
                nearest.clear();
                bounds.clear();
                for (b, (body, moving)) in placed.bodies.iter().zip(&placed.moving).enumerate() {
                    if !moving {
                        continue;
                    }
                    let axis = body.enclosing_capsule();
                    for (i, c) in centres.iter().enumerate() {
                        let bound = point_segment_distance_squared(&axis.a, &axis.b, c).sqrt()
                            - reach
                            - axis.radius;
                        bounds.push((bound, b, i));
                    }
                }
                // The most promising pair first: its exact distance then rules out
                // nearly every other pair by its bound alone (in body-then-box order,
                // every box of a far body was computed exactly before the near one).
                if let Some(first) = bounds
                    .iter()
                    .enumerate()
                    .min_by(|a, b| a.1 .0.total_cmp(&b.1 .0))
                    .map(|(k, _)| k)
                {
                    bounds.swap(0, first);
                }
                for &(bound, b, i) in &bounds {
                    if bound < nearest.limit() {
                        nearest.offer(placed.links[b], &placed.bodies[b], &centres[i], &half);
                    }
                }
                Ok(nearest
                    .finish()
                    .map(|(link, contact)| (link, contact.into())))
            })
            .collect()
    })
}

/// Paper II's Eq. 4 cost of the straight motion q0 → q1, per body point (bodies fixed
/// to the root do not move and add nothing):
///
/// C = Σ_bodies (1/n_b) Σ_points Σ_steps d · (1 + C_voxel)
///
/// Each body carries n_b points along its axis (one per map voxel of length, ends
/// included); the motion is cut into steps of at most `resolution` rad per joint; d is
/// the distance a point travels in a step and C_voxel the danger of the voxel holding
/// the step's midpoint (0 where none is recorded). With no danger anywhere C is the sum
/// of the bodies' mean path lengths; danger adds up to that much again.
pub fn motion_danger(
    model: &RobotModel,
    tree: &OcTree,
    q0: &[f64],
    q1: &[f64],
    resolution: f64,
) -> Result<f64> {
    model.chain().check_configuration(q0, 0)?;
    model.chain().check_configuration(q1, 1)?;
    let steps = interpolate_steps(q0, q1, resolution)?;
    robot_within_map(model, tree)?;
    let res = tree.resolution();
    // Sample parameters of each body's points: one per map voxel of length, bounded so
    // that a body far longer than the map's voxels is refused, not allocated.
    let mut counts = Vec::new();
    let mut points = 0.0;
    for c in model.bodies().iter().flatten() {
        let n = (c.axis.length() / res).ceil().max(1.0);
        points += n + 1.0;
        counts.push(n);
    }
    if !(points <= MAX_DANGER_POINTS as f64 && points * steps as f64 <= MAX_DANGER_WORK as f64) {
        return Err(Error::InvalidArgument(format!(
            "motion_danger would sample {points:.3e} body points at {} configurations \
             (at most {MAX_DANGER_POINTS} points and {MAX_DANGER_WORK} point steps): \
             use a coarser map or a coarser resolution",
            steps + 1
        )));
    }
    let ts: Vec<Vec<f64>> = counts
        .iter()
        .map(|&n| {
            let n = n as usize;
            (0..=n).map(|i| i as f64 / n as f64).collect()
        })
        .collect();
    let danger = tree.danger_map();
    let conv = tree.key_converter();
    let mut scratch = Scratch::new(model);
    let mut q = vec![0.0; q0.len()];
    let mut previous: Vec<Vec<[f64; 3]>> = Vec::new();
    let mut total = 0.0;
    for s in 0..=steps {
        // The configurations `interpolate` lists, one at a time.
        let t = s as f64 / steps as f64;
        for (j, v) in q.iter_mut().enumerate() {
            *v = q0[j] + t * (q1[j] - q0[j]);
        }
        model.place_into(&q, &mut scratch.frames, &mut scratch.placed);
        let points: Vec<Vec<[f64; 3]>> = scratch
            .placed
            .bodies
            .iter()
            .zip(&ts)
            .map(|(c, t)| t.iter().map(|&t| c.axis.axis_point(t)).collect())
            .collect();
        if !previous.is_empty() {
            for (before, after) in previous.iter().zip(&points) {
                let mut body = 0.0;
                for (p, r) in before.iter().zip(after) {
                    let d = crate::geometry::distance_squared(p, r).sqrt();
                    let mid = [
                        0.5 * (p[0] + r[0]),
                        0.5 * (p[1] + r[1]),
                        0.5 * (p[2] + r[2]),
                    ];
                    let c = conv
                        .coord_to_key_checked_f64(mid)
                        .map(|k| danger.value(k.morton()) as f64)
                        .unwrap_or(0.0);
                    body += d * (1.0 + c);
                }
                total += body / before.len() as f64;
            }
        }
        previous = points;
    }
    Ok(total)
}

/// Most body points `motion_danger` samples per configuration.
pub const MAX_DANGER_POINTS: usize = 1 << 20;

/// Most body points × configurations one `motion_danger` call evaluates (about a
/// second's work).
pub const MAX_DANGER_WORK: usize = 1 << 28;

/// Errors unless the sphere that holds the robot in every configuration (its base
/// plus `reach_bound`) lies inside the area `tree` can address: beyond it the map
/// cannot hold an obstacle, so a check there would answer "free" about space the map
/// cannot see.
pub fn robot_within_map(model: &RobotModel, tree: &OcTree) -> Result<()> {
    let t = model.base().translation;
    let reach = model.reach_bound();
    let (_, limit) = tree.key_converter().metric_limits();
    if !t.iter().all(|c| c.is_finite() && c.abs() + reach < limit) {
        return Err(Error::OutOfBounds {
            what: "the robot's base (its reach included)",
            point: [t.x, t.y, t.z],
            limit: (limit - reach).max(0.0),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::bisection_order;

    #[test]
    fn bisection_order_visits_every_index_once() {
        assert_eq!(bisection_order(4), vec![0, 4, 2, 1, 3]);
        assert_eq!(bisection_order(0), vec![0]);
        for n in 1..200 {
            let mut o = bisection_order(n);
            o.sort_unstable();
            assert_eq!(o, (0..=n).collect::<Vec<_>>(), "n = {n}");
        }
    }
}
