//! Lower bounds on the distance from a cell to the nearest occupied voxel box, exact
//! within a window of cells around it: what the body tests read per sample.

use super::VoxelIndex;

impl VoxelIndex {
    /// Distance to the nearest occupied box within a window of `w` cells per axis:
    /// three passes of a 1D min-convolution with the per-axis gap (|n| − shift)₊²
    /// (shift ½: from the cell centre; shift 1: from the nearest point of the cell),
    /// then clamped to (w + 1 − shift)·res, below which no box outside the window comes.
    pub(super) fn windowed_box_distance(&self, shift: f64) -> Vec<f32> {
        let res = self.resolution;
        let w = ((0.25 / res).ceil() as usize).clamp(2, 8);
        let gap: Vec<f64> = (0..=w)
            .map(|n| {
                let e = (n as f64 - shift).max(0.0);
                e * e
            })
            .collect();
        let mut f: Vec<f64> = self
            .occupied
            .iter()
            .map(|&o| if o { 0.0 } else { f64::INFINITY })
            .collect();
        let mut line = vec![0.0f64; self.dims.into_iter().max().unwrap_or(0)];
        for axis in 0..3 {
            for (start, stride, len) in self.lines(axis) {
                for q in 0..len {
                    line[q] = f[start + q * stride];
                }
                if line[..len].iter().all(|v| v.is_infinite()) {
                    continue;
                }
                for q in 0..len {
                    let lo = q.saturating_sub(w);
                    let hi = (q + w).min(len - 1);
                    let mut best = f64::INFINITY;
                    for (k, v) in line[lo..=hi].iter().enumerate() {
                        let n = (lo + k).abs_diff(q);
                        best = best.min(v + gap[n]);
                    }
                    f[start + q * stride] = best;
                }
            }
        }
        let cap = (w as f64 + 1.0 - shift) * res;
        f.iter()
            .map(|&v| (v.sqrt() * res).min(cap) as f32)
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::super::body_check::point_box_distance_squared;
    use super::super::tests::random_index;
    use crate::synthetic::Rng;

    #[test]
    fn box_distance_is_a_tight_lower_bound() {
        let mut rng = Rng::new(6);
        let index = random_index(&mut rng, 0.05, 30);
        let occupied = index.occupied_centers();
        let half = index.half();
        for i in 0..index.occupied.len() {
            let c = index.center_of(i);
            let brute = occupied
                .iter()
                .map(|o| point_box_distance_squared(&c, o, &half).sqrt())
                .fold(f64::INFINITY, f64::min);
            let got = index.field[i].box_distance as f64;
            assert!(got <= brute + 1e-6, "{got} > {brute}");
            if brute < 0.25 {
                assert!((got - brute).abs() < 1e-6, "{got} vs {brute}");
            }
        }
    }
}
