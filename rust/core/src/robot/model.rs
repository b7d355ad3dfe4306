//! A robot: its kinematic chain, one padded capsule per link (in the link's frame),
//! where its base stands, and which link pairs to test for self-collision.

use crate::error::{Error, Result};
use crate::robot::body::{AxisBounds, Body};
use crate::robot::chain::{Chain, Frame, JointKind, MAX_ROBOT_LENGTH};
use crate::synthetic::Rng;

/// A robot: its kinematic chain, a body per link (link frame), the base's place
/// in the world and the link pairs tested for self-collision.
///
/// ```
/// use std::f64::consts::FRAC_PI_2;
///
/// use earcore_core::na::Vector3;
/// use earcore_core::robot::{
///     check_configurations, Body, Chain, CheckParams, Contact, Frame, Joint, JointKind,
///     RobotModel, VoxelIndex,
/// };
///
/// // A base and one arm link turning about z, 0.3 m up, 0.5 m long along its x axis.
/// let shoulder = Joint {
///     name: "shoulder".into(),
///     kind: JointKind::Revolute,
///     parent: 0,
///     child: 1,
///     origin: Frame::from_xyz_rpy([0.0, 0.0, 0.3], [0.0; 3]),
///     axis: Vector3::z(),
///     lower: -3.0,
///     upper: 3.0,
/// };
/// let chain = Chain::new(vec!["base".into(), "arm".into()], vec![shoulder])?;
/// let arm = Body::capsule([0.0; 3], [0.5, 0.0, 0.0], 0.05);
/// let model = RobotModel::new(chain, vec![None, Some(arm)])?;
///
/// // At 90° the arm points along y.
/// let placed = model.place(&[FRAC_PI_2])?;
/// let tip = placed.bodies[0].axis.b;
/// assert!(tip[0].abs() < 1e-12 && (tip[1] - 0.5).abs() < 1e-12 && (tip[2] - 0.3).abs() < 1e-12);
///
/// // An obstacle voxel on the y axis is hit there, not at 0°.
/// let mut index = VoxelIndex::empty(0.05, [0.0, 0.0, 0.3], 1.0)?;
/// index.mark_point([0.02, 0.47, 0.32]);
/// index.compute_distance_field();
/// let contacts = check_configurations(&model, &index, &[0.0, FRAC_PI_2], CheckParams::default())?;
/// assert_eq!(contacts, [Contact::Free, Contact::Obstacle(1)]);
/// # Ok::<(), earcore_core::Error>(())
/// ```
#[derive(Clone, Debug)]
pub struct RobotModel {
    chain: Chain,
    /// Body of each link in the link frame (None: the link has no geometry).
    bodies: Vec<Option<Body>>,
    /// world_from_root.
    base: Frame,
    /// Link pairs tested for self-collision.
    self_pairs: Vec<(usize, usize)>,
    /// Links rigidly attached to the root (no movable joint on the way): they never
    /// move, so whatever they touch is the robot's own stand and is not an obstacle.
    fixed_to_root: Vec<bool>,
    /// The joints forward kinematics needs to place the bodies (not those leading
    /// only to frames without bodies, such as a tool flange).
    placement_joints: Vec<usize>,
}

/// The robot's bodies placed for one configuration (world frame), with their links.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlacedBodies {
    /// Link index of each body.
    pub links: Vec<usize>,
    /// The bodies, world frame.
    pub bodies: Vec<Body>,
    /// False for bodies fixed to the root (skipped by obstacle checks and clearance).
    pub moving: Vec<bool>,
}

/// Bodies placed on demand for one configuration: forward kinematics runs only as far
/// as the bodies asked for need, so a check that ends at its first body skips the rest
/// of the chain. Slots are those of `PlacedBodies` (links with bodies, in link order).
#[derive(Clone, Debug)]
pub struct LazyPlacement {
    frames: Vec<Frame>,
    /// Placement joints run so far for this configuration.
    joints_done: usize,
    bodies: Vec<Option<Body>>,
    /// Link index of each slot's body.
    pub links: Vec<usize>,
    /// False for bodies fixed to the root, as in [`PlacedBodies`].
    pub moving: Vec<bool>,
    joints_needed: Vec<usize>,
}

impl LazyPlacement {
    /// Forget the last configuration's placements.
    pub fn reset(&mut self) {
        self.joints_done = 0;
        self.bodies.fill(None);
    }

