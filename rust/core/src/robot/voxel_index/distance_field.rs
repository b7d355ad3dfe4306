//! The Euclidean distance transform of the occupied cells: for every cell, the
//! occupied cell whose centre is nearest its centre.

use super::{CellField, VoxelIndex, NONE};

impl VoxelIndex {
    /// Distance transform (Felzenszwalb & Huttenlocher, separable, with the nearest
    /// site carried along): exact Euclidean distances between cell centres.
    pub fn compute_distance_field(&mut self) {
        let n = self.occupied.len();
        let mut sq: Vec<f64> = self
            .occupied
            .iter()
            .map(|&o| if o { 0.0 } else { f64::INFINITY })
            .collect();
        let mut site: Vec<u32> = (0..n)
            .map(|i| if self.occupied[i] { i as u32 } else { NONE })
            .collect();
        let longest = self.dims.into_iter().max().unwrap_or(0);
        let mut line_f = vec![0.0; longest];
        let mut line_s = vec![NONE; longest];
        let mut out_f = vec![0.0; longest];
        let mut out_s = vec![NONE; longest];
        let mut v = vec![0usize; longest];
        let mut z = vec![0.0f64; longest + 1];
        for axis in 0..3 {
            for (start, stride, len) in self.lines(axis) {
                for q in 0..len {
                    line_f[q] = sq[start + q * stride];
                    line_s[q] = site[start + q * stride];
                }
                distance_transform_1d(
                    &line_f[..len],
                    &line_s[..len],
                    &mut out_f[..len],
                    &mut out_s[..len],
                    &mut v,
                    &mut z,
                );
                for q in 0..len {
                    sq[start + q * stride] = out_f[q];
                    site[start + q * stride] = out_s[q];
                }
            }
        }
        let from_centre = self.windowed_box_distance(0.5);
        let from_cell = self.windowed_box_distance(1.0);
        self.field = (0..n)
            .map(|i| CellField {
                nearest: site[i],
                box_distance: from_centre[i],
                cell_distance: from_cell[i],
            })
            .collect();
    }

    /// The grid's lines along `axis` as (first cell, stride, length): the separable
    /// passes of the distance fields run along each in turn.
    pub(super) fn lines(&self, axis: usize) -> impl Iterator<Item = (usize, usize, usize)> + '_ {
        let strides = [1, self.dims[0], self.dims[0] * self.dims[1]];
        let others: Vec<usize> = (0..3).filter(|&a| a != axis).collect();
        let (a, b) = (others[0], others[1]);
        (0..self.dims[b]).flat_map(move |j| {
            (0..self.dims[a]).map(move |i| {
                (
                    i * strides[a] + j * strides[b],
                    strides[axis],
                    self.dims[axis],
                )
            })
        })
    }
}

/// Lower envelope of parabolas (q − v)² + f(v) over the sites with finite f; writes
/// the squared distance and the nearest site's label for every q.
fn distance_transform_1d(
    f: &[f64],
    label: &[u32],
    d: &mut [f64],
    out_label: &mut [u32],
    v: &mut [usize],
    z: &mut [f64],
) {
    let n = f.len();
    let Some(first) = f.iter().position(|x| x.is_finite()) else {
        d.fill(f64::INFINITY);
        out_label.fill(NONE);
        return;
    };
    let mut k = 0usize;
    v[0] = first;
    z[0] = f64::NEG_INFINITY;
    z[1] = f64::INFINITY;
    for q in first + 1..n {
        if !f[q].is_finite() {
            continue;
        }
        let fq = f[q] + (q * q) as f64;
        loop {
            let p = v[k];
            let s = (fq - (f[p] + (p * p) as f64)) / (2.0 * (q as f64 - p as f64));
            if s <= z[k] {
                // k > 0 here: z[0] = -∞ is never ≥ s.
                k -= 1;
                continue;
            }
            k += 1;
            v[k] = q;
            z[k] = s;
            z[k + 1] = f64::INFINITY;
            break;
        }
    }
    k = 0;
    for q in 0..n {
        while z[k + 1] < q as f64 {
            k += 1;
        }
        let p = v[k];
        let dq = q as f64 - p as f64;
        d[q] = dq * dq + f[p];
        out_label[q] = label[p];
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::random_index;
    use crate::synthetic::Rng;

    #[test]
    fn distance_field_matches_brute_force() {
        let mut rng = Rng::new(5);
        let index = random_index(&mut rng, 0.1, 12);
        let occupied = index.occupied_centers();
        for i in 0..index.occupied.len() {
            let c = index.center_of(i);
            let brute = occupied
                .iter()
                .map(|o| crate::geometry::distance_squared(o, &c).sqrt())
                .fold(f64::INFINITY, f64::min);
            let near = index.center_of(index.field[i].nearest as usize);
            assert!((crate::geometry::distance_squared(&near, &c).sqrt() - brute).abs() < 1e-9);
        }
    }
}
