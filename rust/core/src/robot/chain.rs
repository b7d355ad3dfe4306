//! Kinematic chain: links joined by revolute, prismatic and fixed joints (a tree, as
//! in URDF), forward kinematics for one or many configurations.

use crate::error::{Error, Result};
use crate::na::{Matrix3, Matrix4, Rotation3, Vector3};

/// A rigid transform kept as rotation matrix + translation (cheaper to compose and to
/// apply to points than a quaternion, and what the 4×4 outputs need anyway).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frame {
    /// Rotation part.
    pub rotation: Matrix3<f64>,
    /// Translation part, in metres.
    pub translation: Vector3<f64>,
}

impl Frame {
    /// The identity transform.
    pub fn identity() -> Self {
        Frame {
            rotation: Matrix3::identity(),
            translation: Vector3::zeros(),
        }
    }

    /// URDF `<origin xyz rpy>`: R = Rz(yaw) · Ry(pitch) · Rx(roll).
    pub fn from_xyz_rpy(xyz: [f64; 3], rpy: [f64; 3]) -> Self {
        Frame {
            rotation: *Rotation3::from_euler_angles(rpy[0], rpy[1], rpy[2]).matrix(),
            translation: Vector3::from(xyz),
        }
    }

    /// From a homogeneous matrix (the caller checks that it is rigid).
    pub fn from_matrix(m: &Matrix4<f64>) -> Self {
        Frame {
            rotation: m.fixed_view::<3, 3>(0, 0).into_owned(),
            translation: m.fixed_view::<3, 1>(0, 3).into_owned(),
        }
    }

    /// The same transform as a homogeneous 4×4 matrix.
    pub fn to_matrix(&self) -> Matrix4<f64> {
        let mut m = Matrix4::identity();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&self.rotation);
        m.fixed_view_mut::<3, 1>(0, 3).copy_from(&self.translation);
        m
    }

    /// `self ∘ other` (apply `other` first).
    #[inline]
    pub fn compose(&self, other: &Frame) -> Frame {
        Frame {
            rotation: self.rotation * other.rotation,
            translation: self.rotation * other.translation + self.translation,
        }
    }

    /// Transform a point.
    #[inline]
    pub fn apply(&self, p: &[f64; 3]) -> [f64; 3] {
        let v = self.rotation * Vector3::from(*p) + self.translation;
        [v.x, v.y, v.z]
    }
}

/// Largest length (m) a robot's geometry may hold: joint offsets, prismatic travel and
/// body coordinates. Far beyond any arm (so only unit mistakes and garbage meet it), and
/// it keeps the sums and squares of reach and sampling arithmetic far from overflow.
pub const MAX_ROBOT_LENGTH: f64 = 1e4;

/// How a joint moves.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JointKind {
    /// Rotation about the axis, within limits.
    Revolute,
    /// Rotation about the axis without limits.
    Continuous,
    /// Translation along the axis, within limits.
    Prismatic,
    /// No motion: the child is rigidly attached to the parent.
    Fixed,
}

/// A movable joint's axis placed in the world for one configuration (see
/// [`Chain::jacobian_axes`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JointAxis {
    /// Revolute, continuous or prismatic.
    pub kind: JointKind,
    /// Unit axis in the world frame.
    pub direction: Vector3<f64>,
    /// A point on the axis: the origin of the joint's child link.
    pub origin: Vector3<f64>,
}

/// A joint between a parent and a child link, as URDF describes it.
#[derive(Clone, Debug)]
pub struct Joint {
    /// The joint's name (URDF).
    pub name: String,
    /// How it moves.
    pub kind: JointKind,
    /// Index of the parent link.
    pub parent: usize,
    /// Index of the child link.
    pub child: usize,
    /// parent_from_joint at zero motion.
    pub origin: Frame,
    /// Unit axis in the joint frame (unused for fixed joints).
    pub axis: Vector3<f64>,
    /// Position limits (rad or m); ±∞ for continuous joints.
    pub lower: f64,
    /// Upper position limit (rad or m); +∞ for continuous joints.
    pub upper: f64,
}

