//! `earcore.OcTree`: the occupancy + danger map.
//!
//! Locking: the tree sits behind a read-write lock. Insertions, `update_node`, `prune`,
//! `end_frame` and file reads take the write lock; every query takes the read lock, so
//! any number of threads may query at once and a writer waits for them (and they for
//! it). All O(N) work runs detached from the GIL, so other Python threads keep going.

use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};

use earcore_core::octree::{
    trace_scan, DangerParams, DecayMode, FrameReport, InsertReport, KeyConverter, Leaf, OcTree,
    OcTreeKey, OccupancyParams, TracedScan,
};
use numpy::{PyArray1, PyArray2};
use parking_lot::RwLock;
use pyo3::exceptions::{PyOSError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyType;

use crate::convert::{points, rows_to_array, vec_to_array, vector3};
use crate::errors::IntoPyResult;
use crate::interrupt::detach_interruptible;

type Voxels<'py> = (Bound<'py, PyArray2<f64>>, Bound<'py, PyArray1<f64>>);
/// Centres, sizes and a float32 value per voxel.
type ValuedVoxels<'py> = (
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<f32>>,
);
/// Keys, depths and log-odds of leaves.
type KeyedLeaves<'py> = (
    Bound<'py, PyArray2<u16>>,
    Bound<'py, PyArray1<u8>>,
    Bound<'py, PyArray1<f32>>,
);
/// Centres and log-odds of finest cells.
type Cells<'py> = (Bound<'py, PyArray2<f64>>, Bound<'py, PyArray1<f32>>);
/// Hit flags and end points of rays.
type RayHits<'py> = (Bound<'py, PyArray1<bool>>, Bound<'py, PyArray2<f64>>);

/// Occupancy octree with OctoMap's semantics and files, plus per-voxel danger decay.
///
/// `resolution` must lie in [1e-18, 1e14] m: points are float32 as in OctoMap, so one
/// cell's squared length must be a normal float32 and the map's squared diagonal a
/// finite one. Trees pickle (nodes, sensor model and danger state).
#[pyclass(name = "OcTree", module = "earcore", frozen)]
pub struct PyOcTree {
    inner: RwLock<OcTree>,
    /// Unique per tree object and bumped by every write, so derived indexes (the robot's
    /// collision index) know when to rebuild.
    uid: u64,
    revision: AtomicU64,
}

static NEXT_TREE_UID: AtomicU64 = AtomicU64::new(1);

#[pyclass(name = "InsertReport", module = "earcore", frozen, get_all)]
#[derive(Clone)]
pub struct PyInsertReport {
    /// Rays integrated (distinct end cells with `discretize`).
    rays: usize,
    /// Cells updated as free.
    free_cells: usize,
    /// Cells updated as occupied.
    occupied_cells: usize,
}

#[pymethods]
impl PyInsertReport {
    fn __repr__(&self) -> String {
        format!(
            "InsertReport(rays={}, free_cells={}, occupied_cells={})",
            self.rays, self.free_cells, self.occupied_cells
        )
    }
}

impl From<InsertReport> for PyInsertReport {
    fn from(r: InsertReport) -> Self {
        PyInsertReport {
            rays: r.rays,
            free_cells: r.free_cells,
            occupied_cells: r.occupied_cells,
        }
    }
}

#[pyclass(name = "FrameReport", module = "earcore", frozen, get_all)]
#[derive(Clone)]
pub struct PyFrameReport {
    /// Voxels hit during the frame (danger reset to 0.999).
    hit: usize,
    /// Voxels whose danger decayed.
    decayed: usize,
    /// Voxels that reached 0 and stopped being dangerous.
    cleared: usize,
    /// Voxels still dangerous.
    active: usize,
}

#[pymethods]
impl PyFrameReport {
    fn __repr__(&self) -> String {
        format!(
            "FrameReport(hit={}, decayed={}, cleared={}, active={})",
            self.hit, self.decayed, self.cleared, self.active
        )
    }
}

impl From<FrameReport> for PyFrameReport {
    fn from(r: FrameReport) -> Self {
        PyFrameReport {
            hit: r.hit,
            decayed: r.decayed,
            cleared: r.cleared,
            active: r.active,
        }
    }
}

fn parse_mode(mode: &str) -> PyResult<DecayMode> {
    match mode {
        "observed" => Ok(DecayMode::Observed),
        "always" => Ok(DecayMode::Always),
        other => Err(PyValueError::new_err(format!(
            "decay_mode must be 'observed' or 'always', got {other:?}"
        ))),
    }
}

fn mode_name(mode: DecayMode) -> &'static str {
    match mode {
        DecayMode::Observed => "observed",
        DecayMode::Always => "always",
    }
}

fn read_file(path: &PathBuf) -> PyResult<Vec<u8>> {
    std::fs::read(path)
        .map_err(|e| PyOSError::new_err(format!("cannot read {}: {e}", path.display())))
}