    /// The body in `slot` placed for `q` (checked by the caller; the same `q` since the
    /// last `reset`).
    #[inline]
    pub fn body(&mut self, model: &RobotModel, q: &[f64], slot: usize) -> Body {
        if let Some(body) = self.bodies[slot] {
            return body;
        }
        if self.joints_done == 0 {
            self.frames[0] = model.base;
        }
        let needed = self.joints_needed[slot];
        while self.joints_done < needed {
            let joint = model.placement_joints[self.joints_done];
            model.chain.place_child(joint, q, &mut self.frames);
            self.joints_done += 1;
        }
        let link = self.links[slot];
        let body = model.bodies[link]
            .expect("slots are links with bodies")
            .placed(&self.frames[link]);
        self.bodies[slot] = Some(body);
        body
    }

    /// Every body placed for `q`, as `place_into` would give them.
    pub fn fill(&mut self, model: &RobotModel, q: &[f64], out: &mut PlacedBodies) {
        out.links.clear();
        out.bodies.clear();
        out.moving.clear();
        for slot in 0..self.links.len() {
            out.bodies.push(self.body(model, q, slot));
        }
        out.links.extend_from_slice(&self.links);
        out.moving.extend_from_slice(&self.moving);
    }
}

impl PlacedBodies {
    /// Bounds of all bodies (min, max); inverted (empty) when there are none.
    pub fn aabb(&self) -> ([f64; 3], [f64; 3]) {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for body in &self.bodies {
            let (a, b) = body.aabb();
            for i in 0..3 {
                lo[i] = lo[i].min(a[i]);
                hi[i] = hi[i].max(b[i]);
            }
        }
        (lo, hi)
    }
}

impl RobotModel {
    /// `bodies` has one entry per link. Self-collision pairs default to
    /// `default_self_collision_pairs()`.
    pub fn new(chain: Chain, bodies: Vec<Option<Body>>) -> Result<Self> {
        if bodies.len() != chain.num_links() {
            return Err(Error::InvalidArgument(format!(
                "{} bodies for {} links",
                bodies.len(),
                chain.num_links()
            )));
        }
        if chain.dof() == 0 {
            return Err(Error::InvalidArgument(format!(
                "the robot has no movable joints ({} links, all joined by fixed joints): \
                 a configuration would be empty, so there is nothing to move or check",
                chain.num_links()
            )));
        }
        for (l, b) in bodies.iter().enumerate() {
            if let Some(body) = b {
                let c = &body.axis;
                let within = |v: &f64| v.is_finite() && v.abs() <= MAX_ROBOT_LENGTH;
                if !(c.a.iter().chain(&c.b).all(within) && within(&c.radius) && c.radius >= 0.0) {
                    return Err(Error::InvalidArgument(format!(
                        "the body of link '{}' must have finite end points and a radius >= 0, \
                         all within {MAX_ROBOT_LENGTH} m; got a = {:?}, b = {:?}, radius = {}",
                        chain.link_names()[l],
                        c.a,
                        c.b,
                        c.radius
                    )));
                }
            }
        }
        let mut fixed_to_root = vec![false; chain.num_links()];
        fixed_to_root[0] = true;
        for joint in chain.joints() {
            fixed_to_root[joint.child] = fixed_to_root[joint.parent] && !joint.is_movable();
        }
        let has_body: Vec<bool> = bodies.iter().map(|b| b.is_some()).collect();
        let placement_joints = chain.joints_reaching(&has_body);
        let mut model = RobotModel {
            chain,
            bodies,
            base: Frame::identity(),
            self_pairs: Vec::new(),
            fixed_to_root,
            placement_joints,
        };
        model.self_pairs = model.default_self_collision_pairs(1000, 1);
        Ok(model)
    }

    /// The kinematic chain.
    pub fn chain(&self) -> &Chain {
        &self.chain
    }

    /// Degrees of freedom (movable joints).
    pub fn dof(&self) -> usize {
        self.chain.dof()
    }

    /// Each link's body in the link frame (None: the link has no geometry).
    pub fn bodies(&self) -> &[Option<Body>] {
        &self.bodies
    }

    /// world_from_root: where the robot stands.
    pub fn base(&self) -> &Frame {
        &self.base
    }

    /// Move the robot's base (world_from_root).
    pub fn set_base(&mut self, base: Frame) {
        self.base = base;
    }

    /// Whether each link is rigidly attached to the root (never moves).
    pub fn fixed_to_root(&self) -> &[bool] {
        &self.fixed_to_root
    }

