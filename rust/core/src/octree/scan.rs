//! Inserting point clouds: OctoMap's `insertPointCloud` (rays from a sensor origin,
//! free cells along them, occupied end cells) with the same cells and values, done
//! as one sorted batch.

use super::key::OcTreeKey;
use super::occupancy::{KeyUpdate, OcTree};
use super::ray::{compute_ray_keys, walk_ray, Point3f};
use super::volume::KeyVolume;
use crate::error::{Error, Result};
use crate::threads;

/// What one insertion did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct InsertReport {
    /// Points (rays) integrated, after `discretize` merged duplicates.
    pub rays: usize,
    /// Cells updated as free.
    pub free_cells: usize,
    /// Cells updated as occupied.
    pub occupied_cells: usize,
}

impl OcTree {
    /// Integrate one scan taken from `origin` (all in metres, map frame).
    ///
    /// Every ray marks the cells it crosses free (its end cell excluded) and its end
    /// cell occupied; a cell both free and occupied in one scan counts as occupied;
    /// each cell is updated once. Rays longer than `max_range` are cut there and mark
    /// no hit. With `discretize`, points falling in the same cell are merged into one
    /// ray to the cell's centre. The whole input is checked before the tree changes.
    pub fn insert_point_cloud(
        &mut self,
        points: &[[f64; 3]],
        origin: [f64; 3],
        max_range: Option<f64>,
        discretize: bool,
    ) -> Result<InsertReport> {
        let (origin, points) = self.checked_scan(points, origin, max_range)?;
        let rays = if discretize { self.discretized(&points) } else { points };
        let volume = self.trace(&rays, origin, max_range);
        let mut updates: Vec<KeyUpdate> = Vec::new();
        let mut hits = Vec::new();
        let (hit, miss) = (self.lo.hit, self.lo.miss);
        volume.for_each_sorted(|code, is_hit| {
            updates.push((code, if is_hit { hit } else { miss }));
            if is_hit {
                hits.push(code);
            }
        });
        self.danger.record_hits(hits.iter().copied());
        if !self.danger.is_empty() {
            self.danger.record_seen_free(|code| volume.is_free(OcTreeKey::from_morton(code)));
        }
        self.apply_sorted_updates(&updates);
        Ok(InsertReport { rays: rays.len(), free_cells: updates.len() - hits.len(), occupied_cells: hits.len() })
    }

    /// Validate a scan and convert it to OctoMap's float points.
    fn checked_scan(&self, points: &[[f64; 3]], origin: [f64; 3], max_range: Option<f64>) -> Result<(Point3f, Vec<Point3f>)> {
        if let Some(r) = max_range {
            if !(r.is_finite() && r > 0.0) {
                return Err(Error::InvalidArgument(format!("max_range must be a positive distance in metres, got {r}")));
            }
        }
        if points.is_empty() {
            return Err(Error::InvalidArgument(
                "points is empty: a scan needs at least one point (skip frames without valid depth)".into(),
            ));
        }
        let origin32 = to_f32(origin);
        self.key_of("sensor origin", origin)?;
        if self.conv.coord_to_key_checked(origin32).is_none() {
            return Err(self.out_of_bounds("sensor origin", origin));
        }
        let mut out = Vec::with_capacity(points.len());
        for (i, &p) in points.iter().enumerate() {
            if !p.iter().all(|c| c.is_finite()) {
                return Err(Error::InvalidArgument(format!("point {i} {p:?} is not finite")));
            }
            let p32 = to_f32(p);
            if self.conv.coord_to_key_checked(p32).is_none() {
                return Err(self.out_of_bounds(if i == 0 { "point 0" } else { "a point" }, p));
            }
            out.push(p32);
        }
        Ok((origin32, out))
    }

    fn out_of_bounds(&self, what: &'static str, point: [f64; 3]) -> Error {
        Error::OutOfBounds { what, point, limit: self.conv.metric_limits().1 }
    }

    /// OctoMap's `computeDiscreteUpdate`: one ray per distinct end cell, to its centre.
    fn discretized(&self, points: &[Point3f]) -> Vec<Point3f> {
        let mut codes: Vec<u64> =
            points.iter().filter_map(|&p| self.conv.coord_to_key_checked(p)).map(OcTreeKey::morton).collect();
        codes.sort_unstable();
        codes.dedup();
        codes.into_iter().map(|m| self.conv.key_to_point(OcTreeKey::from_morton(m))).collect()
    }

    /// Mark the cells of every ray (OctoMap's `computeUpdate`), split over threads.
    fn trace(&self, points: &[Point3f], origin: Point3f, max_range: Option<f64>) -> KeyVolume {
        const PARTS_PER_THREAD: usize = 4;
        let parts = (threads::num_threads() * PARTS_PER_THREAD).max(1);
        let chunk = points.len().div_ceil(parts).max(1024);
        let chunks: Vec<&[Point3f]> = points.chunks(chunk).collect();
        let conv = &self.conv;
        let (lo, hi) = key_bounds(conv, origin, points);
        let volumes = threads::map_parts(&chunks, |part| {
            let mut volume = KeyVolume::with_bounds(lo, hi);
            for &p in part.iter() {
                trace_ray(conv, origin, p, max_range, &mut volume);
            }
            volume
        });
        volumes.into_iter().reduce(KeyVolume::merge).unwrap_or_default()
    }
}

/// Key box holding the origin and every point, one cell wider on each side (a ray's
/// cells lie between its end cells, give or take rounding).
fn key_bounds(conv: &super::key::KeyConverter, origin: Point3f, points: &[Point3f]) -> (OcTreeKey, OcTreeKey) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for p in points.iter().chain(std::iter::once(&origin)) {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    // Points were validated, so both corners map to keys; clamp the widened box.
    let key = |p: Point3f| conv.coord_to_key_checked(p).unwrap_or_default();
    let (klo, khi) = (key(lo), key(hi));
    (OcTreeKey(klo.0.map(|k| k.saturating_sub(1))), OcTreeKey(khi.0.map(|k| k.saturating_add(1))))
}

/// One ray of `computeUpdate`, float arithmetic as in OctoMap.
#[inline]
fn trace_ray(conv: &super::key::KeyConverter, origin: Point3f, p: Point3f, max_range: Option<f64>, volume: &mut KeyVolume) {
    let within = match max_range {
        None => true,
        Some(r) => super::ray::norm(super::ray::sub(p, origin)) <= r,
    };
    let end = if within {
        p
    } else {
        let r = max_range.unwrap_or(f64::INFINITY);
        super::ray::point_at(origin, super::ray::normalized(super::ray::sub(p, origin)), r as f32)
    };
    mark_ray_free(conv, origin, end, volume);
    if within {
        if let Some(k) = conv.coord_to_key_checked(p) {
            volume.mark_occupied(k);
        }
    }
}

/// Mark the free cells of one ray: through the dense box when every cell fits in it
/// (the fast path), else cell by cell through the general store.
#[inline]
fn mark_ray_free(conv: &super::key::KeyConverter, origin: Point3f, end: Point3f, volume: &mut KeyVolume) {
    if let Some(mut dense) = volume.dense_marker() {
        walk_ray(conv, origin, end, &mut dense);
        if !dense.outside {
            return;
        }
    }
    // Marking is idempotent, so cells the fast path already marked may be marked again.
    compute_ray_keys(conv, origin, end, |k| volume.mark_free(k));
}

#[inline]
fn to_f32(p: [f64; 3]) -> Point3f {
    [p[0] as f32, p[1] as f32, p[2] as f32]
}