/// Write through a temporary file and rename, so a failed write never leaves a
/// half-written map where a good one was.
fn write_file(path: &std::path::Path, bytes: &[u8]) -> PyResult<()> {
    let error =
        |e: std::io::Error| PyOSError::new_err(format!("cannot write {}: {e}", path.display()));
    // Through a symbolic link to its target; a device or pipe is written as it is (no
    // temporary beside it can replace it).
    let target = through_links(path);
    let existing = std::fs::metadata(&target).ok();
    if existing.as_ref().is_some_and(|m| !m.is_file()) {
        return std::fs::write(&target, bytes).map_err(error);
    }
    let mut tmp = target.clone().into_os_string();
    tmp.push(".earcore-tmp");
    let tmp = PathBuf::from(tmp);
    std::fs::write(&tmp, bytes)
        // A file that was there keeps its permissions.
        .and_then(|_| match &existing {
            Some(m) => std::fs::set_permissions(&tmp, m.permissions()),
            None => Ok(()),
        })
        .and_then(|_| std::fs::rename(&tmp, &target))
        .map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            error(e)
        })
}

/// `path` with its symbolic links followed, also to a target that does not exist yet
/// (which `canonicalize` refuses: the link itself was then replaced by the file).
fn through_links(path: &std::path::Path) -> PathBuf {
    let mut at = path.to_path_buf();
    // A cycle of links ends after as many hops as the system follows.
    for _ in 0..40 {
        let Ok(next) = std::fs::read_link(&at) else {
            return at;
        };
        at = match at.parent() {
            Some(dir) if next.is_relative() => dir.join(next),
            _ => next,
        };
    }
    at
}

impl PyOcTree {
    fn wrap(tree: OcTree) -> Self {
        PyOcTree {
            inner: RwLock::new(tree),
            uid: NEXT_TREE_UID.fetch_add(1, Ordering::Relaxed),
            revision: AtomicU64::new(0),
        }
    }

    /// Read a file and parse it with `reader` (detached from the GIL).
    fn load(
        py: Python<'_>,
        path: &PathBuf,
        params: OccupancyParams,
        reader: fn(&[u8], OccupancyParams) -> earcore_core::Result<OcTree>,
    ) -> PyResult<Self> {
        let bytes = read_file(path)?;
        let tree = py.detach(|| reader(&bytes, params)).py()?;
        Ok(Self::wrap(tree))
    }

    /// Run `f` on the tree under the read lock, detached from the GIL (waiting for a
    /// writer never stalls other Python threads).
    fn with_read<R: Send>(&self, py: Python<'_>, f: impl FnOnce(&OcTree) -> R + Send) -> R {
        py.detach(|| f(&self.inner.read()))
    }

    /// Same under the write lock.
    fn with_write<R: Send>(&self, py: Python<'_>, f: impl FnOnce(&mut OcTree) -> R + Send) -> R {
        py.detach(|| {
            let mut tree = self.inner.write();
            self.revision.fetch_add(1, Ordering::Relaxed);
            f(&mut tree)
        })
    }

    /// Insert a scan `trace` traces (ray casting, the long part) for this tree's key
    /// converter: traced with no lock on the tree held (its resolution never changes),
    /// so that the signal handlers run between rounds (Ctrl-C stops it) may use the
    /// tree, then applied under the write lock.
    fn insert_traced(
        &self,
        py: Python<'_>,
        trace: impl FnOnce(
                &KeyConverter,
                &mut earcore_core::threads::Interrupt<'_>,
            ) -> earcore_core::Result<Option<TracedScan>>
            + Send,
    ) -> PyResult<PyInsertReport> {
        let conv = self.with_read(py, |tree| *tree.key_converter());
        let Some(scan) = detach_interruptible(py, |stop| trace(&conv, stop))?.py()? else {
            // Stopped only when a signal handler raised, which detach_interruptible returned.
            return Err(pyo3::exceptions::PyKeyboardInterrupt::new_err(
                "the insertion was interrupted; the map is unchanged",
            ));
        };
        let report = self.with_write(py, |tree| tree.apply_scan(scan)).py()?;
        Ok(report.into())
    }

    /// Replace the danger's parameters by `change` of them (the map's contents stay, so
    /// the revision does too).
    fn change_danger_params(
        &self,
        py: Python<'_>,
        change: impl FnOnce(DangerParams) -> DangerParams + Send,
    ) -> PyResult<()> {
        py.detach(|| {
            let mut tree = self.inner.write();
            let params = change(tree.danger_map().params());
            tree.danger_map_mut().set_params(params)
        })
        .py()
    }

    /// (tree id, revision): changes whenever the tree's contents may have changed.
    pub(crate) fn version(&self) -> (u64, u64) {
        (self.uid, self.revision.load(Ordering::Relaxed))
    }