    /// Link pairs tested for self-collision.
    pub fn self_collision_pairs(&self) -> &[(usize, usize)] {
        &self.self_pairs
    }

    /// Replace the link pairs tested for self-collision; errors on a pair that is not
    /// two different links of the chain.
    pub fn set_self_collision_pairs(&mut self, pairs: Vec<(usize, usize)>) -> Result<()> {
        let n = self.chain.num_links();
        if let Some(p) = pairs.iter().find(|(a, b)| *a >= n || *b >= n || a == b) {
            return Err(Error::InvalidArgument(format!(
                "self-collision pair {p:?} is not two different links of {n}"
            )));
        }
        self.self_pairs = pairs;
        Ok(())
    }

    /// Radius of the sphere around the base that holds every body in every
    /// configuration (a bound from the joint offsets, not the exact reach).
    pub fn reach_bound(&self) -> f64 {
        let extent: Vec<f64> = self
            .bodies
            .iter()
            .map(|b| match b {
                Some(body) => {
                    let c = &body.axis;
                    let n = |p: &[f64; 3]| (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
                    n(&c.a).max(n(&c.b)) + c.radius
                }
                None => 0.0,
            })
            .collect();
        self.chain.reach_bound(&extent)
    }

    /// Place every body for configuration `q` (checked by the caller); `frames` is
    /// scratch space with one frame per link (only links on the way to a body are set).
    #[inline]
    pub fn place_into(&self, q: &[f64], frames: &mut [Frame], out: &mut PlacedBodies) {
        self.chain
            .forward_kinematics_of(&self.base, q, frames, &self.placement_joints);
        out.links.clear();
        out.bodies.clear();
        out.moving.clear();
        for (l, body) in self.bodies.iter().enumerate() {
            if let Some(c) = body {
                out.links.push(l);
                out.bodies.push(c.placed(&frames[l]));
                out.moving.push(!self.fixed_to_root[l]);
            }
        }
    }

    /// The links that carry bodies, in the order `place_into` lists them (body slots).
    pub fn body_links(&self) -> impl Iterator<Item = usize> + '_ {
        (0..self.bodies.len()).filter(|&l| self.bodies[l].is_some())
    }

    /// Scratch for placing bodies one at a time (see `LazyPlacement`).
    pub fn lazy_placement(&self) -> LazyPlacement {
        let links: Vec<usize> = self.body_links().collect();
        // How many of the placement joints (parent-first) must run before a body's
        // link is placed: up to and including the joint that makes that link.
        let joints_needed = links
            .iter()
            .map(|&l| {
                self.placement_joints
                    .iter()
                    .position(|&j| self.chain.joints()[j].child == l)
                    .map_or(0, |at| at + 1)
            })
            .collect();
        LazyPlacement {
            frames: vec![Frame::identity(); self.chain.num_links()],
            joints_done: 0,
            bodies: vec![None; links.len()],
            moving: links.iter().map(|&l| !self.fixed_to_root[l]).collect(),
            links,
            joints_needed,
        }
    }

    /// Check `q` and `link`, and place every link for `q` (world frames, base included).
    fn frames_for_jacobian(&self, q: &[f64], link: usize) -> Result<Vec<Frame>> {
        self.chain.check_configuration(q, 0)?;
        if link >= self.chain.num_links() {
            return Err(Error::InvalidArgument(format!(
                "link must be 0 to {} (the robot's links), got {link}",
                self.chain.num_links() - 1
            )));
        }
        let mut frames = vec![Frame::identity(); self.chain.num_links()];
        self.chain
            .forward_kinematics_into(&self.base, q, &mut frames);
        Ok(frames)
    }

    /// Jacobian (3 × dof, one `[dx, dy, dz]` per coordinate) of a point rigidly attached
    /// to `link`, given by its world position `point` at configuration `q`: how fast the
    /// point moves in the world frame per unit of each coordinate. Revolute joints on
    /// the way to `link` give `z × (point − o)` (world axis `z` through `o`), prismatic
    /// ones `z`; fixed joints and joints not on the way give zero. The exact derivative
    /// of forward kinematics (joint limits play no part; `q` must lie within them).
    pub fn point_jacobian(&self, q: &[f64], link: usize, point: [f64; 3]) -> Result<Vec<[f64; 3]>> {
        if !point.iter().all(|c| c.is_finite()) {
            return Err(Error::InvalidArgument(format!(
                "point {point:?} is not finite"
            )));
        }
        let frames = self.frames_for_jacobian(q, link)?;
        let p = crate::na::Vector3::from(point);
        Ok(self
            .chain
            .jacobian_axes(&frames, link)
            .into_iter()
            .map(|axis| match axis {
                Some(a) if a.kind == JointKind::Prismatic => a.direction.into(),
                Some(a) => a.direction.cross(&(p - a.origin)).into(),
                None => [0.0; 3],
            })
            .collect())
    }