impl Joint {
    /// Whether the joint moves (is not fixed), i.e. takes a configuration coordinate.
    pub fn is_movable(&self) -> bool {
        self.kind != JointKind::Fixed
    }
}

/// Links and joints of a robot; link 0 is the root, every joint's parent comes before
/// its child, and the movable joints in order are the configuration's coordinates.
#[derive(Clone, Debug)]
pub struct Chain {
    link_names: Vec<String>,
    joints: Vec<Joint>,
    /// For each movable joint (in configuration order), its index in `joints`.
    movable: Vec<usize>,
    /// For each joint, its coordinate in q (None for fixed joints).
    coordinate: Vec<Option<usize>>,
    /// For each joint, parent_from_child as a function of q, precomputed.
    local: Vec<LocalTransform>,
}

/// parent_from_child of a joint with the origin folded in, so forward kinematics
/// costs one frame product per joint instead of two. A revolute joint's
/// origin · R(axis, q) is cos q · C + sin q · S + K (Rodrigues' formula multiplied out).
#[derive(Clone, Debug)]
enum LocalTransform {
    Fixed(Frame),
    Revolute {
        cos: Matrix3<f64>,
        sin: Matrix3<f64>,
        constant: Matrix3<f64>,
        translation: Vector3<f64>,
    },
    Prismatic {
        origin: Frame,
        /// origin.rotation · axis: the child's displacement per unit q.
        step: Vector3<f64>,
    },
}

impl LocalTransform {
    fn of(joint: &Joint) -> Self {
        let o = &joint.origin;
        match joint.kind {
            JointKind::Fixed => LocalTransform::Fixed(*o),
            JointKind::Prismatic => LocalTransform::Prismatic {
                origin: *o,
                step: o.rotation * joint.axis,
            },
            JointKind::Revolute | JointKind::Continuous => {
                let a = joint.axis;
                let outer = a * a.transpose();
                LocalTransform::Revolute {
                    cos: o.rotation * (Matrix3::identity() - outer),
                    sin: o.rotation * a.cross_matrix(),
                    constant: o.rotation * outer,
                    translation: o.translation,
                }
            }
        }
    }

    #[inline]
    fn at(&self, q: f64) -> Frame {
        match self {
            LocalTransform::Fixed(f) => *f,
            LocalTransform::Prismatic { origin, step } => Frame {
                rotation: origin.rotation,
                translation: origin.translation + step * q,
            },
            LocalTransform::Revolute {
                cos,
                sin,
                constant,
                translation,
            } => {
                let (s, c) = q.sin_cos();
                Frame {
                    rotation: cos * c + sin * s + constant,
                    translation: *translation,
                }
            }
        }
    }
}