    /// Read access for other binding modules (the caller is already detached).
    pub(crate) fn read_detached(&self) -> parking_lot::RwLockReadGuard<'_, OcTree> {
        self.inner.read()
    }

    fn centres_and_sizes(tree: &OcTree, leaves: &[(OcTreeKey, u32)]) -> (Vec<[f64; 3]>, Vec<f64>) {
        let centres = leaves
            .iter()
            .map(|&(k, d)| tree.node_center(k, d))
            .collect();
        let sizes = leaves
            .iter()
            .map(|&(_, d)| tree.key_converter().node_size(d))
            .collect();
        (centres, sizes)
    }
}

#[pymethods]
impl PyOcTree {
    #[new]
    #[pyo3(signature = (resolution=0.05, *, prob_hit=0.7, prob_miss=0.4, clamping_min=0.1192, clamping_max=0.971,
                        occupancy_threshold=0.5, danger_alpha=0.3, decay_mode="observed"))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        resolution: f64,
        prob_hit: f64,
        prob_miss: f64,
        clamping_min: f64,
        clamping_max: f64,
        occupancy_threshold: f64,
        danger_alpha: f64,
        decay_mode: &str,
    ) -> PyResult<Self> {
        let params = OccupancyParams {
            prob_hit,
            prob_miss,
            clamping_min,
            clamping_max,
            occupancy_threshold,
        };
        let mut tree = OcTree::with_params(resolution, params).py()?;
        tree.danger_map_mut()
            .set_params(DangerParams {
                alpha: danger_alpha,
                mode: parse_mode(decay_mode)?,
            })
            .py()?;
        Ok(Self::wrap(tree))
    }

    /// Edge length of the finest voxels, in metres.
    #[getter]
    fn resolution(&self, py: Python<'_>) -> f64 {
        self.with_read(py, |tree| tree.resolution())
    }

    #[getter]
    fn prob_hit(&self, py: Python<'_>) -> f64 {
        self.with_read(py, |tree| tree.params().prob_hit)
    }

    #[getter]
    fn prob_miss(&self, py: Python<'_>) -> f64 {
        self.with_read(py, |tree| tree.params().prob_miss)
    }

    #[getter]
    fn clamping_min(&self, py: Python<'_>) -> f64 {
        self.with_read(py, |tree| tree.params().clamping_min)
    }

    #[getter]
    fn clamping_max(&self, py: Python<'_>) -> f64 {
        self.with_read(py, |tree| tree.params().clamping_max)
    }

    #[getter]
    fn occupancy_threshold(&self, py: Python<'_>) -> f64 {
        self.with_read(py, |tree| tree.params().occupancy_threshold)
    }

    /// Decay speed α of the danger rule (Paper II, Eq. 1).
    #[getter]
    fn get_danger_alpha(&self, py: Python<'_>) -> f64 {
        self.with_read(py, |tree| tree.danger_map().params().alpha)
    }

    #[setter]
    fn set_danger_alpha(&self, py: Python<'_>, alpha: f64) -> PyResult<()> {
        self.change_danger_params(py, |p| DangerParams { alpha, ..p })
    }

    /// 'observed' (decay only where a ray saw the voxel free) or 'always'.
    #[getter]
    fn get_decay_mode(&self, py: Python<'_>) -> &'static str {
        mode_name(self.with_read(py, |tree| tree.danger_map().params().mode))
    }

    #[setter]
    fn set_decay_mode(&self, py: Python<'_>, mode: &str) -> PyResult<()> {
        let mode = parse_mode(mode)?;
        self.change_danger_params(py, |p| DangerParams { mode, ..p })
    }

    /// Integrate a scan: rays from `sensor_origin` to each point (N, 3).
    ///
    /// Cells along a ray become more likely free, end cells more likely occupied (and
    /// dangerous); rays longer than `max_range` are cut there and mark no hit (so
    /// their points may lie off the map, unless `discretize`d); `discretize` merges
    /// points that fall in the same cell. Invalid input raises
    /// before anything changes; Ctrl-C stops a long insertion while its rays are
    /// traced, the map unchanged.
    #[pyo3(signature = (points, sensor_origin, max_range=None, discretize=false))]
    fn insert_point_cloud(
        &self,
        py: Python<'_>,
        points: &Bound<'_, PyAny>,
        sensor_origin: &Bound<'_, PyAny>,
        max_range: Option<f64>,
        discretize: bool,
    ) -> PyResult<PyInsertReport> {
        let pts = self::points(points, "points")?;
        let origin = vector3(sensor_origin, "sensor_origin")?;
        let slice = pts.as_slice()?;
        self.insert_traced(py, |conv, stop| {
            trace_scan(conv, slice, origin, max_range, discretize, true, stop)
        })
    }

    /// Rays that only clear space: the cells each ray from `sensor_origin` to a point
    /// crosses are marked free (end cells excluded), no end cell is hit; seen-free
    /// danger decays as with `insert_point_cloud`. For points that are not obstacles
    /// (e.g. a table the map models as known geometry).
    #[pyo3(signature = (points, sensor_origin, max_range = None))]
    fn insert_free_rays(
        &self,
        py: Python<'_>,
        points: &Bound<'_, PyAny>,
        sensor_origin: &Bound<'_, PyAny>,
        max_range: Option<f64>,
    ) -> PyResult<PyInsertReport> {
        let pts = self::points(points, "points")?;
        let origin = vector3(sensor_origin, "sensor_origin")?;
        let slice = pts.as_slice()?;
        self.insert_traced(py, |conv, stop| {
            trace_scan(conv, slice, origin, max_range, false, false, stop)
        })
    }

    /// Occupancy per point: -1 unknown, 0 free, 1 occupied (int8, shape (N,)).
    fn is_occupied<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray1<i8>>> {
        let pts = self::points(points, "points")?;
        let slice = pts.as_slice()?;
        let out = self.with_read(py, |tree| {
            slice
                .iter()
                .map(|&p| match lookup(tree, p) {
                    None => -1,
                    Some(l) => i8::from(tree.is_occupied_log_odds(l)),
                })
                .collect::<Vec<i8>>()
        });
        Ok(vec_to_array(py, out))
    }

    /// Log-odds per point (float32, NaN where unknown).
    fn log_odds<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray1<f32>>> {
        let pts = self::points(points, "points")?;
        let slice = pts.as_slice()?;
        let out = self.with_read(py, |tree| {
            slice
                .iter()
                .map(|&p| lookup(tree, p).unwrap_or(f32::NAN))
                .collect::<Vec<f32>>()
        });
        Ok(vec_to_array(py, out))
    }

    /// Log-odds of the node holding `point` at `depth` (0 = finest), None if unknown.
    #[pyo3(signature = (point, depth=0))]
    fn search(
        &self,
        py: Python<'_>,
        point: &Bound<'_, PyAny>,
        depth: i64,
    ) -> PyResult<Option<f32>> {
        let max = earcore_core::octree::TREE_DEPTH;
        let depth = u32::try_from(depth)
            .ok()
            .filter(|&d| d <= max)
            .ok_or_else(|| {
                pyo3::exceptions::PyValueError::new_err(format!(
                    "depth must be 0 to {max}, got {depth}"
                ))
            })?;
        let p = vector3(point, "point")?;
        self.with_read(py, |tree| {
            tree.key_of("point", p).map(|key| tree.search(key, depth))
        })
        .py()
    }

    /// Batched `update_node` with a hit (`occupied=True`) or miss for every point, in
    /// order (a cell listed twice is updated twice). All points are checked first, so a
    /// point off the map changes nothing.
    #[pyo3(signature = (points, occupied = true))]
    fn update_nodes(
        &self,
        py: Python<'_>,
        points: &Bound<'_, PyAny>,
        occupied: bool,
    ) -> PyResult<()> {
        let pts = crate::convert::points(points, "points")?;
        let pts = pts.as_slice()?;
        self.with_write(py, |tree| {
            let keys = pts
                .iter()
                .map(|&p| tree.key_of("point", p))
                .collect::<earcore_core::Result<Vec<_>>>()?;
            for key in keys {
                tree.update_node(key, occupied);
            }
            Ok(())
        })
        .py()
    }

    /// Integrate one measurement at `point`: `True` a hit, `False` a miss (Python or
    /// numpy bools), or a real number, a log-odds change (OctoMap's `updateNode`).
    fn update_node(
        &self,
        py: Python<'_>,
        point: &Bound<'_, PyAny>,
        update: &Bound<'_, PyAny>,
    ) -> PyResult<()> {
        let p = vector3(point, "point")?;
        let update = hit_or_change(update)?;
        self.with_write(py, |tree| {
            let key = tree.key_of("point", p)?;
            match update {
                Update::Hit(h) => {
                    tree.update_node(key, h);
                    Ok(())
                }
                Update::Change(d) => tree.update_node_log_odds(key, d),
            }
        })
        .py()
    }

    /// Set the log-odds of the finest cell holding each point (N, 3) to `value`,
    /// clamped to [clamping_min, clamping_max] in log-odds (`math.inf` / `-math.inf`
    /// give the clamps): OctoMap's `setNodeValue` for each cell, pruned nodes expanded,
    /// ancestors updated and equal siblings pruned as it does. A cell listed twice is
    /// set once. Danger is not touched (as with `update_nodes`). All points are
    /// checked first, so bad input changes nothing.
    fn set_log_odds(&self, py: Python<'_>, points: &Bound<'_, PyAny>, value: f64) -> PyResult<()> {
        if value.is_nan() {
            return Err(PyValueError::new_err(
                "value must be a log-odds number, got NaN",
            ));
        }
        let pts = self::points(points, "points")?;
        let pts = pts.as_slice()?;
        self.with_write(py, |tree| {
            let keys = keys_of(tree, pts)?;
            tree.set_log_odds(&keys, value as f32)
        })
        .py()
    }

    /// Add `delta` (log-odds) to the finest cell holding each point (N, 3), `repeat`
    /// times per point: the tree ends as after OctoMap's `updateNode(key, delta)` called
    /// for every point in turn, `repeat` times over (a cell listed twice is updated
    /// twice per round), with its clamping and its early abort for cells already at the
    /// bound. `update_nodes(points, occupied)` repeated k times equals
    /// `update_log_odds(points, log(p / (1 - p)), repeat=k)` with p = prob_hit or
    /// prob_miss. Danger is not touched. All points are checked first.
    #[pyo3(signature = (points, delta, *, repeat = 1))]
    fn update_log_odds(
        &self,
        py: Python<'_>,
        points: &Bound<'_, PyAny>,
        delta: f64,
        repeat: i64,
    ) -> PyResult<()> {
        let repeat = u32::try_from(repeat).map_err(|_| {
            PyValueError::new_err(format!(
                "repeat must be a count from 0 to {}, got {repeat}",
                u32::MAX
            ))
        })?;
        let delta32 = delta as f32;
        if !delta32.is_finite() {
            return Err(PyValueError::new_err(format!(
                "delta must be a finite log-odds change (in float32), got {}",
                earcore_core::geometry::fmt_num(delta)
            )));
        }
        let pts = self::points(points, "points")?;
        let pts = pts.as_slice()?;
        self.with_write(py, |tree| {
            let keys = keys_of(tree, pts)?;
            tree.update_log_odds(&keys, delta32, repeat)
        })
        .py()
    }

    /// Every known finest-resolution cell whose centre lies in the box
    /// [bbx_min, bbx_max] (bounds included): centres (M, 3) float64 and log-odds (M,)
    /// float32, pruned leaves split into their cells. `occupied_only`: only cells at or
    /// above the occupancy threshold. Parts of the box beyond the map are ignored; an
    /// empty box (min > max on an axis) gives nothing; a box holding more than 2^26
    /// cells raises ValueError.
    #[pyo3(signature = (bbx_min, bbx_max, *, occupied_only = false))]
    fn leaves_at_full_depth<'py>(
        &self,
        py: Python<'py>,
        bbx_min: &Bound<'py, PyAny>,
        bbx_max: &Bound<'py, PyAny>,
        occupied_only: bool,
    ) -> PyResult<Cells<'py>> {
        let lo = vector3(bbx_min, "bbx_min")?;
        let hi = vector3(bbx_max, "bbx_max")?;
        let (c, l) = self
            .with_read(py, |tree| {
                let cells =
                    tree.finest_cells_in_box(lo, hi, occupied_only, MAX_FULL_DEPTH_CELLS)?;
                let centres: Vec<[f64; 3]> = cells
                    .iter()
                    .map(|&(k, _)| tree.node_center(k, earcore_core::octree::TREE_DEPTH))
                    .collect();
                Ok((centres, cells.iter().map(|&(_, l)| l).collect::<Vec<f32>>()))
            })
            .py()?;
        Ok((rows_to_array(py, c)?, vec_to_array(py, l)))
    }

    /// An independent copy: every node and log-odds, the sensor model, the danger
    /// parameters and state (dangerous voxels, the frame's hits and free sightings, the
    /// last frame's obstacles). The copy is a new map for caches such as the robot's
    /// collision index.
    fn copy(&self, py: Python<'_>) -> Self {
        Self::wrap(self.with_read(py, |tree| tree.clone()))
    }

    fn __copy__(&self, py: Python<'_>) -> Self {
        self.copy(py)
    }

    fn __deepcopy__(&self, py: Python<'_>, _memo: &Bound<'_, PyAny>) -> Self {
        self.copy(py)
    }

    /// Pickling: the tree's `.ot` bytes plus what they do not hold (the sensor model
    /// and the danger state), so an unpickled tree equals a `copy()`.
    fn __reduce__<'py>(
        slf: &Bound<'py, Self>,
        py: Python<'py>,
    ) -> PyResult<(Bound<'py, PyAny>, (Bound<'py, pyo3::types::PyBytes>,))> {
        let state = slf.get().with_read(py, |t| t.write_state_bytes());
        let rebuild = slf.get_type().getattr("_from_state")?;
        Ok((rebuild, (pyo3::types::PyBytes::new(py, &state),)))
    }

    /// The tree `__reduce__` saved (bytes are checked as map files are).
    #[classmethod]
    fn _from_state(_cls: &Bound<'_, PyType>, py: Python<'_>, state: &[u8]) -> PyResult<Self> {
        let tree = py.detach(|| OcTree::read_state_bytes(state)).py()?;
        Ok(Self::wrap(tree))
    }

    /// Centres (M, 3) and edge lengths (M,) of the occupied leaves.
    fn occupied_voxels<'py>(&self, py: Python<'py>) -> PyResult<Voxels<'py>> {
        let (c, s) = self.with_read(py, |tree| {
            let mut leaves = Vec::new();
            tree.for_each_leaf(|l| {
                if tree.is_occupied_log_odds(l.log_odds) {
                    leaves.push((l.key, l.depth));
                }
            });
            Self::centres_and_sizes(tree, &leaves)
        });
        Ok((rows_to_array(py, c)?, vec_to_array(py, s)))
    }

    /// Leaves (pruned ones included) as centres (M, 3), sizes (M,) and log-odds (M,),
    /// optionally only those meeting the box [bbx_min, bbx_max].
    #[pyo3(signature = (bbx_min=None, bbx_max=None))]
    fn leaves<'py>(
        &self,
        py: Python<'py>,
        bbx_min: Option<&Bound<'py, PyAny>>,
        bbx_max: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<ValuedVoxels<'py>> {
        let bounds = self.key_bounds(py, bbx_min, bbx_max)?;
        let (c, s, l) = self.with_read(py, |tree| {
            let leaves = collect_leaves(tree, bounds);
            let keyed: Vec<(OcTreeKey, u32)> = leaves.iter().map(|l| (l.key, l.depth)).collect();
            let (c, s) = Self::centres_and_sizes(tree, &keyed);
            (c, s, leaves.iter().map(|l| l.log_odds).collect())
        });
        Ok((
            rows_to_array(py, c)?,
            vec_to_array(py, s),
            vec_to_array(py, l),
        ))
    }

    /// Leaves as OctoMap keys: lower-corner keys (M, 3) uint16, depths (M,) uint8 and
    /// log-odds (M,) float32 (for exact comparisons with OctoMap).
    fn leaf_keys<'py>(&self, py: Python<'py>) -> PyResult<KeyedLeaves<'py>> {
        let bounds = self.key_bounds(py, None, None)?;
        let leaves = self.with_read(py, |tree| collect_leaves(tree, bounds));
        let m = leaves.len();
        let keys: Vec<u16> = leaves.iter().flat_map(|l| l.key.0).collect();
        let keys = numpy::ndarray::Array2::from_shape_vec((m, 3), keys)
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        Ok((
            numpy::IntoPyArray::into_pyarray(keys, py),
            vec_to_array(py, leaves.iter().map(|l| l.depth as u8).collect()),
            vec_to_array(py, leaves.iter().map(|l| l.log_odds).collect()),
        ))
    }

    /// Cast a ray from `origin` along `direction`; returns (hit, end) where `end` is the
    /// centre of the first occupied cell, or of the cell where the search stopped
    /// (unknown cell unless `ignore_unknown`, `max_range`, or the map's edge).
    #[pyo3(signature = (origin, direction, max_range=None, ignore_unknown=false))]
    fn cast_ray<'py>(
        &self,
        py: Python<'py>,
        origin: &Bound<'py, PyAny>,
        direction: &Bound<'py, PyAny>,
        max_range: Option<f64>,
        ignore_unknown: bool,
    ) -> PyResult<(bool, Bound<'py, PyArray1<f64>>)> {
        let o = vector3(origin, "origin")?;
        let d = vector3(direction, "direction")?;
        let hit = self
            .with_read(py, |tree| tree.cast_ray(o, d, max_range, ignore_unknown))
            .py()?;
        Ok((hit.hit, vec_to_array(py, hit.end.to_vec())))
    }

    /// `cast_ray` for many rays: origins and directions (N, 3) (or one origin (3,) for
    /// all); returns hits (N,) bool and ends (N, 3).
    #[pyo3(signature = (origins, directions, max_range=None, ignore_unknown=false))]
    fn cast_rays<'py>(
        &self,
        py: Python<'py>,
        origins: &Bound<'py, PyAny>,
        directions: &Bound<'py, PyAny>,
        max_range: Option<f64>,
        ignore_unknown: bool,
    ) -> PyResult<RayHits<'py>> {
        let dirs = self::points(directions, "directions")?;
        let single = vector3(origins, "origins").ok();
        let many = if single.is_none() {
            Some(self::points(origins, "origins")?)
        } else {
            None
        };
        let d = dirs.as_slice()?;
        if let Some(m) = &many {
            if m.as_slice()?.len() != d.len() {
                return Err(PyValueError::new_err(format!(
                    "origins ({}) and directions ({}) must have the same length",
                    m.as_slice()?.len(),
                    d.len()
                )));
            }
        }
        let o_many = many.as_ref().map(|m| m.as_slice()).transpose()?;
        let results = self
            .with_read(py, |tree| {
                d.iter()
                    .enumerate()
                    .map(|(i, &dir)| {
                        let o = single.unwrap_or_else(|| o_many.map(|m| m[i]).unwrap_or_default());
                        tree.cast_ray(o, dir, max_range, ignore_unknown)
                    })
                    .collect::<Result<Vec<_>, _>>()
            })
            .py()?;
        let hits = results.iter().map(|r| r.hit).collect();
        let ends = results.iter().map(|r| r.end).collect();
        Ok((vec_to_array(py, hits), rows_to_array(py, ends)?))
    }

    /// Collapse every set of eight equal leaves into their parent (OctoMap's `prune`).
    fn prune(&self, py: Python<'_>) {
        self.with_write(py, |t| t.prune())
    }

    /// Recompute every inner node from its children.
    fn update_inner_occupancy(&self, py: Python<'_>) {
        self.with_write(py, |t| t.update_inner_occupancy())
    }

    /// Number of nodes (OctoMap's `size()`).
    fn size(&self, py: Python<'_>) -> usize {
        self.with_read(py, |t| t.size())
    }

    fn __len__(&self, py: Python<'_>) -> usize {
        self.size(py)
    }

    fn num_leaf_nodes(&self, py: Python<'_>) -> usize {
        self.with_read(py, |t| t.num_leaf_nodes())
    }

    /// Bytes held by the map (nodes, child blocks and danger), spare capacity included.
    fn memory_usage(&self, py: Python<'_>) -> usize {
        self.with_read(py, |t| t.memory_usage())
    }

    /// Forget every voxel's occupancy and danger; the sensor model, `danger_alpha` and
    /// `decay_mode` stay.
    fn clear(&self, py: Python<'_>) {
        self.with_write(py, |t| t.clear())
    }

    /// Save as OctoMap's binary `.bt` (maximum-likelihood occupancy; this tree is not changed).
    fn write_binary(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        let bytes = self.with_read(py, |t| t.write_binary_bytes());
        write_file(&path, &bytes)
    }

    /// Save as OctoMap's full `.ot` (every node's log-odds).
    fn write(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        let bytes = self.with_read(py, |t| t.write_full_bytes());
        write_file(&path, &bytes)
    }

    /// Load an OctoMap `.bt` file into a new tree (sensor model keyword arguments as in the constructor).
    #[classmethod]
    #[pyo3(signature = (path, *, prob_hit=0.7, prob_miss=0.4, clamping_min=0.1192, clamping_max=0.971, occupancy_threshold=0.5))]
    #[allow(clippy::too_many_arguments)]
    fn read_binary(
        _cls: &Bound<'_, PyType>,
        py: Python<'_>,
        path: PathBuf,
        prob_hit: f64,
        prob_miss: f64,
        clamping_min: f64,
        clamping_max: f64,
        occupancy_threshold: f64,
    ) -> PyResult<Self> {
        let params = OccupancyParams {
            prob_hit,
            prob_miss,
            clamping_min,
            clamping_max,
            occupancy_threshold,
        };
        Self::load(py, &path, params, OcTree::read_binary_bytes)
    }

    /// Load an OctoMap `.ot` file into a new tree.
    #[classmethod]
    #[pyo3(signature = (path, *, prob_hit=0.7, prob_miss=0.4, clamping_min=0.1192, clamping_max=0.971, occupancy_threshold=0.5))]
    #[allow(clippy::too_many_arguments)]
    fn read(
        _cls: &Bound<'_, PyType>,
        py: Python<'_>,
        path: PathBuf,
        prob_hit: f64,
        prob_miss: f64,
        clamping_min: f64,
        clamping_max: f64,
        occupancy_threshold: f64,
    ) -> PyResult<Self> {
        let params = OccupancyParams {
            prob_hit,
            prob_miss,
            clamping_min,
            clamping_max,
            occupancy_threshold,
        };
        Self::load(py, &path, params, OcTree::read_full_bytes)
    }

    // ---- danger (Paper II, Eq. 1) ----

    /// Close the current frame of `dt` seconds: voxels hit since the last call are at
    /// 0.999, the others decay by C ← C + ln(C)·dt·α (per `decay_mode`).
    fn end_frame(&self, py: Python<'_>, dt: f64) -> PyResult<PyFrameReport> {
        Ok(self
            .with_write(py, |t| t.danger_map_mut().end_frame(dt))
            .py()?
            .into())
    }

    /// Danger per point (float32 in [0, 0.999], 0 where never dangerous).
    fn danger<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray1<f32>>> {
        let pts = self::points(points, "points")?;
        let slice = pts.as_slice()?;
        let out = self.with_read(py, |tree| {
            slice
                .iter()
                .map(
                    |&p| match tree.key_converter().coord_to_key_checked_f64(p) {
                        Some(k) => tree.danger_map().value(k.morton()),
                        None => 0.0,
                    },
                )
                .collect::<Vec<f32>>()
        });
        Ok(vec_to_array(py, out))
    }

    /// Dangerous voxels: centres (M, 3), sizes (M,) and danger values (M,) float32.
    fn danger_voxels<'py>(&self, py: Python<'py>) -> PyResult<ValuedVoxels<'py>> {
        let (c, s, v) = self.with_read(py, |tree| {
            let cells = tree.danger_map().sorted_cells();
            let keyed: Vec<(OcTreeKey, u32)> = cells
                .iter()
                .map(|&(m, _)| (OcTreeKey::from_morton(m), 16))
                .collect();
            let (c, s) = Self::centres_and_sizes(tree, &keyed);
            (c, s, cells.iter().map(|&(_, v)| v).collect())
        });
        Ok((
            rows_to_array(py, c)?,
            vec_to_array(py, s),
            vec_to_array(py, v),
        ))
    }

    /// Voxels hit during the last closed frame: centres (M, 3) and sizes (M,).
    fn current_obstacles<'py>(&self, py: Python<'py>) -> PyResult<Voxels<'py>> {
        let (c, s) = self.with_read(py, |tree| {
            let keyed: Vec<(OcTreeKey, u32)> = tree
                .danger_map()
                .current_obstacles()
                .iter()
                .map(|&m| (OcTreeKey::from_morton(m), 16))
                .collect();
            Self::centres_and_sizes(tree, &keyed)
        });
        Ok((rows_to_array(py, c)?, vec_to_array(py, s)))
    }

    fn __repr__(&self, py: Python<'_>) -> String {
        self.with_read(py, |tree| {
            format!(
                "OcTree(resolution={}, nodes={}, dangerous_voxels={})",
                tree.resolution(),
                tree.size(),
                tree.danger_map().len()
            )
        })
    }
}

