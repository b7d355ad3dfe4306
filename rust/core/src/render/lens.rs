//! Resampling an image where a lens's pixels land in it: each output pixel reads the
//! source at a fractional position (its undistorted ray, projected by the render's
//! pinhole). Colour is bilinear; labels are the nearest sample's; depth interpolates
//! inverse depth (affine across a plane's image, so planes stay exact) where the four
//! neighbours are one surface and takes the nearest sample at edges and holes.

use crate::{Error, Result};

/// Where each output pixel samples the source, prepared once for many frames.
#[derive(Debug, Clone)]
pub struct PixelMap {
    source: (usize, usize),
    /// Source index of the nearest sample, per output pixel.
    nearest: Vec<u32>,
    /// Source index of the top-left of the four neighbours, per output pixel.
    corner: Vec<u32>,
    /// Fractions across the four neighbours (x, y), per output pixel.
    fraction: Vec<[f64; 2]>,
}

impl PixelMap {
    /// A map for a `source` image of (width, height) pixels from the positions
    /// `(u, v)` (source pixel coordinates, centres at integers) of each output pixel;
    /// positions outside the source are clamped to its border.
    pub fn new(source: (usize, usize), u: &[f64], v: &[f64]) -> Result<Self> {
        let (w, h) = source;
        if w < 2 || h < 2 || w.saturating_mul(h) > u32::MAX as usize {
            return Err(Error::InvalidArgument(format!(
                "the source must be at least 2×2 pixels, got {w}×{h}"
            )));
        }
        if u.len() != v.len() {
            return Err(Error::InvalidArgument(format!(
                "{} u positions for {} v positions",
                u.len(),
                v.len()
            )));
        }
        if u.iter().chain(v).any(|x| !x.is_finite()) {
            return Err(Error::InvalidArgument(
                "pixel positions must be finite".into(),
            ));
        }
        let (wf, hf) = (w as f64, h as f64);
        let mut map = PixelMap {
            source,
            nearest: Vec::with_capacity(u.len()),
            corner: Vec::with_capacity(u.len()),
            fraction: Vec::with_capacity(u.len()),
        };
        for (&x, &y) in u.iter().zip(v) {
            let nx = x.round_ties_even().clamp(0.0, wf - 1.0) as usize;
            let ny = y.round_ties_even().clamp(0.0, hf - 1.0) as usize;
            map.nearest.push((ny * w + nx) as u32);
            // Clamped just inside the last pixel so the four neighbours exist.
            let (cx, cy) = (x.clamp(0.0, wf - 1.001), y.clamp(0.0, hf - 1.001));
            let (x0, y0) = (cx.floor(), cy.floor());
            map.corner.push((y0 as usize * w + x0 as usize) as u32);
            map.fraction.push([cx - x0, cy - y0]);
        }
        Ok(map)
    }

    /// The number of output pixels.
    pub fn len(&self) -> usize {
        self.nearest.len()
    }

    /// Whether the map has no output pixels.
    pub fn is_empty(&self) -> bool {
        self.nearest.is_empty()
    }

    fn check(&self, len: usize, channels: usize) -> Result<()> {
        if channels == 0 {
            return Err(Error::InvalidArgument(
                "an image needs at least one channel".into(),
            ));
        }
        let expected = self.source.0 * self.source.1 * channels;
        if len != expected {
            return Err(Error::InvalidArgument(format!(
                "the map reads a {}×{} image of {channels} channel(s) ({expected} values), got {len}",
                self.source.0, self.source.1
            )));
        }
        Ok(())
    }

    /// The four neighbours' source indices and bilinear weights of output pixel `i`.
    fn quad(&self, i: usize) -> ([usize; 4], [f64; 4]) {
        let c = self.corner[i] as usize;
        let w = self.source.0;
        let [fu, fv] = self.fraction[i];
        (
            [c, c + 1, c + w, c + w + 1],
            [
                (1.0 - fu) * (1.0 - fv),
                fu * (1.0 - fv),
                (1.0 - fu) * fv,
                fu * fv,
            ],
        )
    }
}

