//! `earcore._earcore.Rasterizer` and `PixelMap` (`earcore_core::render`), wrapped by
//! `earcore.render`: the simulated cameras' images.

use earcore_core::render::{self, Light, Mesh, Pinhole, Rasterizer};
use numpy::ndarray::{Array2, Array3};
use numpy::{
    IntoPyArray, PyArray2, PyArray3, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::convert::{contiguous_slice, numbers, points, shaped};
use crate::errors::IntoPyResult;

/// (rgb (H, W, 3) uint8, depth (H, W) float64, label (H, W) int64).
type Images<'py> = (
    Bound<'py, PyArray3<u8>>,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<i64>>,
);

#[pyclass(name = "Rasterizer", module = "earcore._earcore", frozen)]
pub struct PyRasterizer {
    inner: Rasterizer,
}

#[pymethods]
impl PyRasterizer {
    /// `meshes`: a sequence of (vertices (N, 3), triangles (M, 3) ints, rgb (3,) in
    /// [0, 1], label int).
    #[new]
    fn new(meshes: &Bound<'_, PyAny>) -> PyResult<Self> {
        let mut inner = Rasterizer::new();
        for (k, item) in meshes.try_iter()?.enumerate() {
            let item = item?;
            let (vertices, triangles, rgb, label): (
                Bound<'_, PyAny>,
                Bound<'_, PyAny>,
                Bound<'_, PyAny>,
                i64,
            ) = item.extract().map_err(|_| {
                PyValueError::new_err(format!(
                    "mesh {k} must be (vertices, triangles, rgb, label)"
                ))
            })?;
            let v = points(&vertices, "vertices")?;
            let idx = triangle_indices(&triangles, k)?;
            let c = numbers(&rgb, "rgb")?;
            let rgb: [f64; 3] = c.try_into().map_err(|_| {
                PyValueError::new_err(format!("mesh {k}: rgb must be three numbers"))
            })?;
            inner
                .add_mesh(Mesh {
                    vertices: v.as_slice()?.to_vec(),
                    triangles: idx,
                    rgb,
                    label,
                })
                .map_err(|e| PyValueError::new_err(format!("mesh {k}: {e}")))?;
        }
        Ok(Self { inner })
    }

    fn __len__(&self) -> usize {
        self.inner.len()
    }

    /// Draws the meshes placed by `camera_from_mesh` (M, 4, 4); rows of `hidden` (M,)
    /// that are true are skipped.
    #[pyo3(signature = (camera_from_mesh, hidden, fx, fy, cx, cy, width, height, near, far, light, ambient, diffuse, background))]
    #[allow(clippy::too_many_arguments)]
    fn render<'py>(
        &self,
        py: Python<'py>,
        camera_from_mesh: PyReadonlyArray3<'py, f64>,
        hidden: Vec<bool>,
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
        width: usize,
        height: usize,
        near: f64,
        far: f64,
        light: [f64; 3],
        ambient: f64,
        diffuse: f64,
        background: [u8; 3],
    ) -> PyResult<Images<'py>> {
        let shape = camera_from_mesh.shape();
        if shape[1] != 4 || shape[2] != 4 || hidden.len() != shape[0] {
            return Err(PyValueError::new_err(format!(
                "camera_from_mesh must be (M, 4, 4) with one hidden flag per mesh, got {:?} and {} flags",
                shape,
                hidden.len()
            )));
        }
        let values = camera_from_mesh.as_array();
        let poses: Vec<Option<[[f64; 4]; 4]>> = (0..shape[0])
            .map(|k| {
                (!hidden[k])
                    .then(|| std::array::from_fn(|i| std::array::from_fn(|j| values[[k, i, j]])))
            })
            .collect();
        let camera = Pinhole {
            fx,
            fy,
            cx,
            cy,
            width,
            height,
            near,
            far,
        };
        let light = Light {
            direction: light,
            ambient,
            diffuse,
        };
        let out = py
            .detach(|| self.inner.render(&poses, &camera, &light, background))
            .py()?;
        let rgb = shaped(Array3::from_shape_vec((height, width, 3), out.rgb))?;
        let depth = shaped(Array2::from_shape_vec((height, width), out.depth))?;
        let label = shaped(Array2::from_shape_vec((height, width), out.label))?;
        Ok((
            rgb.into_pyarray(py),
            depth.into_pyarray(py),
            label.into_pyarray(py),
        ))
    }
}