impl PyOcTree {
    /// Key box of an optional metric bounding box (the whole map where absent).
    fn key_bounds(
        &self,
        py: Python<'_>,
        bbx_min: Option<&Bound<'_, PyAny>>,
        bbx_max: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<(OcTreeKey, OcTreeKey)> {
        let lo = bbx_min.map(|b| vector3(b, "bbx_min")).transpose()?;
        let hi = bbx_max.map(|b| vector3(b, "bbx_max")).transpose()?;
        self.with_read(py, |tree| {
            let kmin = lo
                .map(|p| tree.key_of("bbx_min", p))
                .transpose()?
                .unwrap_or(OcTreeKey([0; 3]));
            let kmax = hi
                .map(|p| tree.key_of("bbx_max", p))
                .transpose()?
                .unwrap_or(OcTreeKey([u16::MAX; 3]));
            Ok((kmin, kmax))
        })
        .py()
    }
}

/// What `update_node` was asked to do.
enum Update {
    /// A hit (`true`) or a miss.
    Hit(bool),
    /// A log-odds change.
    Change(f32),
}

/// A bool (Python's or numpy's, which is no Python bool but converts to a float) is a
/// hit or miss; a real number is a log-odds change.
fn hit_or_change(update: &Bound<'_, PyAny>) -> PyResult<Update> {
    let wrong = |got: &str| {
        PyTypeError::new_err(format!(
            "update must be a bool (hit/miss) or a real log-odds change, got {got}"
        ))
    };
    if let Ok(b) = update.cast::<pyo3::types::PyBool>() {
        return Ok(Update::Hit(b.is_true()));
    }
    // numpy scalars and arrays: decide by dtype before any float conversion.
    if let Ok(dtype) = update.getattr("dtype") {
        let kind: String = dtype.getattr("kind")?.extract()?;
        let ndim: usize = update.getattr("ndim")?.extract()?;
        if ndim != 0 {
            return Err(wrong(&format!("an array of {ndim} dimensions")));
        }
        return match kind.as_str() {
            "b" => Ok(Update::Hit(update.is_truthy()?)),
            "f" | "i" | "u" => Ok(Update::Change(update.extract::<f64>()? as f32)),
            _ => Err(wrong(&format!("dtype {}", dtype.str()?))),
        };
    }
    match update.extract::<f64>() {
        Ok(d) if !update.is_instance_of::<pyo3::types::PyComplex>() => Ok(Update::Change(d as f32)),
        _ => Err(wrong(&format!("{}", update.get_type().name()?))),
    }
}

/// Most cells `leaves_at_full_depth` returns (1.5 GiB of centres).
const MAX_FULL_DEPTH_CELLS: usize = 1 << 26;

/// Keys of points that must all lie on the map (the first that does not is the error).
fn keys_of(tree: &OcTree, points: &[[f64; 3]]) -> earcore_core::Result<Vec<OcTreeKey>> {
    points.iter().map(|&p| tree.key_of("point", p)).collect()
}

fn collect_leaves(tree: &OcTree, (kmin, kmax): (OcTreeKey, OcTreeKey)) -> Vec<Leaf> {
    let mut leaves = Vec::new();
    tree.for_each_leaf_in_keys(kmin, kmax, |l| leaves.push(l));
    leaves
}

/// Log-odds of the leaf holding a double-precision point, `None` if unknown or off the map.
fn lookup(tree: &OcTree, p: [f64; 3]) -> Option<f32> {
    let key = tree.key_converter().coord_to_key_checked_f64(p)?;
    tree.search(key, 0)
}
