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

thread_local! {
    /// The maps a long call on this thread (ICP) holds for reading while it runs
    /// Python's signal handlers between iterations: a handler on this thread may read
    /// them (recursively, past a writer waiting on another thread) but not write them.
    static HELD: std::cell::RefCell<Vec<usize>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// A map held for reading by a long call on this thread (`PySurfaceMap::hold`).
pub(crate) struct Held<'a> {
    guard: parking_lot::RwLockReadGuard<'a, SurfaceMap>,
    id: usize,
}

impl std::ops::Deref for Held<'_> {
    type Target = SurfaceMap;
    fn deref(&self) -> &SurfaceMap {
        &self.guard
    }
}

impl Drop for Held<'_> {
    fn drop(&mut self) {
        HELD.with(|held| {
            let mut held = held.borrow_mut();
            if let Some(at) = held.iter().rposition(|&id| id == self.id) {
                held.remove(at);
            }
        });
    }
}

impl PySurfaceMap {
    fn id(&self) -> usize {
        self as *const Self as usize
    }

    fn held_here(&self) -> bool {
        HELD.with(|held| held.borrow().contains(&self.id()))
    }

    /// The map under its read lock for a long call on this thread that runs Python's
    /// signal handlers (ICP against it).
    pub(crate) fn hold(&self) -> Held<'_> {
        let guard = self.read();
        HELD.with(|held| held.borrow_mut().push(self.id()));
        Held {
            guard,
            id: self.id(),
        }
    }

    /// The map under its read lock: recursively where this thread already holds it.
    fn read(&self) -> parking_lot::RwLockReadGuard<'_, SurfaceMap> {
        if self.held_here() {
            self.inner.read_recursive()
        } else {
            self.inner.read()
        }
    }

    /// A `RuntimeError` where this thread holds the map for reading (a signal handler
    /// run by ICP against it): its write lock would wait forever.
    fn check_writable(&self) -> PyResult<()> {
        if self.held_here() {
            return Err(pyo3::exceptions::PyRuntimeError::new_err(
                "the surface map is being read by ICP on this thread (e.g. in a signal handler it runs): \
                 change it after the ICP returns",
            ));
        }
        Ok(())
    }
}

#[pymethods]
impl PySurfaceMap {
    #[new]
    #[pyo3(signature = (resolution=0.01, *, prob_hit=0.7, clamping_max=0.971, similar=0.25, position_memory=None))]
    fn new(
        resolution: f64,
        prob_hit: f64,
        clamping_max: f64,
        similar: f64,
        position_memory: Option<i128>,
    ) -> PyResult<Self> {
        // The leaves count their points in 16 bits.
        let position_memory = position_memory
            .map(|n| {
                u16::try_from(n).map_err(|_| {
                    pyo3::exceptions::PyValueError::new_err(format!(
                        "position_memory must be 1 to 65535 points (or None for the paper's blend), got {}",
                        earcore_core::geometry::fmt_num(n as f64)
                    ))
                })
            })
            .transpose()?;
        let params = SurfaceParams {
            prob_hit,
            clamping_max,
            similar,
            position_memory,
        };
        Ok(PySurfaceMap {
            inner: RwLock::new(SurfaceMap::new(resolution, params).py()?),
        })
    }

    #[getter]
    fn resolution(&self, py: Python<'_>) -> f64 {
        py.detach(|| self.read().resolution())
    }