impl Chain {
    /// Build from links and joints; joints may come in any order (they are sorted
    /// parent-first, keeping the given order among movable joints where the tree allows).
    pub fn new(link_names: Vec<String>, joints: Vec<Joint>) -> Result<Self> {
        let n = link_names.len();
        if n == 0 {
            return Err(Error::InvalidArgument(
                "a robot needs at least one link".into(),
            ));
        }
        if joints.len() + 1 != n {
            return Err(Error::InvalidArgument(format!(
                "a tree of {n} links needs {} joints, got {}",
                n - 1,
                joints.len()
            )));
        }
        let mut parent_joint: Vec<Option<usize>> = vec![None; n];
        for (j, joint) in joints.iter().enumerate() {
            if joint.parent >= n || joint.child >= n {
                return Err(Error::InvalidArgument(format!(
                    "joint '{}' names a link index out of range",
                    joint.name
                )));
            }
            if joint.child == 0 {
                return Err(Error::InvalidArgument(format!(
                    "joint '{}' has the root link as its child",
                    joint.name
                )));
            }
            if parent_joint[joint.child].replace(j).is_some() {
                return Err(Error::InvalidArgument(format!(
                    "link '{}' is the child of two joints",
                    link_names[joint.child]
                )));
            }
            let origin = &joint.origin;
            if !(origin.rotation.iter().all(|v| v.is_finite())
                && origin.translation.iter().all(|v| v.is_finite()))
            {
                return Err(Error::InvalidArgument(format!(
                    "joint '{}' has a non-finite origin (xyz or rpy)",
                    joint.name
                )));
            }
            if origin
                .translation
                .iter()
                .any(|v| v.abs() > MAX_ROBOT_LENGTH)
            {
                return Err(Error::InvalidArgument(format!(
                    "joint '{}' has an origin xyz {:?} beyond {MAX_ROBOT_LENGTH} m",
                    joint.name,
                    [
                        origin.translation.x,
                        origin.translation.y,
                        origin.translation.z
                    ]
                )));
            }
            let norm = joint.axis.norm();
            if joint.is_movable() && !(norm.is_finite() && norm > 1e-12) {
                return Err(Error::InvalidArgument(format!(
                    "joint '{}' has a zero or non-finite axis",
                    joint.name
                )));
            }
            if joint.kind != JointKind::Continuous
                && joint.is_movable()
                && !(joint.lower <= joint.upper
                    && joint.lower.is_finite()
                    && joint.upper.is_finite())
            {
                return Err(Error::InvalidArgument(format!(
                    "joint '{}' has invalid limits [{}, {}]",
                    joint.name, joint.lower, joint.upper
                )));
            }
            if joint.kind == JointKind::Prismatic
                && joint.lower.abs().max(joint.upper.abs()) > MAX_ROBOT_LENGTH
            {
                return Err(Error::InvalidArgument(format!(
                    "prismatic joint '{}' has limits [{}, {}] beyond {MAX_ROBOT_LENGTH} m",
                    joint.name, joint.lower, joint.upper
                )));
            }
        }
        // Parent-first order: repeatedly emit joints whose parent link is placed.
        let mut placed = vec![false; n];
        placed[0] = true;
        let mut order = Vec::with_capacity(joints.len());
        let mut remaining: Vec<usize> = (0..joints.len()).collect();
        while !remaining.is_empty() {
            let before = remaining.len();
            remaining.retain(|&j| {
                if placed[joints[j].parent] {
                    placed[joints[j].child] = true;
                    order.push(j);
                    false
                } else {
                    true
                }
            });
            if remaining.len() == before {
                return Err(Error::InvalidArgument(
                    "the joints do not form a tree rooted at link 0 (a cycle or a detached link)"
                        .into(),
                ));
            }
        }
        let mut sorted: Vec<Joint> = order.iter().map(|&j| joints[j].clone()).collect();
        for joint in &mut sorted {
            if joint.is_movable() {
                joint.axis = joint.axis.normalize();
            }
            if joint.kind == JointKind::Continuous {
                joint.lower = f64::NEG_INFINITY;
                joint.upper = f64::INFINITY;
            }
        }
        // Configuration order: movable joints in the order they were given.
        let mut movable_given: Vec<usize> = Vec::new();
        for (given, joint) in joints.iter().enumerate() {
            if joint.is_movable() {
                movable_given.push(given);
            }
        }
        let position_in_sorted = |given: usize| order.iter().position(|&o| o == given);
        let movable: Vec<usize> = movable_given
            .iter()
            .filter_map(|&g| position_in_sorted(g))
            .collect();
        let mut coordinate = vec![None; sorted.len()];
        for (c, &j) in movable.iter().enumerate() {
            coordinate[j] = Some(c);
        }
        let local = sorted.iter().map(LocalTransform::of).collect();
        Ok(Chain {
            link_names,
            joints: sorted,
            movable,
            coordinate,
            local,
        })
    }

    /// Degrees of freedom: the number of movable joints.
    pub fn dof(&self) -> usize {
        self.movable.len()
    }

