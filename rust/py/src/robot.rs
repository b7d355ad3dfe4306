//! `earcore.RobotModel`: kinematics, padded link capsules, self-filter, collision,
//! clearance and motion danger. Python builds it from URDF (`earcore.robots`); this
//! file holds the chain and answers batched queries with the GIL released.
//!
//! Caches: the collision index of a map is rebuilt only when the map (its id and
//! write revision), the obstacle source, the base pose or the margin change; the
//! self-filter reuses the placed bodies while the configuration is unchanged. Both sit
//! behind mutexes, so the model can be shared across threads.

use std::sync::Arc;

use earcore_core::na::Vector3;
use earcore_core::robot::{
    self, Body, BodyShape, Chain, CheckParams, Clearance, Contact, FitShape, Frame, Joint,
    JointKind, PlacedBodies, RobotModel, VoxelIndex, VoxelSource,
};
use numpy::ndarray::{Array1, Array2, Array4};
use numpy::{IntoPyArray, PyArray1, PyArray2};
use parking_lot::{Mutex, RwLock};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::{configurations, points as point_rows, pose, rows_to_array, vec_to_array};
use crate::errors::IntoPyResult;
use crate::octree::PyOcTree;

/// A joint as Python hands it over: name, kind, parent link, child link, origin xyz,
/// origin rpy, axis, lower, upper.
type JointSpec = (
    String,
    String,
    usize,
    usize,
    [f64; 3],
    [f64; 3],
    [f64; 3],
    f64,
    f64,
);

/// A body as Python sees it: (a, b, radius, "capsule" | "cylinder") in the link frame.
type BodySpec = ([f64; 3], [f64; 3], f64, String);

fn body_spec(b: &Body) -> BodySpec {
    (
        b.axis.a,
        b.axis.b,
        b.axis.radius,
        shape_name(b.shape).to_string(),
    )
}

fn shape_name(shape: BodyShape) -> &'static str {
    match shape {
        BodyShape::Capsule => "capsule",
        BodyShape::Cylinder => "cylinder",
    }
}

fn body_from_spec((a, b, r, shape): BodySpec) -> PyResult<Body> {
    match shape.as_str() {
        "capsule" => Ok(Body::capsule(a, b, r)),
        "cylinder" => Ok(Body::cylinder(a, b, r)),
        other => Err(PyValueError::new_err(format!(
            "body shape must be 'capsule' or 'cylinder', got '{other}'"
        ))),
    }
}

/// Collision indices kept per robot model.
const INDEX_CACHE_SIZE: usize = 4;

struct CachedIndex {
    key: (u64, u64, VoxelSource, [u64; 3], u64),
    index: Arc<VoxelIndex>,
}

/// A robot arm's kinematics and padded link capsules (build it with
/// `earcore.robots.load(name)` or `RobotModel.from_urdf(path)`).
#[pyclass(name = "RobotModel", module = "earcore", subclass, frozen)]
pub struct PyRobotModel {
    model: RwLock<RobotModel>,
    name: String,
    padding: f64,
    margin: Mutex<f64>,
    /// The last few collision indices, most recent first (a planner often alternates
    /// between maps, e.g. the live map and a static one).
    index_cache: Mutex<Vec<CachedIndex>>,
    filter_cache: Mutex<Option<(Vec<f64>, f64, PlacedBodies)>>,
}

fn joint_kind(kind: &str, name: &str) -> PyResult<JointKind> {
    Ok(match kind {
        "revolute" => JointKind::Revolute,
        "continuous" => JointKind::Continuous,
        "prismatic" => JointKind::Prismatic,
        "fixed" => JointKind::Fixed,
        other => {
            return Err(PyValueError::new_err(format!(
                "joint '{name}' has unsupported type '{other}' (revolute, continuous, prismatic and fixed are)"
            )))
        }
    })
}

fn obstacle_source(obstacles: &str) -> PyResult<VoxelSource> {
    match obstacles {
        "occupied" => Ok(VoxelSource::Occupied),
        "current" => Ok(VoxelSource::CurrentObstacles),
        other => Err(PyValueError::new_err(format!(
            "obstacles must be 'occupied' (every occupied voxel) or 'current' (obstacles seen in the last frame), got '{other}'"
        ))),
    }
}