    /// Insert end points (N, 3) and propagate positions and normals up the tree;
    /// returns the number of leaves touched. With `sensor_origin` and `beam_spacing`
    /// (radians between neighbouring scan lines, e.g. 2° for a 16-line lidar over 30°)
    /// each point's leaf is the smallest node spanning the gap between scan lines at
    /// its range, at most `max_leaf_size` metres (NOctoSLAM's dynamic leaf depth).
    #[pyo3(signature = (points, sensor_origin=None, beam_spacing=None, max_leaf_size=0.32))]
    fn insert(
        &self,
        py: Python<'_>,
        points: &Bound<'_, PyAny>,
        sensor_origin: Option<&Bound<'_, PyAny>>,
        beam_spacing: Option<f64>,
        max_leaf_size: f64,
    ) -> PyResult<usize> {
        self.check_writable()?;
        let sensor_origin = sensor_origin
            .map(|o| crate::convert::vector3(o, "sensor_origin"))
            .transpose()?;
        let pts = self::points(points, "points")?;
        let slice = pts.as_slice()?;
        py.detach(|| {
            let depths = match (sensor_origin, beam_spacing) {
                (None, None) => None,
                (Some(o), Some(b)) => Some(self.read().leaf_depths(slice, o, b, max_leaf_size)?),
                _ => {
                    return Err(earcore_core::Error::InvalidArgument(
                        "dynamic leaf depth needs both sensor_origin and beam_spacing".into(),
                    ))
                }
            };
            self.inner
                .write()
                .insert_at_depths(slice, depths.as_deref())
        })
        .py()
    }

    /// Nodes at `depth` (16 = the finest level; None = every node), or only the
    /// leaves (nodes without children, at any depth): positions (M, 3), normals
    /// (M, 3, NaN where a node has none) and depths (M,).
    #[pyo3(signature = (depth=None, *, leaves_only=false))]
    fn nodes<'py>(
        &self,
        py: Python<'py>,
        depth: Option<u32>,
        leaves_only: bool,
    ) -> PyResult<SurfaceNodes<'py>> {
        if depth.is_some_and(|d| d > 16) {
            return Err(pyo3::exceptions::PyValueError::new_err(
                "depth must be between 0 and 16",
            ));
        }
        let (p, n, d) = py.detach(|| {
            let map = self.read();
            let (mut p, mut n, mut d) = (Vec::new(), Vec::new(), Vec::new());
            map.for_each_node(depth, |s| {
                if leaves_only && !s.leaf {
                    return;
                }
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

    /// NOctoSLAM's association for each query point (N, 3): the paired position (M, 3)
    /// and normal, and the depth of the node that gave the position; NaN rows and
    /// depth 0 where no node with a normal lies on the point's branch.
    fn associate<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'_, PyAny>,
    ) -> PyResult<SurfaceNodes<'py>> {
        let pts = self::points(points, "points")?;
        let slice = pts.as_slice()?;
        let (p, n, d) = py.detach(|| {
            let map = self.read();
            let mut cursor = earcore_core::octree::Descent::default();
            let (mut p, mut n, mut d) = (Vec::new(), Vec::new(), Vec::new());
            for &q in slice {
                match map.associate_from(q, &mut cursor) {
                    Some((pos, normal, depth)) => {
                        p.push(pos);
                        n.push(normal);
                        d.push(depth as u8);
                    }
                    None => {
                        p.push([f64::NAN; 3]);
                        n.push([f64::NAN; 3]);
                        d.push(0);
                    }
                }
            }
            (p, n, d)
        });
        Ok((
            rows_to_array(py, p)?,
            rows_to_array(py, n)?,
            vec_to_array(py, d),
        ))
    }

    /// Number of nodes.
    fn size(&self, py: Python<'_>) -> usize {
        py.detach(|| self.read().size())
    }

    fn __len__(&self, py: Python<'_>) -> usize {
        self.size(py)
    }

    fn memory_usage(&self, py: Python<'_>) -> usize {
        py.detach(|| self.read().memory_usage())
    }

    /// A surface map has no file format to pickle through; say so rather than fail
    /// with pickle's generic message.
    fn __reduce__(&self) -> PyResult<()> {
        Err(pyo3::exceptions::PyTypeError::new_err(
            "earcore.SurfaceMap cannot be pickled (it has no serialised form): rebuild it \
             in the other process by inserting the same points",
        ))
    }

    fn __repr__(&self, py: Python<'_>) -> String {
        py.detach(|| {
            let map = self.read();
            format!(
                "SurfaceMap(resolution={}, nodes={})",
                map.resolution(),
                map.size()
            )
        })
    }
}