    /// Number of links.
    pub fn num_links(&self) -> usize {
        self.link_names.len()
    }

    /// Link names, by link index.
    pub fn link_names(&self) -> &[String] {
        &self.link_names
    }

    /// Joints parent-first.
    pub fn joints(&self) -> &[Joint] {
        &self.joints
    }

    /// The movable joints in configuration order.
    pub fn movable_joints(&self) -> impl Iterator<Item = &Joint> {
        self.movable.iter().map(|&j| &self.joints[j])
    }

    /// (lower, upper) per coordinate.
    pub fn limits(&self) -> Vec<(f64, f64)> {
        self.movable_joints().map(|j| (j.lower, j.upper)).collect()
    }

    /// Parent link of each link (None for the root).
    pub fn parents(&self) -> Vec<Option<usize>> {
        let mut parents = vec![None; self.num_links()];
        for j in &self.joints {
            parents[j.child] = Some(j.parent);
        }
        parents
    }

    /// Check a configuration: right length, finite, within limits (1e-9 slack).
    pub fn check_configuration(&self, q: &[f64], index: usize) -> Result<()> {
        if q.len() != self.dof() {
            return Err(Error::InvalidArgument(format!(
                "configuration {index} has {} values, the robot has {} joints",
                q.len(),
                self.dof()
            )));
        }
        for (c, joint) in self.movable_joints().enumerate() {
            let v = q[c];
            if !v.is_finite() {
                return Err(Error::InvalidArgument(format!(
                    "configuration {index}: joint '{}' is {v}",
                    joint.name
                )));
            }
            if v < joint.lower - 1e-9 || v > joint.upper + 1e-9 {
                return Err(Error::InvalidArgument(format!(
                    "configuration {index}: joint '{}' = {v} is outside its limits [{}, {}]",
                    joint.name, joint.lower, joint.upper
                )));
            }
        }
        Ok(())
    }

    /// world_from_link for every link, given world_from_root (`base`); `out` has one
    /// frame per link. `q` must have been checked.
    #[inline]
    pub fn forward_kinematics_into(&self, base: &Frame, q: &[f64], out: &mut [Frame]) {
        out[0] = *base;
        for j in 0..self.joints.len() {
            self.place_child(j, q, out);
        }
    }

    /// `forward_kinematics_into` for the child links of `joints` only (indices into
    /// `joints()`, parent-first, e.g. from `joints_reaching`); other frames are left as
    /// they were.
    #[inline]
    pub fn forward_kinematics_of(
        &self,
        base: &Frame,
        q: &[f64],
        out: &mut [Frame],
        joints: &[usize],
    ) {
        out[0] = *base;
        for &j in joints {
            self.place_child(j, q, out);
        }
    }

    /// Set the frame of joint `j`'s child from its parent's (already set).
    #[inline]
    pub fn place_child(&self, j: usize, q: &[f64], out: &mut [Frame]) {
        let joint = &self.joints[j];
        let local = self.local[j].at(self.coordinate[j].map_or(0.0, |c| q[c]));
        out[joint.child] = out[joint.parent].compose(&local);
    }

    /// The joints (indices into `joints()`, parent-first) on the way from the root to
    /// any link marked in `wanted`: all forward kinematics needs to place those links.
    pub fn joints_reaching(&self, wanted: &[bool]) -> Vec<usize> {
        let mut needed = wanted.to_vec();
        // Children come after parents, so a backward pass marks every ancestor.
        for joint in self.joints.iter().rev() {
            if needed[joint.child] {
                needed[joint.parent] = true;
            }
        }
        (0..self.joints.len())
            .filter(|&j| needed[self.joints[j].child])
            .collect()
    }