/// The two ends of one motion, each a single (dof,) configuration.
fn motion_ends(
    q0: &Bound<'_, PyAny>,
    q1: &Bound<'_, PyAny>,
    dof: usize,
    what: &str,
) -> PyResult<(Vec<f64>, Vec<f64>)> {
    let (a, _, s0) = configurations(q0, dof, "q0")?;
    let (b, _, s1) = configurations(q1, dof, "q1")?;
    if !(s0 && s1) {
        return Err(PyValueError::new_err(format!(
            "{what} takes two configurations of shape ({dof},)"
        )));
    }
    Ok((a, b))
}

fn contact_link(c: &Contact) -> i32 {
    c.link().map_or(-1, |l| l as i32)
}

/// The dict `clearance` returns: distance, link, on_robot, on_obstacle (scalars and
/// 3-vectors for one configuration, arrays for a batch).
fn clearance_dict<'py>(
    py: Python<'py>,
    found: &[Option<(usize, Clearance)>],
    single: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let nan = [f64::NAN; 3];
    let distance: Vec<f64> = found
        .iter()
        .map(|f| f.map_or(f64::INFINITY, |(_, c)| c.distance))
        .collect();
    let link: Vec<i64> = found
        .iter()
        .map(|f| f.map_or(-1, |(l, _)| l as i64))
        .collect();
    let on_robot: Vec<[f64; 3]> = found
        .iter()
        .map(|f| f.map_or(nan, |(_, c)| c.on_body))
        .collect();
    let on_obstacle: Vec<[f64; 3]> = found
        .iter()
        .map(|f| f.map_or(nan, |(_, c)| c.on_obstacle))
        .collect();
    let d = PyDict::new(py);
    if single {
        d.set_item("distance", distance[0])?;
        d.set_item("link", link[0])?;
        d.set_item(
            "on_robot",
            Array1::from(on_robot[0].to_vec()).into_pyarray(py),
        )?;
        d.set_item(
            "on_obstacle",
            Array1::from(on_obstacle[0].to_vec()).into_pyarray(py),
        )?;
    } else {
        d.set_item("distance", vec_to_array(py, distance))?;
        d.set_item("link", vec_to_array(py, link))?;
        d.set_item("on_robot", rows_to_array(py, on_robot)?)?;
        d.set_item("on_obstacle", rows_to_array(py, on_obstacle)?)?;
    }
    Ok(d)
}

impl PyRobotModel {
    fn read(&self) -> parking_lot::RwLockReadGuard<'_, RobotModel> {
        self.model.read()
    }

    /// The collision index of `tree` for `source`, built or taken from the cache.
    fn index(
        &self,
        py: Python<'_>,
        tree: &PyOcTree,
        source: VoxelSource,
    ) -> PyResult<Arc<VoxelIndex>> {
        let (uid, revision) = tree.version();
        let model = self.read();
        let centre = model.base().translation;
        let margin = *self.margin.lock();
        let half = model.reach_bound() + margin;
        drop(model);
        let key = (
            uid,
            revision,
            source,
            [centre.x.to_bits(), centre.y.to_bits(), centre.z.to_bits()],
            margin.to_bits(),
        );
        {
            let mut cache = self.index_cache.lock();
            if let Some(i) = cache.iter().position(|c| c.key == key) {
                let hit = cache.remove(i);
                let index = hit.index.clone();
                cache.insert(0, hit);
                return Ok(index);
            }
        }
        let index = py
            .detach(|| {
                let t = tree.read_detached();
                robot::robot_within_map(&self.read(), &t)?;
                VoxelIndex::from_tree(&t, source, [centre.x, centre.y, centre.z], half)
            })
            .py()?;
        let index = Arc::new(index);
        let mut cache = self.index_cache.lock();
        // One entry per (map, source, base, margin): a newer revision replaces its own.
        cache.retain(|c| (c.key.0, c.key.2, c.key.3, c.key.4) != (key.0, key.2, key.3, key.4));
        cache.insert(
            0,
            CachedIndex {
                key,
                index: index.clone(),
            },
        );
        cache.truncate(INDEX_CACHE_SIZE);
        Ok(index)
    }

    /// One configuration (dof,) for `what`.
    fn one_configuration(&self, q: &Bound<'_, PyAny>, what: &str) -> PyResult<Vec<f64>> {
        let (q, _, single) = configurations(q, self.read().dof(), "q")?;
        if !single {
            return Err(PyValueError::new_err(format!(
                "{what} takes one configuration (dof,)"
            )));
        }
        Ok(q)
    }

    /// A link index, checked against the robot's links.
    fn link_index(&self, link: i64) -> PyResult<usize> {
        let n = self.read().chain().num_links();
        usize::try_from(link)
            .ok()
            .filter(|&l| l < n)
            .ok_or_else(|| {
                PyValueError::new_err(format!(
                    "link must be 0 to {} (the robot's links), got {link}",
                    n - 1
                ))
            })
    }

    fn check_q(&self, q: &[f64], k: usize) -> PyResult<()> {
        let model = self.read();
        let dof = model.dof();
        for (i, row) in q.chunks(dof.max(1)).enumerate().take(k) {
            model.chain().check_configuration(row, i).py()?;
        }
        Ok(())
    }
}