/// Bilinear resampling of an 8-bit image with `channels` interleaved channels.
pub fn remap_bilinear(image: &[u8], channels: usize, map: &PixelMap) -> Result<Vec<u8>> {
    map.check(image.len(), channels)?;
    let w = map.source.0;
    let mut out = vec![0u8; map.len() * channels];
    for (i, pixel) in out.chunks_exact_mut(channels).enumerate() {
        let c = map.corner[i] as usize;
        let [fu, fv] = map.fraction[i];
        let (top, bottom) = (c * channels, (c + w) * channels);
        for (ch, value) in pixel.iter_mut().enumerate() {
            let s = |at: usize| image[at + ch] as f64;
            let upper = s(top) + fu * (s(top + channels) - s(top));
            let lower = s(bottom) + fu * (s(bottom + channels) - s(bottom));
            *value = (upper + fv * (lower - upper))
                .round_ties_even()
                .clamp(0.0, 255.0) as u8;
        }
    }
    Ok(out)
}

/// Nearest-sample resampling (labels, or anything never blended).
pub fn remap_nearest<T: Copy>(image: &[T], map: &PixelMap) -> Result<Vec<T>> {
    map.check(image.len(), 1)?;
    Ok(map.nearest.iter().map(|&i| image[i as usize]).collect())
}

/// Depth resampling: inverse depth interpolated where the four neighbours are valid
/// (> 0) and within `edge` of each other, the nearest sample elsewhere.
pub fn remap_depth(depth: &[f64], map: &PixelMap, edge: f64) -> Result<Vec<f64>> {
    map.check(depth.len(), 1)?;
    let mut out = Vec::with_capacity(map.len());
    for i in 0..map.len() {
        let (q, wts) = map.quad(i);
        let z = q.map(|k| depth[k]);
        let lo = z.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = z.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        // NaN counts as no return (min / max would skip it).
        let valid = z.iter().all(|v| *v > 0.0);
        out.push(if valid && hi - lo < edge {
            1.0 / (0..4).map(|k| wts[k] / z[k]).sum::<f64>()
        } else {
            depth[map.nearest[i] as usize]
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identity_positions_give_the_image_back() {
        let (w, h) = (5, 4);
        let u: Vec<f64> = (0..w * h).map(|i| (i % w) as f64).collect();
        let v: Vec<f64> = (0..w * h).map(|i| (i / w) as f64).collect();
        let map = PixelMap::new((w, h), &u, &v).unwrap();
        let image: Vec<u8> = (0..w * h * 3).map(|i| (i * 7 % 256) as u8).collect();
        // The last column and row sit at 0.999 across: within rounding of the pixel.
        assert_eq!(remap_bilinear(&image, 3, &map).unwrap(), image);
        let labels: Vec<i64> = (0..(w * h) as i64).collect();
        assert_eq!(remap_nearest(&labels, &map).unwrap(), labels);
    }

    #[test]
    fn depth_of_a_plane_stays_exact_and_edges_take_the_nearest_sample() {
        // 1/z affine in the image: a plane.
        let (w, h) = (6, 5);
        let inv = |x: f64, y: f64| 0.5 + 0.01 * x - 0.02 * y;
        let depth: Vec<f64> = (0..w * h)
            .map(|i| 1.0 / inv((i % w) as f64, (i / w) as f64))
            .collect();
        let (u, v) = (vec![1.25, 3.5, 2.0], vec![2.75, 0.5, 3.0]);
        let map = PixelMap::new((w, h), &u, &v).unwrap();
        let out = remap_depth(&depth, &map, 1.0).unwrap();
        for k in 0..3 {
            assert!((out[k] - 1.0 / inv(u[k], v[k])).abs() < 1e-12);
        }
        // A hole among the neighbours: the nearest sample (round half to even).
        let mut holed = depth.clone();
        holed[2 * w + 1] = 0.0;
        let out = remap_depth(&holed, &map, 1.0).unwrap();
        assert_eq!(out[0], holed[3 * w + 1]);
        // A sample beside an edge rounds to the nearest pixel: (3.5, 0.5) -> (4, 0).
        let tight = remap_depth(&depth, &map, 1e-9).unwrap();
        assert_eq!(tight[1], depth[4]);
    }

    #[test]
    fn wrong_sizes_are_refused() {
        let map = PixelMap::new((4, 4), &[1.0], &[1.0]).unwrap();
        assert!(remap_bilinear(&[0; 15], 1, &map).is_err());
        assert!(remap_depth(&[1.0; 17], &map, 0.02).is_err());
        assert!(PixelMap::new((4, 4), &[f64::NAN], &[1.0]).is_err());
        assert!(PixelMap::new((1, 4), &[0.0], &[1.0]).is_err());
    }
}
