//! `earcore.SurfaceMap`: NOctoSLAM's octree of positions and surface normals.

use earcore_core::octree::{SurfaceMap, SurfaceParams};
use numpy::{PyArray1, PyArray2};
use parking_lot::RwLock;
use pyo3::prelude::*;

use crate::convert::{points, rows_to_array, vec_to_array};
use crate::errors::IntoPyResult;

/// Node positions (M, 3), unit normals (M, 3; NaN where a node has none) and depths (M,).
type SurfaceNodes<'py> = (
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray1<u8>>,
);

/// Octree whose nodes hold an occupancy, a position and a surface normal (NOctoSLAM).
/// Locking as for `OcTree`: `insert` writes, queries read, both without the GIL.
#[pyclass(name = "SurfaceMap", module = "earcore", frozen)]
pub struct PySurfaceMap {
    inner: RwLock<SurfaceMap>,
}

impl PySurfaceMap {
    /// The map under its read lock (for ICP against it).
    pub(crate) fn read(&self) -> parking_lot::RwLockReadGuard<'_, SurfaceMap> {
        self.inner.read()
    }
}

#[pymethods]
impl PySurfaceMap {
    #[new]
    #[pyo3(signature = (resolution=0.01, *, prob_hit=0.7, clamping_max=0.971, similar=0.25))]
    fn new(resolution: f64, prob_hit: f64, clamping_max: f64, similar: f64) -> PyResult<Self> {
        let params = SurfaceParams {
            prob_hit,
            clamping_max,
            similar,
        };
        Ok(PySurfaceMap {
            inner: RwLock::new(SurfaceMap::new(resolution, params).py()?),
        })
    }

    #[getter]
    fn resolution(&self) -> f64 {
        self.inner.read().resolution()
    }

    /// Insert end points (N, 3) and propagate positions and normals up the tree;
    /// returns the number of leaves touched.
    fn insert(&self, py: Python<'_>, points: &Bound<'_, PyAny>) -> PyResult<usize> {
        let pts = self::points(points, "points")?;
        let slice = pts.as_slice()?;
        py.detach(|| self.inner.write().insert(slice)).py()
    }

    /// Nodes at `depth` (16 = leaves; None = every node): positions (M, 3), normals
    /// (M, 3, NaN where a node has none) and depths (M,).
    #[pyo3(signature = (depth=None))]
    fn nodes<'py>(&self, py: Python<'py>, depth: Option<u32>) -> PyResult<SurfaceNodes<'py>> {
        if depth.is_some_and(|d| d > 16) {
            return Err(pyo3::exceptions::PyValueError::new_err(
                "depth must be between 0 and 16",
            ));
        }
        let (p, n, d) = py.detach(|| {
            let map = self.inner.read();
            let (mut p, mut n, mut d) = (Vec::new(), Vec::new(), Vec::new());
            map.for_each_node(depth, |s| {
                p.push(s.node.position.map(f64::from));
                n.push(if s.node.has_normal {
                    s.node.normal.map(f64::from)
                } else {
                    [f64::NAN; 3]
                });
                d.push(s.depth as u8);
            });
            (p, n, d)
        });
        Ok((
            rows_to_array(py, p)?,
            rows_to_array(py, n)?,
            vec_to_array(py, d),
        ))
    }

    /// Number of nodes.
    fn size(&self) -> usize {
        self.inner.read().size()
    }

    fn __len__(&self) -> usize {
        self.size()
    }

    fn memory_usage(&self) -> usize {
        self.inner.read().memory_usage()
    }

    fn __repr__(&self) -> String {
        let map = self.inner.read();
        format!(
            "SurfaceMap(resolution={}, nodes={})",
            map.resolution(),
            map.size()
        )
    }
}