    /// Geometric Jacobian (6 × dof) of `link`'s frame at configuration `q`, one column
    /// `[vx, vy, vz, wx, wy, wz]` per coordinate: the linear velocity of the link's
    /// origin, then the link's angular velocity, both in the world frame (Pinocchio's
    /// `LOCAL_WORLD_ALIGNED` frame Jacobian), per unit of each coordinate. The linear
    /// part is [`Self::point_jacobian`] at the link's origin.
    pub fn frame_jacobian(&self, q: &[f64], link: usize) -> Result<Vec<[f64; 6]>> {
        let frames = self.frames_for_jacobian(q, link)?;
        let p = frames[link].translation;
        Ok(self
            .chain
            .jacobian_axes(&frames, link)
            .into_iter()
            .map(|axis| match axis {
                Some(a) if a.kind == JointKind::Prismatic => {
                    let z = a.direction;
                    [z.x, z.y, z.z, 0.0, 0.0, 0.0]
                }
                Some(a) => {
                    let (z, v) = (a.direction, a.direction.cross(&(p - a.origin)));
                    [v.x, v.y, v.z, z.x, z.y, z.z]
                }
                None => [0.0; 6],
            })
            .collect())
    }

    /// Bodies placed for `q`, after checking `q`.
    pub fn place(&self, q: &[f64]) -> Result<PlacedBodies> {
        self.chain.check_configuration(q, 0)?;
        let mut frames = vec![Frame::identity(); self.chain.num_links()];
        let mut out = PlacedBodies::default();
        self.place_into(q, &mut frames, &mut out);
        Ok(out)
    }

    /// First self-colliding pair among `self_pairs` for placed bodies (capsules touch).
    pub fn self_collision(
        &self,
        placed: &PlacedBodies,
        pairs: &[(usize, usize)],
    ) -> Option<(usize, usize)> {
        // Each body's bounds and slot once, not once per pair: most pairs end at their
        // bounds, and a search for the slots cost more than the test. Small tables on
        // the stack (a robot arm has about ten links); larger robots take the plain path.
        const LINKS: usize = 64;
        const BODIES: usize = 16;
        let small = placed.bodies.len() <= BODIES && placed.links.iter().all(|&l| l < LINKS);
        if !small {
            let slot = |link: usize| placed.links.iter().position(|&l| l == link);
            return pairs.iter().copied().find(|&(a, b)| {
                let (Some(i), Some(j)) = (slot(a), slot(b)) else {
                    return false;
                };
                placed.bodies[i].intersects(&placed.bodies[j])
            });
        }
        let mut slot_of = [u8::MAX; LINKS];
        let mut bounds = [AxisBounds::default(); BODIES];
        for (k, (&link, body)) in placed.links.iter().zip(&placed.bodies).enumerate() {
            slot_of[link] = k as u8;
            bounds[k] = body.bounds();
        }
        pairs.iter().copied().find(|&(a, b)| {
            let slot = |link: usize| slot_of.get(link).copied().filter(|&k| k != u8::MAX);
            let (Some(i), Some(j)) = (slot(a), slot(b)) else {
                return false;
            };
            let (i, j) = (i as usize, j as usize);
            !bounds[i].disjoint(&bounds[j])
                && placed.bodies[i].intersects_within_bounds(&placed.bodies[j])
        })
    }

