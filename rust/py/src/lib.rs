//! Python bindings: this file only wires the modules together.

mod cloud;
mod convert;
mod errors;
mod follower;
mod icp;
mod interrupt;
mod octree;
mod render;
mod robot;
mod surface;
mod synthetic;

use pyo3::prelude::*;

/// Number of threads earcore's parallel loops use (0 = one per core).
#[pyfunction]
fn set_num_threads(n: i64) -> PyResult<()> {
    let max = earcore_core::threads::MAX_THREADS;
    match usize::try_from(n) {
        Ok(n) if n <= max => {
            earcore_core::threads::set_num_threads(n);
            Ok(())
        }
        _ => Err(pyo3::exceptions::PyValueError::new_err(format!(
            "num_threads must be 0 (one per core) to {max}, got {n}"
        ))),
    }
}

/// Override the thread count for earcore work started on the calling thread only
/// (0 = one per core; None removes the override); returns the previous override.
#[pyfunction]
fn set_local_num_threads(n: Option<i64>) -> PyResult<Option<usize>> {
    let max = earcore_core::threads::MAX_THREADS;
    let n = match n {
        None => None,
        Some(n) => match usize::try_from(n) {
            Ok(n) if n <= max => Some(n),
            _ => {
                return Err(pyo3::exceptions::PyValueError::new_err(format!(
                    "num_threads must be 0 (one per core) to {max} or None, got {n}"
                )))
            }
        },
    };
    Ok(earcore_core::threads::set_local_num_threads(n))
}

/// Threads earcore's parallel loops started on this thread use now (its local
/// override if set, else the global setting).
#[pyfunction]
fn get_num_threads() -> usize {
    earcore_core::threads::num_threads()
}

/// Take the core's pool lock before `os.fork`, so no other thread holds it at the
/// instant of the fork.
#[pyfunction]
fn _before_fork() {
    earcore_core::threads::before_fork();
}

/// Release the pool lock in the parent after `os.fork`.
#[pyfunction]
fn _after_fork_in_parent() {
    earcore_core::threads::after_fork_in_parent();
}

/// In a forked child: forget the parent's pool (its threads are not here; the next
/// parallel call builds one) and release the lock.
#[pyfunction]
fn _after_fork_in_child() {
    earcore_core::threads::after_fork_in_child();
}

#[pymodule]
fn _earcore(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    // The danger a voxel is reset to when hit (Eq. 1), as the map stores it (float32).
    m.add(
        "DANGER_ON_HIT",
        f64::from(earcore_core::octree::DANGER_ON_HIT),
    )?;
    m.add_class::<octree::PyOcTree>()?;
    m.add_class::<octree::PyInsertReport>()?;
    m.add_class::<octree::PyFrameReport>()?;
    m.add_class::<surface::PySurfaceMap>()?;
    m.add_class::<robot::PyRobotModel>()?;
    m.add_class::<follower::PyFollower>()?;
    m.add_function(wrap_pyfunction!(robot::fit_body, m)?)?;
    m.add_class::<icp::PyPlaneTarget>()?;
    m.add_class::<render::PyRasterizer>()?;
    m.add_class::<render::PyPixelMap>()?;
    m.add_class::<icp::PyIcpResult>()?;
    m.add("EarcoreError", py.get_type::<errors::EarcoreError>())?;
    m.add("OutOfMapError", py.get_type::<errors::OutOfMapError>())?;
    m.add("MapFormatError", py.get_type::<errors::MapFormatError>())?;
    m.add_function(wrap_pyfunction!(set_num_threads, m)?)?;
    m.add_function(wrap_pyfunction!(get_num_threads, m)?)?;
    m.add_function(wrap_pyfunction!(set_local_num_threads, m)?)?;
    // Registered with os.fork, not exported: a forked child then builds its own pool.
    let hooks = pyo3::types::PyDict::new(py);
    hooks.set_item("before", wrap_pyfunction!(_before_fork, m)?)?;
    hooks.set_item(
        "after_in_parent",
        wrap_pyfunction!(_after_fork_in_parent, m)?,
    )?;
    hooks.set_item("after_in_child", wrap_pyfunction!(_after_fork_in_child, m)?)?;
    py.import("os")?
        .call_method("register_at_fork", (), Some(&hooks))?;
    m.add_function(wrap_pyfunction!(cloud::voxel_codes, m)?)?;
    m.add_function(wrap_pyfunction!(cloud::voxel_means, m)?)?;
    m.add_function(wrap_pyfunction!(synthetic::render_depth_points, m)?)?;
    m.add_function(wrap_pyfunction!(synthetic::benchmark_frame, m)?)?;
    m.add_function(wrap_pyfunction!(synthetic::robot_cell_voxels, m)?)?;
    m.add_function(wrap_pyfunction!(synthetic::render_lidar_scan, m)?)?;
    m.add_function(wrap_pyfunction!(cloud::depth_to_points_raw, m)?)?;
    m.add_function(wrap_pyfunction!(cloud::incidence_cosines, m)?)?;
    m.add_function(wrap_pyfunction!(cloud::crop_raw, m)?)?;
    m.add_function(wrap_pyfunction!(cloud::statistical_outlier_indices, m)?)?;
    m.add_function(wrap_pyfunction!(cloud::voxel_downsample_raw, m)?)?;
    m.add_function(wrap_pyfunction!(cloud::estimate_normals, m)?)?;
    m.add_function(wrap_pyfunction!(cloud::cluster_points, m)?)?;
    m.add_function(wrap_pyfunction!(cloud::rigid_fit, m)?)?;
    m.add_function(wrap_pyfunction!(cloud::checked_rigid_transform, m)?)?;
    m.add_function(wrap_pyfunction!(cloud::rigid_fit_ransac, m)?)?;
    m.add_function(wrap_pyfunction!(icp::icp_point_to_plane_raw, m)?)?;
    Ok(())
}