#[pymethods]
impl PyRobotModel {
    /// Build from parts (what `RobotModel.from_urdf` does after parsing): link names
    /// (link 0 is the root), joints as (name, kind, parent, child, xyz, rpy, axis,
    /// lower, upper) and one body per link, None or (a, b, radius, shape) in the link
    /// frame with shape "capsule" or "cylinder".
    #[new]
    #[pyo3(signature = (link_names, joints, bodies, *, name = None, padding = 0.0))]
    fn new(
        link_names: Vec<String>,
        joints: Vec<JointSpec>,
        bodies: Vec<Option<BodySpec>>,
        name: Option<String>,
        padding: f64,
    ) -> PyResult<Self> {
        if !(padding.is_finite() && padding >= 0.0) {
            return Err(pyo3::exceptions::PyValueError::new_err(format!(
                "padding must be a finite length >= 0, got {padding}"
            )));
        }
        let joints = joints
            .into_iter()
            .map(
                |(jname, kind, parent, child, xyz, rpy, axis, lower, upper)| {
                    let kind = joint_kind(&kind, &jname)?;
                    Ok(Joint {
                        name: jname,
                        kind,
                        parent,
                        child,
                        origin: Frame::from_xyz_rpy(xyz, rpy),
                        axis: Vector3::from(axis),
                        lower,
                        upper,
                    })
                },
            )
            .collect::<PyResult<Vec<_>>>()?;
        let chain = Chain::new(link_names, joints).py()?;
        let bodies = bodies
            .into_iter()
            .map(|b| b.map(body_from_spec).transpose())
            .collect::<PyResult<Vec<_>>>()?;
        let model = RobotModel::new(chain, bodies).py()?;
        Ok(PyRobotModel {
            model: RwLock::new(model),
            name: name.unwrap_or_else(|| "robot".to_string()),
            padding,
            margin: Mutex::new(0.5),
            index_cache: Mutex::new(Vec::new()),
            filter_cache: Mutex::new(None),
        })
    }

    #[getter]
    fn name(&self) -> String {
        self.name.clone()
    }

    /// Padding (m) the link bodies were grown by.
    #[getter]
    fn padding(&self) -> f64 {
        self.padding
    }

    /// Number of movable joints (the length of a configuration).
    #[getter]
    fn dof(&self) -> usize {
        self.read().dof()
    }

    #[getter]
    fn link_names(&self) -> Vec<String> {
        self.read().chain().link_names().to_vec()
    }

    /// Names of the movable joints, in configuration order.
    #[getter]
    fn joint_names(&self) -> Vec<String> {
        self.read()
            .chain()
            .movable_joints()
            .map(|j| j.name.clone())
            .collect()
    }