    /// Pairs worth testing, as a setup assistant would choose them: links with bodies,
    /// not parent and child, not touching at the reference configuration (zero moved
    /// into the limits), and touching in at most half of `samples` random
    /// configurations. A pair that touches more often is the capsules' envelope around
    /// a compact joint (a UR3's or UR10's first and third wrist links, whose meshes never
    /// meet), not a contact the arm could make; real self-contacts of the built-in arms
    /// occur in under 40 % of samples.
    pub fn default_self_collision_pairs(&self, samples: usize, seed: u64) -> Vec<(usize, usize)> {
        let parents = self.chain.parents();
        // Links rigidly attached (fixed joints) count as one for adjacency.
        let n = self.chain.num_links();
        let mut candidates = Vec::new();
        for a in 0..n {
            for b in a + 1..n {
                if self.bodies[a].is_none() || self.bodies[b].is_none() {
                    continue;
                }
                if parents[a] == Some(b) || parents[b] == Some(a) {
                    continue;
                }
                candidates.push((a, b));
            }
        }
        let limits = self.chain.limits();
        let finite =
            |lo: f64, hi: f64| (lo.max(-std::f64::consts::PI), hi.min(std::f64::consts::PI));
        let reference: Vec<f64> = limits
            .iter()
            .map(|&(lo, hi)| 0.0f64.clamp(lo, hi))
            .collect();
        let Ok(placed) = self.place(&reference) else {
            return candidates;
        };
        candidates.retain(|&p| self.self_collision(&placed, &[p]).is_none());
        let mut touching = vec![0usize; candidates.len()];
        let mut rng = Rng::new(seed);
        let mut frames = vec![Frame::identity(); n];
        let mut placed = PlacedBodies::default();
        for _ in 0..samples {
            let q: Vec<f64> = limits
                .iter()
                .map(|&(lo, hi)| {
                    let (lo, hi) = finite(lo, hi);
                    rng.uniform(lo, hi)
                })
                .collect();
            self.place_into(&q, &mut frames, &mut placed);
            for (k, &p) in candidates.iter().enumerate() {
                if self.self_collision(&placed, &[p]).is_some() {
                    touching[k] += 1;
                }
            }
        }
        candidates
            .into_iter()
            .zip(touching)
            .filter(|&(_, t)| 2 * t <= samples)
            .map(|(p, _)| p)
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::na::Vector3;
    use crate::robot::chain::{Joint, JointKind};

    /// A model of `n` links in a chain (one revolute joint, then fixed ones), with no
    /// bodies of its own (the test places bodies directly).
    fn fixed_chain(n: usize) -> RobotModel {
        // One movable joint first: a model needs at least one coordinate.
        let joints = (1..n)
            .map(|c| Joint {
                name: format!("j{c}"),
                kind: if c == 1 {
                    JointKind::Revolute
                } else {
                    JointKind::Fixed
                },
                parent: c - 1,
                child: c,
                origin: Frame::identity(),
                axis: Vector3::z(),
                lower: 0.0,
                upper: 0.0,
            })
            .collect();
        let names = (0..n).map(|l| format!("l{l}")).collect();
        RobotModel::new(Chain::new(names, joints).unwrap(), vec![None; n]).unwrap()
    }

    /// Both ways `self_collision` runs (stack tables for arm-sized robots, a search per
    /// pair for larger ones) report the first listed pair that touches, as testing the
    /// pairs one by one does; pairs naming links without bodies never count.
    #[test]
    fn self_collision_reports_the_first_touching_pair() {
        let mut rng = Rng::new(3);
        let mut found = 0;
        for (links, with_bodies) in [(10, 7), (12, 12), (40, 16), (40, 17), (80, 10)] {
            let model = fixed_chain(links);
            for _ in 0..200 {
                let mut chosen: Vec<usize> = (0..links).collect();
                for i in 0..links {
                    let j = i + (rng.uniform(0.0, 1.0) * (links - i) as f64) as usize;
                    chosen.swap(i, j.min(links - 1));
                }
                chosen.truncate(with_bodies);
                chosen.sort_unstable();
                let mut v = || rng.uniform(-0.5, 0.5);
                let bodies: Vec<Body> = chosen
                    .iter()
                    .map(|&l| {
                        let (a, b) = ([v(), v(), v()], [v(), v(), v()]);
                        let r = 0.05 + 0.05 * (v() + 0.5);
                        if l % 2 == 0 {
                            Body::capsule(a, b, r)
                        } else {
                            Body::cylinder(a, b, r)
                        }
                    })
                    .collect();
                let placed = PlacedBodies {
                    links: chosen.clone(),
                    moving: vec![true; chosen.len()],
                    bodies,
                };
                let mut pairs = Vec::new();
                for _ in 0..30 {
                    let a = (rng.uniform(0.0, 1.0) * links as f64) as usize % links;
                    let b = (rng.uniform(0.0, 1.0) * links as f64) as usize % links;
                    if a != b {
                        pairs.push((a, b));
                    }
                }
                let body_of = |l: usize| {
                    chosen
                        .iter()
                        .position(|&c| c == l)
                        .map(|k| &placed.bodies[k])
                };
                let expected =
                    pairs
                        .iter()
                        .copied()
                        .find(|&(a, b)| match (body_of(a), body_of(b)) {
                            (Some(p), Some(q)) => p.intersects_within_bounds(q),
                            _ => false,
                        });
                assert_eq!(model.self_collision(&placed, &pairs), expected);
                found += usize::from(expected.is_some());
            }
        }
        assert!(found > 100 && found < 900, "{found} of 1000 lists touch");
    }

    /// A branching chain with every joint kind: root → a (revolute) → b (prismatic) →
    /// c (fixed) → d (continuous), and a side branch root → e (revolute).
    fn mixed_model() -> RobotModel {
        let joint =
            |name: &str, kind, parent, child, xyz: [f64; 3], rpy: [f64; 3], axis: [f64; 3]| Joint {
                name: name.into(),
                kind,
                parent,
                child,
                origin: Frame::from_xyz_rpy(xyz, rpy),
                axis: Vector3::from(axis),
                lower: -2.0,
                upper: 2.0,
            };
        let joints = vec![
            joint(
                "ja",
                JointKind::Revolute,
                0,
                1,
                [0.1, 0.0, 0.3],
                [0.2, -0.1, 0.4],
                [0.0, 0.3, 1.0],
            ),
            joint(
                "jb",
                JointKind::Prismatic,
                1,
                2,
                [0.4, 0.1, 0.0],
                [0.0, 0.5, 0.0],
                [1.0, 0.2, 0.0],
            ),
            joint(
                "jc",
                JointKind::Fixed,
                2,
                3,
                [0.0, 0.2, 0.1],
                [0.3, 0.0, -0.2],
                [0.0, 0.0, 1.0],
            ),
            joint(
                "jd",
                JointKind::Continuous,
                3,
                4,
                [0.2, 0.0, 0.0],
                [-0.4, 0.1, 0.0],
                [1.0, 0.0, 0.0],
            ),
            joint(
                "je",
                JointKind::Revolute,
                0,
                5,
                [0.0, -0.5, 0.0],
                [0.0; 3],
                [0.0, 1.0, 0.0],
            ),
        ];
        let names = ["root", "a", "b", "c", "d", "e"].map(String::from).to_vec();
        let mut model = RobotModel::new(Chain::new(names, joints).unwrap(), vec![None; 6]).unwrap();
        let base = Frame::from_xyz_rpy([0.5, -0.2, 0.8], [0.3, 0.2, -1.0]);
        model.set_base(base);
        model
    }

    /// Central differences of forward kinematics: the point fixed to `link` and the
    /// link's rotation (as an angular velocity from R(q+h)·R(q−h)ᵀ).
    fn numeric_jacobian(
        model: &RobotModel,
        q: &[f64],
        link: usize,
        point: [f64; 3],
    ) -> Vec<[f64; 6]> {
        let frames = model.chain().forward_kinematics(model.base(), q).unwrap();
        let local =
            frames[link].rotation.transpose() * (Vector3::from(point) - frames[link].translation);
        let h = 1e-6;
        (0..q.len())
            .map(|c| {
                let at = |s: f64| {
                    let mut qq = q.to_vec();
                    qq[c] += s;
                    model.chain().forward_kinematics(model.base(), &qq).unwrap()[link]
                };
                let (f1, f0) = (at(h), at(-h));
                let v =
                    (f1.rotation * local + f1.translation - f0.rotation * local - f0.translation)
                        / (2.0 * h);
                let w = f1.rotation * f0.rotation.transpose();
                let w = Vector3::new(
                    w[(2, 1)] - w[(1, 2)],
                    w[(0, 2)] - w[(2, 0)],
                    w[(1, 0)] - w[(0, 1)],
                ) / (4.0 * h);
                [v.x, v.y, v.z, w.x, w.y, w.z]
            })
            .collect()
    }

    #[test]
    fn jacobians_match_central_differences() {
        let model = mixed_model();
        let mut rng = Rng::new(12);
        for _ in 0..50 {
            let q: Vec<f64> = (0..model.dof()).map(|_| rng.uniform(-1.9, 1.9)).collect();
            let frames = model.chain().forward_kinematics(model.base(), &q).unwrap();
            for (link, frame) in frames.iter().enumerate() {
                let offset = Vector3::new(
                    rng.uniform(-0.5, 0.5),
                    rng.uniform(-0.5, 0.5),
                    rng.uniform(-0.5, 0.5),
                );
                let p = frame.rotation * offset + frame.translation;
                let point = [p.x, p.y, p.z];
                let numeric = numeric_jacobian(&model, &q, link, point);
                let analytic = model.point_jacobian(&q, link, point).unwrap();
                let origin = frame.translation;
                let at_origin = numeric_jacobian(&model, &q, link, [origin.x, origin.y, origin.z]);
                let frame = model.frame_jacobian(&q, link).unwrap();
                for c in 0..model.dof() {
                    for r in 0..3 {
                        assert!(
                            (analytic[c][r] - numeric[c][r]).abs() < 1e-8,
                            "link {link} column {c}"
                        );
                    }
                    for r in 0..6 {
                        assert!(
                            (frame[c][r] - at_origin[c][r]).abs() < 1e-8,
                            "link {link} column {c} row {r}"
                        );
                    }
                }
            }
        }
        // Joints off the way to a link give zero columns: e's joint for d, and the
        // chain's joints for e.
        let q = [0.3, 0.2, -0.7, 1.1];
        let jd = model.frame_jacobian(&q, 4).unwrap();
        assert_eq!(jd[3], [0.0; 6]);
        let je = model.frame_jacobian(&q, 5).unwrap();
        assert!(je[..3].iter().all(|c| *c == [0.0; 6]));
        assert_eq!(model.frame_jacobian(&q, 0).unwrap(), vec![[0.0; 6]; 4]);
    }

    /// A planar arm with unit links, written out: p = (cos a + cos(a+b), sin a + sin(a+b)).
    #[test]
    fn planar_two_link_jacobian_by_hand() {
        let joint = |name: &str, parent, child, x: f64| Joint {
            name: name.into(),
            kind: JointKind::Revolute,
            parent,
            child,
            origin: Frame::from_xyz_rpy([x, 0.0, 0.0], [0.0; 3]),
            axis: Vector3::z(),
            lower: -3.0,
            upper: 3.0,
        };
        let names = ["base", "upper", "fore", "tip"].map(String::from).to_vec();
        let mut tip = joint("tip", 2, 3, 1.0);
        tip.kind = JointKind::Fixed;
        let chain = Chain::new(
            names,
            vec![joint("a", 0, 1, 0.0), joint("b", 1, 2, 1.0), tip],
        )
        .unwrap();
        let model = RobotModel::new(chain, vec![None; 4]).unwrap();
        let (a, b) = (0.4f64, -1.2f64);
        let j = model.frame_jacobian(&[a, b], 3).unwrap();
        let want_a = [
            -a.sin() - (a + b).sin(),
            a.cos() + (a + b).cos(),
            0.0,
            0.0,
            0.0,
            1.0,
        ];
        let want_b = [-(a + b).sin(), (a + b).cos(), 0.0, 0.0, 0.0, 1.0];
        for r in 0..6 {
            assert!(
                (j[0][r] - want_a[r]).abs() < 1e-15 && (j[1][r] - want_b[r]).abs() < 1e-15,
                "{j:?}"
            );
        }
        let p = model.point_jacobian(&[a, b], 2, [0.0, 0.0, 5.0]).unwrap();
        // The world point (0, 0, 5) carried by the forearm: joint b (axis z through
        // (cos a, sin a, 0)) moves it at z × (p − o) = (sin a, −cos a, 0); joint a's
        // axis passes through it.
        let o_b = [a.cos(), a.sin()];
        assert!((p[1][0] - o_b[1]).abs() < 1e-15 && (p[1][1] + o_b[0]).abs() < 1e-15);
        assert!(p[0][0].abs() < 1e-15 && p[0][1].abs() < 1e-15);
        // Bad input: errors, not panics.
        assert!(model.point_jacobian(&[a, b], 4, [0.0; 3]).is_err());
        assert!(model.point_jacobian(&[a, b, 0.0], 1, [0.0; 3]).is_err());
        assert!(model.point_jacobian(&[a, 3.5], 1, [0.0; 3]).is_err());
        assert!(model
            .point_jacobian(&[a, b], 1, [f64::NAN, 0.0, 0.0])
            .is_err());
        assert!(model.frame_jacobian(&[a, b], 9).is_err());
    }
}