fn triangle_indices(obj: &Bound<'_, PyAny>, k: usize) -> PyResult<Vec<[u32; 3]>> {
    let np = PyModule::import(obj.py(), "numpy")?;
    let array = np.call_method1("asarray", (obj.clone(),))?;
    let shape: Vec<usize> = array.getattr("shape")?.extract()?;
    if shape.len() != 2 || shape[1] != 3 {
        return Err(PyValueError::new_err(format!(
            "mesh {k}: triangles must be (M, 3), got shape {shape:?}"
        )));
    }
    let ints = np.call_method1("ascontiguousarray", (array, np.getattr("int64")?))?;
    let ints: PyReadonlyArray2<i64> = ints.extract()?;
    ints.as_array()
        .rows()
        .into_iter()
        .map(|r| {
            let t = [r[0], r[1], r[2]];
            if t.iter().any(|&i| i < 0 || i > u32::MAX as i64) {
                Err(PyValueError::new_err(format!(
                    "mesh {k}: triangle {t:?} has a negative or too large index"
                )))
            } else {
                Ok(t.map(|i| i as u32))
            }
        })
        .collect()
}

#[pyclass(name = "PixelMap", module = "earcore._earcore", frozen)]
pub struct PyPixelMap {
    inner: render::PixelMap,
    shape: (usize, usize),
    /// (width, height) of the images it reads.
    source: (usize, usize),
}

impl PyPixelMap {
    fn check_shape(&self, shape: &[usize]) -> PyResult<()> {
        if shape[0] != self.source.1 || shape[1] != self.source.0 {
            return Err(PyValueError::new_err(format!(
                "the map reads {}×{} images (height, width = {}, {}), got shape {:?}",
                self.source.0, self.source.1, self.source.1, self.source.0, shape
            )));
        }
        Ok(())
    }
}

#[pymethods]
impl PyPixelMap {
    /// Each output pixel of `u`, `v` (H, W; source pixel coordinates) samples a
    /// `source_width` × `source_height` image.
    #[new]
    fn new(
        source_width: usize,
        source_height: usize,
        u: PyReadonlyArray2<'_, f64>,
        v: PyReadonlyArray2<'_, f64>,
    ) -> PyResult<Self> {
        if u.shape() != v.shape() {
            return Err(PyValueError::new_err(format!(
                "u and v must have one shape, got {:?} and {:?}",
                u.shape(),
                v.shape()
            )));
        }
        let shape = (u.shape()[0], u.shape()[1]);
        let (u, v) = (contiguous_slice(&u, "u")?, contiguous_slice(&v, "v")?);
        Ok(Self {
            inner: render::PixelMap::new((source_width, source_height), u, v).py()?,
            shape,
            source: (source_width, source_height),
        })
    }

    /// Bilinear resampling of an (h, w, C) uint8 image.
    fn bilinear<'py>(
        &self,
        py: Python<'py>,
        image: PyReadonlyArray3<'py, u8>,
    ) -> PyResult<Bound<'py, PyArray3<u8>>> {
        let channels = image.shape()[2];
        self.check_shape(image.shape())?;
        let data = contiguous_slice(&image, "image")?;
        let out = py
            .detach(|| render::remap_bilinear(data, channels, &self.inner))
            .py()?;
        Ok(shaped(Array3::from_shape_vec(
            (self.shape.0, self.shape.1, channels),
            out,
        ))?
        .into_pyarray(py))
    }

    /// Nearest-sample resampling of an (h, w) int64 image.
    fn nearest<'py>(
        &self,
        py: Python<'py>,
        image: PyReadonlyArray2<'py, i64>,
    ) -> PyResult<Bound<'py, PyArray2<i64>>> {
        self.check_shape(image.shape())?;
        let data = contiguous_slice(&image, "image")?;
        let out = py
            .detach(|| render::remap_nearest(data, &self.inner))
            .py()?;
        Ok(shaped(Array2::from_shape_vec(self.shape, out))?.into_pyarray(py))
    }

    /// Depth resampling of an (h, w) float64 image (0 = no return).
    fn depth<'py>(
        &self,
        py: Python<'py>,
        depth: PyReadonlyArray2<'py, f64>,
        edge: f64,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        self.check_shape(depth.shape())?;
        let data = contiguous_slice(&depth, "depth")?;
        let out = py
            .detach(|| render::remap_depth(data, &self.inner, edge))
            .py()?;
        Ok(shaped(Array2::from_shape_vec(self.shape, out))?.into_pyarray(py))
    }
}