    /// Every link's world frame for configuration `q` (one value per movable joint, rad
    /// or m) with the root at `base`. Errors when `q` has the wrong length or a value
    /// that is not finite.
    pub fn forward_kinematics(&self, base: &Frame, q: &[f64]) -> Result<Vec<Frame>> {
        self.check_configuration(q, 0)?;
        let mut out = vec![Frame::identity(); self.num_links()];
        self.forward_kinematics_into(base, q, &mut out);
        Ok(out)
    }

    /// Geometric Jacobian of `link` for frames placed by forward kinematics (`frames`,
    /// one per link, world_from_link at some q): one column per coordinate, each the
    /// joint's world axis `z` and a point on it `o` (the joint's child frame origin),
    /// for the movable joints on the way from the root to `link`; `None` for joints
    /// elsewhere (their columns are zero). A point `p` fixed to `link` moves at
    /// `z × (p − o)` per unit of a revolute coordinate and at `z` per unit of a
    /// prismatic one; the link turns at `z` per unit of a revolute coordinate.
    pub fn jacobian_axes(&self, frames: &[Frame], link: usize) -> Vec<Option<JointAxis>> {
        let mut axes = vec![None; self.dof()];
        let mut parent_joint = vec![None; self.num_links()];
        for (j, joint) in self.joints.iter().enumerate() {
            parent_joint[joint.child] = Some(j);
        }
        let mut at = link;
        while let Some(j) = parent_joint[at] {
            let joint = &self.joints[j];
            if let Some(c) = self.coordinate[j] {
                let child = &frames[joint.child];
                axes[c] = Some(JointAxis {
                    kind: joint.kind,
                    direction: child.rotation * joint.axis,
                    origin: child.translation,
                });
            }
            at = joint.parent;
        }
        axes
    }

    /// An upper bound on how far any point fixed in link `l` within `extent[l]` of its
    /// origin can get from the root's origin (for sizing the collision index).
    pub fn reach_bound(&self, extent: &[f64]) -> f64 {
        let mut reach = vec![0.0f64; self.num_links()];
        for joint in &self.joints {
            let travel = match joint.kind {
                JointKind::Prismatic => joint.lower.abs().max(joint.upper.abs()),
                _ => 0.0,
            };
            reach[joint.child] = reach[joint.parent] + joint.origin.translation.norm() + travel;
        }
        reach
            .iter()
            .zip(extent)
            .map(|(r, e)| r + e)
            .fold(0.0, f64::max)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn two_link() -> Chain {
        let joint = |name: &str, parent, child, xyz: [f64; 3], axis: [f64; 3]| Joint {
            name: name.into(),
            kind: JointKind::Revolute,
            parent,
            child,
            origin: Frame::from_xyz_rpy(xyz, [0.0; 3]),
            axis: Vector3::from(axis),
            lower: -3.0,
            upper: 3.0,
        };
        Chain::new(
            vec!["base".into(), "a".into(), "b".into()],
            vec![
                joint("j1", 0, 1, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]),
                joint("j2", 1, 2, [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]),
            ],
        )
        .unwrap()
    }

    #[test]
    fn partial_kinematics_places_what_the_wanted_links_need() {
        // base → a → b, and a branch base → c (fixed).
        let mut joints = vec![
            Joint {
                name: "j1".into(),
                kind: JointKind::Revolute,
                parent: 0,
                child: 1,
                origin: Frame::from_xyz_rpy([0.0, 0.0, 0.5], [0.0; 3]),
                axis: Vector3::z(),
                lower: -3.0,
                upper: 3.0,
            },
            Joint {
                name: "j2".into(),
                kind: JointKind::Revolute,
                parent: 1,
                child: 2,
                origin: Frame::from_xyz_rpy([1.0, 0.0, 0.0], [0.2, 0.0, 0.0]),
                axis: Vector3::y(),
                lower: -3.0,
                upper: 3.0,
            },
        ];
        joints.push(Joint {
            name: "c".into(),
            kind: JointKind::Fixed,
            parent: 0,
            child: 3,
            origin: Frame::from_xyz_rpy([0.0, 1.0, 0.0], [0.0; 3]),
            axis: Vector3::z(),
            lower: 0.0,
            upper: 0.0,
        });
        let names = ["base", "a", "b", "c"].map(String::from).to_vec();
        let chain = Chain::new(names, joints).unwrap();
        let wanted = chain.joints_reaching(&[false, false, true, false]);
        let children: Vec<usize> = wanted.iter().map(|&j| chain.joints()[j].child).collect();
        assert_eq!(children, vec![1, 2]);
        let q = [0.4, -0.7];
        let full = chain.forward_kinematics(&Frame::identity(), &q).unwrap();
        let mut part = vec![Frame::identity(); 4];
        chain.forward_kinematics_of(&Frame::identity(), &q, &mut part, &wanted);
        assert_eq!(part[2], full[2]);
        assert_eq!(part[3], Frame::identity());
    }