    /// (dof, 2) lower and upper limits (±inf for continuous joints).
    #[getter]
    fn joint_limits<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let limits = self.read().chain().limits();
        let flat: Vec<f64> = limits.iter().flat_map(|&(a, b)| [a, b]).collect();
        let n = limits.len();
        Ok(Array2::from_shape_vec((n, 2), flat)
            .map_err(|e| PyValueError::new_err(e.to_string()))?
            .into_pyarray(py))
    }

    /// world_from_root, (4, 4). Setting it moves the whole robot.
    #[getter]
    fn base<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        let m = self.read().base().to_matrix();
        Array2::from_shape_fn((4, 4), |(r, c)| m[(r, c)]).into_pyarray(py)
    }

    #[setter]
    fn set_base(&self, value: &Bound<'_, PyAny>) -> PyResult<()> {
        let m = pose(value, "base")?;
        earcore_core::geometry::check_rigid(&m, "base").py()?;
        self.model.write().set_base(Frame::from_matrix(&m));
        *self.filter_cache.lock() = None;
        Ok(())
    }

    /// How far (m) beyond the robot's reach the collision index looks for obstacles
    /// (clearance to anything farther is not seen). Default 0.5.
    #[getter]
    fn index_margin(&self) -> f64 {
        *self.margin.lock()
    }

    #[setter]
    fn set_index_margin(&self, value: f64) -> PyResult<()> {
        if !(value.is_finite() && value >= 0.0) {
            return Err(PyValueError::new_err(format!(
                "index_margin must be finite and ≥ 0, got {value}"
            )));
        }
        *self.margin.lock() = value;
        Ok(())
    }

    /// Radius (m) around the base that holds every body in every configuration.
    #[getter]
    fn reach_bound(&self) -> f64 {
        self.read().reach_bound()
    }

    /// Per link: rigidly attached to the root (never moves; skipped by obstacle
    /// checks and clearance, since what it touches is the robot's own stand).
    #[getter]
    fn fixed_to_root(&self) -> Vec<bool> {
        self.read().fixed_to_root().to_vec()
    }

    /// Link pairs tested for self-collision (indices into `link_names`).
    #[getter]
    fn self_collision_pairs(&self) -> Vec<(usize, usize)> {
        self.read().self_collision_pairs().to_vec()
    }

    #[setter]
    fn set_self_collision_pairs(&self, pairs: Vec<(usize, usize)>) -> PyResult<()> {
        self.model.write().set_self_collision_pairs(pairs).py()
    }

    /// Each link's body in its own frame: None or (a, b, radius, shape).
    #[getter]
    fn link_bodies(&self) -> Vec<Option<BodySpec>> {
        self.read()
            .bodies()
            .iter()
            .map(|b| b.as_ref().map(body_spec))
            .collect()
    }

    /// Forward kinematics: world_from_link for every link. q (dof,) → (L, 4, 4);
    /// (K, dof) → (K, L, 4, 4).
    fn fk<'py>(&self, py: Python<'py>, q: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyAny>> {
        let dof = self.dof();
        let (qs, k, single) = configurations(q, dof, "q")?;
        self.check_q(&qs, k)?;
        let model = self.read();
        let links = model.chain().num_links();
        let flat = py.detach(|| {
            let mut frames = vec![Frame::identity(); links];
            let mut out = Vec::with_capacity(k * links * 16);
            for row in qs.chunks(dof.max(1)).take(k) {
                model
                    .chain()
                    .forward_kinematics_into(model.base(), row, &mut frames);
                for f in &frames {
                    let m = f.to_matrix();
                    for r in 0..4 {
                        for c in 0..4 {
                            out.push(m[(r, c)]);
                        }
                    }
                }
            }
            out
        });
        let array = Array4::from_shape_vec((k, links, 4, 4), flat)
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        if single {
            Ok(array
                .index_axis_move(numpy::ndarray::Axis(0), 0)
                .into_pyarray(py)
                .into_any())
        } else {
            Ok(array.into_pyarray(py).into_any())
        }
    }

    /// (3, dof) Jacobian of a point rigidly attached to link `link` (an index into
    /// `link_names`), given by its world position `point` at configuration q (dof,):
    /// column i is the point's velocity in the world frame per unit velocity of joint
    /// i (revolute: z_i × (point − o_i); prismatic: z_i; zero for joints not between
    /// the root and `link`). Exact, with the base pose included; q must lie within the
    /// joint limits.
    fn jacobian<'py>(
        &self,
        py: Python<'py>,
        q: &Bound<'py, PyAny>,
        link: i64,
        point: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let q = self.one_configuration(q, "jacobian()")?;
        let link = self.link_index(link)?;
        let p = crate::convert::vector3(point, "point")?;
        let columns = self.read().point_jacobian(&q, link, p).py()?;
        Ok(crate::convert::columns_to_array(py, &columns))
    }

    /// (6, dof) geometric Jacobian of link `link`'s frame at configuration q (dof,):
    /// rows 0-2 the linear velocity of the link's origin, rows 3-5 the link's angular
    /// velocity, both in the world frame (Pinocchio's LOCAL_WORLD_ALIGNED), per unit
    /// velocity of each joint. Rows 0-2 equal `jacobian(q, link, origin of link)`.
    fn frame_jacobian<'py>(
        &self,
        py: Python<'py>,
        q: &Bound<'py, PyAny>,
        link: i64,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let q = self.one_configuration(q, "frame_jacobian()")?;
        let link = self.link_index(link)?;
        let columns = self.read().frame_jacobian(&q, link).py()?;
        Ok(crate::convert::columns_to_array(py, &columns))
    }

    /// The padded bodies placed for one configuration: a dict with `link` (B,), `a`
    /// and `b` (B, 3) axis end points, `radius` (B,) and `shape` (a list of "capsule"
    /// or "cylinder").
    fn bodies<'py>(&self, py: Python<'py>, q: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyDict>> {
        let (qs, _, single) = configurations(q, self.dof(), "q")?;
        if !single {
            return Err(PyValueError::new_err(
                "bodies() takes one configuration (dof,)",
            ));
        }
        let placed = self.read().place(&qs).py()?;
        let d = PyDict::new(py);
        d.set_item(
            "link",
            vec_to_array(py, placed.links.iter().map(|&l| l as i64).collect()),
        )?;
        d.set_item(
            "a",
            rows_to_array(py, placed.bodies.iter().map(|c| c.axis.a).collect())?,
        )?;
        d.set_item(
            "b",
            rows_to_array(py, placed.bodies.iter().map(|c| c.axis.b).collect())?,
        )?;
        d.set_item(
            "radius",
            vec_to_array(py, placed.bodies.iter().map(|c| c.axis.radius).collect()),
        )?;
        let shapes: Vec<&str> = placed.bodies.iter().map(|c| shape_name(c.shape)).collect();
        d.set_item("shape", shapes)?;
        Ok(d)
    }

    /// Boolean mask of the points to keep: False where a point lies inside a padded
    /// body at configuration q, the bodies grown by a further `margin` (m) for sensor
    /// noise. The placed bodies are reused while q and the margin are unchanged.
    #[pyo3(signature = (points, q, margin = 0.0))]
    fn self_filter<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
        q: &Bound<'py, PyAny>,
        margin: f64,
    ) -> PyResult<Bound<'py, PyArray1<bool>>> {
        if !(margin.is_finite() && margin >= 0.0) {
            return Err(PyValueError::new_err(format!(
                "margin must be finite and >= 0, got {margin}"
            )));
        }
        let pts = point_rows(points, "points")?;
        let pts = pts.as_slice()?;
        earcore_core::geometry::check_finite(pts, "point").py()?;
        let (qs, _, single) = configurations(q, self.dof(), "q")?;
        if !single {
            return Err(PyValueError::new_err(
                "self_filter() takes one configuration (dof,)",
            ));
        }
        let keep = py.detach(|| -> earcore_core::Result<Vec<bool>> {
            let mut cache = self.filter_cache.lock();
            let placed = match cache.as_ref() {
                Some((cached_q, cached_margin, placed))
                    if *cached_q == qs && *cached_margin == margin =>
                {
                    placed.clone()
                }
                _ => {
                    let mut placed = self.read().place(&qs)?;
                    for body in &mut placed.bodies {
                        *body = body.grown(margin);
                    }
                    *cache = Some((qs.clone(), margin, placed.clone()));
                    placed
                }
            };
            drop(cache);
            Ok(robot::self_filter(pts, &placed))
        });
        Ok(vec_to_array(py, keep.py()?))
    }

    /// True where a configuration collides with the map's obstacles (or itself).
    /// qs (dof,) → bool; (K, dof) → (K,) bool. With `return_links`, also the index of
    /// a colliding link (the first one found; -1 where free).
    ///
    /// Cost: the first check on a map revision builds its collision index, a dense cube
    /// of (2·(reach_bound + index_margin)/resolution + 3)³ cells of 13 bytes, kept for
    /// later calls (four per model). A UR5 at 5 cm: 78³ cells, 6 MB, milliseconds; at
    /// 1 cm: 379³ cells, 0.7 GB (2.4 GB at the peak of the distance transform) and
    /// about 5 s. More than 64 M cells is refused; a smaller `index_margin` or a coarser
    /// map shrinks it. `clearance`, `check_motion(s)` share the index.
    #[pyo3(signature = (tree, qs, *, obstacles = "occupied", self_collision = true, return_links = false))]
    fn check_configurations<'py>(
        &self,
        py: Python<'py>,
        tree: &PyOcTree,
        qs: &Bound<'py, PyAny>,
        obstacles: &str,
        self_collision: bool,
        return_links: bool,
    ) -> PyResult<Bound<'py, PyAny>> {
        let source = obstacle_source(obstacles)?;
        let (q, _, single) = configurations(qs, self.dof(), "qs")?;
        let index = self.index(py, tree, source)?;
        let params = CheckParams { self_collision };
        let contacts = py
            .detach(|| robot::check_configurations(&self.read(), &index, &q, params))
            .py()?;
        let hit: Vec<bool> = contacts.iter().map(|c| !c.is_free()).collect();
        let links: Vec<i32> = contacts.iter().map(contact_link).collect();
        let (hit_obj, link_obj) = if single {
            (
                hit[0].into_pyobject(py)?.to_owned().into_any(),
                links[0].into_pyobject(py)?.into_any(),
            )
        } else {
            (
                vec_to_array(py, hit).into_any(),
                vec_to_array(py, links).into_any(),
            )
        };
        if return_links {
            Ok((hit_obj, link_obj).into_pyobject(py)?.into_any())
        } else {
            Ok(hit_obj)
        }
    }

    /// True when the straight joint-space motion q0 → q1 collides anywhere, checked at
    /// configurations no more than `resolution` rad apart per joint.
    #[pyo3(signature = (tree, q0, q1, resolution = 0.02, *, obstacles = "occupied", self_collision = true))]
    #[allow(clippy::too_many_arguments)]
    fn check_motion(
        &self,
        py: Python<'_>,
        tree: &PyOcTree,
        q0: &Bound<'_, PyAny>,
        q1: &Bound<'_, PyAny>,
        resolution: f64,
        obstacles: &str,
        self_collision: bool,
    ) -> PyResult<bool> {
        let source = obstacle_source(obstacles)?;
        let dof = self.dof();
        let (a, b) = motion_ends(
            q0,
            q1,
            dof,
            "check_motion() (use check_motions for batches)",
        )?;
        let index = self.index(py, tree, source)?;
        let params = CheckParams { self_collision };
        let hit = py
            .detach(|| robot::check_motion(&self.read(), &index, &a, &b, resolution, params))
            .py()?;
        Ok(hit.is_some())
    }

    /// Batched `check_motion`: (K, dof) starts and ends → (K,) bool.
    #[pyo3(signature = (tree, q0s, q1s, resolution = 0.02, *, obstacles = "occupied", self_collision = true))]
    #[allow(clippy::too_many_arguments)]
    fn check_motions<'py>(
        &self,
        py: Python<'py>,
        tree: &PyOcTree,
        q0s: &Bound<'py, PyAny>,
        q1s: &Bound<'py, PyAny>,
        resolution: f64,
        obstacles: &str,
        self_collision: bool,
    ) -> PyResult<Bound<'py, PyArray1<bool>>> {
        let source = obstacle_source(obstacles)?;
        let dof = self.dof();
        let (a, ka, _) = configurations(q0s, dof, "q0s")?;
        let (b, kb, _) = configurations(q1s, dof, "q1s")?;
        if ka != kb {
            return Err(PyValueError::new_err(format!("{ka} starts but {kb} ends")));
        }
        let index = self.index(py, tree, source)?;
        let params = CheckParams { self_collision };
        let pairs: Vec<(&[f64], &[f64])> = a.chunks(dof.max(1)).zip(b.chunks(dof.max(1))).collect();
        let hits = py.detach(|| {
            let model = self.read();
            let results = earcore_core::threads::map_parts(&pairs, |(x, y)| {
                robot::check_motion(&model, &index, x, y, resolution, params).map(|h| h.is_some())
            });
            results
                .into_iter()
                .collect::<earcore_core::Result<Vec<bool>>>()
        });
        Ok(vec_to_array(py, hits.py()?))
    }

    /// True where a configuration's bodies touch each other (pairs in
    /// `self_collision_pairs`). qs (dof,) or (K, dof).
    fn self_collisions<'py>(
        &self,
        py: Python<'py>,
        qs: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray1<bool>>> {
        let dof = self.dof();
        let (q, k, _) = configurations(qs, dof, "qs")?;
        self.check_q(&q, k)?;
        let hits = py.detach(|| {
            let model = self.read();
            q.chunks(dof.max(1))
                .map(|row| {
                    model.place(row).map(|p| {
                        model
                            .self_collision(&p, model.self_collision_pairs())
                            .is_some()
                    })
                })
                .collect::<earcore_core::Result<Vec<bool>>>()
        });
        Ok(vec_to_array(py, hits.py()?))
    }

    /// Distance from the robot's bodies to the nearest obstacle voxel, per
    /// configuration, with the closest points: a dict with `distance` (negative when
    /// overlapping; inf when there is no obstacle), `link`, `on_robot`, `on_obstacle`.
    /// Validates as `check_configurations` does (the same errors) and shares its
    /// collision index and that index's cost.
    #[pyo3(signature = (tree, qs, *, obstacles = "occupied"))]
    fn clearance<'py>(
        &self,
        py: Python<'py>,
        tree: &PyOcTree,
        qs: &Bound<'py, PyAny>,
        obstacles: &str,
    ) -> PyResult<Bound<'py, PyDict>> {
        let source = obstacle_source(obstacles)?;
        let (q, _, single) = configurations(qs, self.dof(), "qs")?;
        let index = self.index(py, tree, source)?;
        let found = py
            .detach(|| robot::clearances(&self.read(), &index, &q))
            .py()?;
        clearance_dict(py, &found, single)
    }

    /// Clearance to boxes given directly (e.g. one tracked obstacle's voxels: centres
    /// (N, 3) and their edge length `size`), exact and without a map. Same result as
    /// `clearance`: distance (inf when there are no boxes; negative when touching),
    /// link, on_robot, on_obstacle.
    #[pyo3(signature = (centres, size, qs))]
    fn clearance_to_voxels<'py>(
        &self,
        py: Python<'py>,
        centres: &Bound<'py, PyAny>,
        size: f64,
        qs: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let (q, _, single) = configurations(qs, self.dof(), "qs")?;
        let boxes = point_rows(centres, "centres")?;
        let boxes = boxes.as_slice()?;
        let half = [0.5 * size; 3];
        let found = py
            .detach(|| robot::clearances_to_boxes(&self.read(), &q, boxes, half))
            .py()?;
        clearance_dict(py, &found, single)
    }

    /// Whether the robot's moving bodies meet any of the boxes (centres (N, 3), edge
    /// `size`; touching counts), per configuration: `clearance_to_voxels`'s
    /// distance ≤ 0 without computing the distance, so cheaper for a yes/no.
    #[pyo3(signature = (centres, size, qs))]
    fn touches_voxels<'py>(
        &self,
        py: Python<'py>,
        centres: &Bound<'py, PyAny>,
        size: f64,
        qs: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray1<bool>>> {
        let (q, _, _) = configurations(qs, self.dof(), "qs")?;
        let boxes = point_rows(centres, "centres")?;
        let boxes = boxes.as_slice()?;
        let half = [0.5 * size; 3];
        let hits = py.detach(|| robot::touches_boxes(&self.read(), &q, boxes, half));
        Ok(vec_to_array(py, hits.py()?))
    }

    /// Paper II's Eq. 4 danger cost of the straight motion q0 → q1 on `tree`'s danger
    /// map: Σ over bodies of the mean over the body's axis points of Σ d·(1 + C_voxel).
    #[pyo3(signature = (tree, q0, q1, resolution = 0.02))]
    fn motion_danger(
        &self,
        py: Python<'_>,
        tree: &PyOcTree,
        q0: &Bound<'_, PyAny>,
        q1: &Bound<'_, PyAny>,
        resolution: f64,
    ) -> PyResult<f64> {
        let dof = self.dof();
        let (a, b) = motion_ends(q0, q1, dof, "motion_danger()")?;
        py.detach(|| {
            let t = tree.read_detached();
            robot::motion_danger(&self.read(), &t, &a, &b, resolution)
        })
        .py()
    }

    /// Eq. 4 along a polyline (M, dof): the sum of `motion_danger` over its segments.
    #[pyo3(signature = (tree, path, resolution = 0.02))]
    fn path_danger(
        &self,
        py: Python<'_>,
        tree: &PyOcTree,
        path: &Bound<'_, PyAny>,
        resolution: f64,
    ) -> PyResult<f64> {
        let dof = self.dof();
        let (q, k, _) = configurations(path, dof, "path")?;
        py.detach(|| {
            let t = tree.read_detached();
            let model = self.read();
            // Every configuration is checked, a lone one (no segment) included.
            for i in 0..k {
                model
                    .chain()
                    .check_configuration(&q[i * dof..(i + 1) * dof], i)?;
            }
            let mut total = 0.0;
            for i in 1..k {
                let (a, b) = (&q[(i - 1) * dof..i * dof], &q[i * dof..(i + 1) * dof]);
                total += robot::motion_danger(&model, &t, a, b, resolution)?;
            }
            Ok(total)
        })
        .py()
    }

    fn __repr__(&self) -> String {
        let model = self.read();
        format!(
            "RobotModel('{}', dof={}, links={}, bodies={}, padding={})",
            self.name,
            model.dof(),
            model.chain().num_links(),
            model.bodies().iter().filter(|b| b.is_some()).count(),
            self.padding
        )
    }
}

/// Smallest body enclosing `vertices` (N, 3), grown by `padding` in every direction:
/// `shape` "capsule", "cylinder" or "auto" (the one with less volume). Returns
/// (a, b, radius, shape).
#[pyfunction]
#[pyo3(signature = (vertices, padding = 0.0, shape = "auto"))]
pub fn fit_body(vertices: &Bound<'_, PyAny>, padding: f64, shape: &str) -> PyResult<BodySpec> {
    let shape = match shape {
        "capsule" => FitShape::Capsule,
        "cylinder" => FitShape::Cylinder,
        "auto" => FitShape::Auto,
        other => {
            return Err(PyValueError::new_err(format!(
                "shape must be 'capsule', 'cylinder' or 'auto', got '{other}'"
            )))
        }
    };
    let v = point_rows(vertices, "vertices")?;
    let v = v.as_slice()?;
    let body = vertices
        .py()
        .detach(|| robot::fit_body(v, padding, shape))
        .py()?;
    Ok(body_spec(&body))
}