    #[test]
    fn planar_two_link_matches_trigonometry() {
        let chain = two_link();
        let (a, b) = (0.3f64, -1.1f64);
        let frames = chain
            .forward_kinematics(&Frame::identity(), &[a, b])
            .unwrap();
        let p = frames[2].translation;
        assert!((p.x - a.cos()).abs() < 1e-15 && (p.y - a.sin()).abs() < 1e-15);
        let yaw = frames[2].rotation[(1, 0)].atan2(frames[2].rotation[(0, 0)]);
        assert!((yaw - (a + b)).abs() < 1e-15);
    }

    #[test]
    fn rejects_bad_configurations() {
        let chain = two_link();
        assert!(chain.check_configuration(&[0.0], 0).is_err());
        assert!(chain.check_configuration(&[f64::NAN, 0.0], 0).is_err());
        let err = chain
            .check_configuration(&[0.0, 3.5], 4)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("j2") && err.contains("outside its limits"),
            "{err}"
        );
    }

    #[test]
    fn rejects_cycles_and_orphans() {
        let mut j = two_link().joints().to_vec();
        j[1].child = 1;
        assert!(Chain::new(vec!["base".into(), "a".into(), "b".into()], j).is_err());
    }

    #[test]
    fn urdf_rpy_convention() {
        // Rz(yaw)·Ry(pitch)·Rx(roll) applied to x̂ with only yaw = π/2 gives ŷ.
        let f = Frame::from_xyz_rpy([0.0; 3], [0.0, 0.0, std::f64::consts::FRAC_PI_2]);
        let v = f.apply(&[1.0, 0.0, 0.0]);
        assert!((v[1] - 1.0).abs() < 1e-15);
        // All three angles at once, against the product of the three rotations written
        // out by hand (any other order of the factors differs).
        let (r, p, y) = (0.3f64, -0.5f64, 0.8f64);
        let rx = [
            [1.0, 0.0, 0.0],
            [0.0, r.cos(), -r.sin()],
            [0.0, r.sin(), r.cos()],
        ];
        let ry = [
            [p.cos(), 0.0, p.sin()],
            [0.0, 1.0, 0.0],
            [-p.sin(), 0.0, p.cos()],
        ];
        let rz = [
            [y.cos(), -y.sin(), 0.0],
            [y.sin(), y.cos(), 0.0],
            [0.0, 0.0, 1.0],
        ];
        let mul = |a: [[f64; 3]; 3], b: [[f64; 3]; 3]| {
            let mut m = [[0.0; 3]; 3];
            for i in 0..3 {
                for j in 0..3 {
                    m[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum();
                }
            }
            m
        };
        let want = mul(rz, mul(ry, rx));
        let f = Frame::from_xyz_rpy([0.1, -0.2, 0.3], [r, p, y]);
        for (column, axis) in [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
            .iter()
            .enumerate()
        {
            let v = f.apply(axis);
            for row in 0..3 {
                let expected = want[row][column] + [0.1, -0.2, 0.3][row];
                assert!((v[row] - expected).abs() < 1e-14, "{v:?} column {column}");
            }
        }
    }
}
