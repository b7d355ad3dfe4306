//! Inserting point clouds: OctoMap's `insertPointCloud` (rays from a sensor origin,
//! free cells along them, occupied end cells) with the same cells and values, done
//! as one sorted batch.

use super::key::KeyConverter;
use super::key::OcTreeKey;
use super::occupancy::{KeyUpdate, OcTree};
use super::ray::{
    compute_ray_keys, norm, normalized, plan_ray, point_at, sub, walk_from, Point3f, RayPlan,
};
use super::volume::KeyVolume;
use crate::error::{Error, Result};
use crate::geometry::{fmt_num, fmt_point};
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

/// A scan's rays traced into the cells they update (OctoMap's `computeUpdate`), for
/// trees of one resolution: [`trace_scan`] makes it without touching a tree,
/// [`OcTree::apply_scan`] updates a tree with it.
pub struct TracedScan {
    volume: KeyVolume,
    rays: usize,
    resolution: f64,
}

/// Trace one scan taken from `origin` (all in metres, map frame) for trees whose keys
/// `conv` gives: every ray marks the cells it crosses free (its end cell excluded) and,
/// with `hits`, its end cell occupied; a cell both free and occupied in one scan counts
/// as occupied. Rays longer than `max_range` are cut there and mark no hit. With
/// `discretize`, points falling in the same cell are merged into one ray to the cell's
/// centre. The whole input is checked first. Asks `interrupt` on the calling thread
/// between rounds of rays (about every tenth of a second); `Ok(None)` when it asked to
/// stop.
pub fn trace_scan(
    conv: &KeyConverter,
    points: &[[f64; 3]],
    origin: [f64; 3],
    max_range: Option<f64>,
    discretize: bool,
    hits: bool,
    interrupt: &mut threads::Interrupt<'_>,
) -> Result<Option<TracedScan>> {
    let scan = Scan {
        points,
        origin,
        max_range,
        discretize,
        hits,
    };
    trace_scan_in_rounds(conv, scan, ROUND, interrupt)
}

/// A scan to trace: [`trace_scan`]'s arguments.
#[derive(Clone, Copy)]
struct Scan<'a> {
    points: &'a [[f64; 3]],
    origin: [f64; 3],
    max_range: Option<f64>,
    discretize: bool,
    hits: bool,
}

/// [`trace_scan`] with rounds of `round`.
fn trace_scan_in_rounds(
    conv: &KeyConverter,
    Scan {
        points,
        origin,
        max_range,
        discretize,
        hits,
    }: Scan<'_>,
    round: std::time::Duration,
    interrupt: &mut threads::Interrupt<'_>,
) -> Result<Option<TracedScan>> {
    let (origin, bounds) = checked_scan(conv, points, origin, max_range, discretize)?;
    let centres;
    let rays = if discretize {
        centres = discretized(conv, points);
        &centres
    } else {
        points
    };
    let traced = trace(
        conv, rays, origin, bounds, max_range, hits, round, interrupt,
    );
    Ok(traced.map(|volume| TracedScan {
        volume,
        rays: rays.len(),
        resolution: conv.resolution(),
    }))
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
        self.insert_whole(Scan {
            points,
            origin,
            max_range,
            discretize,
            hits: true,
        })
    }

    /// Like `insert_point_cloud`, but the rays only clear space: every cell a ray
    /// crosses is marked free (its end cell excluded), no end cell is hit. For points
    /// known not to be obstacles (e.g. on a support surface the map models otherwise),
    /// whose rays still show what lies in front of them is empty.
    pub fn insert_free_rays(
        &mut self,
        points: &[[f64; 3]],
        origin: [f64; 3],
        max_range: Option<f64>,
    ) -> Result<InsertReport> {
        self.insert_whole(Scan {
            points,
            origin,
            max_range,
            discretize: false,
            hits: false,
        })
    }

    /// Trace `scan` with no one to stop it and apply it.
    fn insert_whole(&mut self, scan: Scan<'_>) -> Result<InsertReport> {
        let traced = trace_scan_in_rounds(&self.conv, scan, ROUND, &mut || false)?;
        // Never asked to stop, so always traced.
        self.apply_scan(
            traced.ok_or_else(|| Error::InvalidArgument("the scan was interrupted".into()))?,
        )
    }

    /// Update the tree with a scan [`trace_scan`] traced for its resolution: each
    /// cell once, as `insert_point_cloud` does. Errors, leaving the tree as it was, for
    /// a scan traced for another resolution.
    pub fn apply_scan(&mut self, scan: TracedScan) -> Result<InsertReport> {
        if scan.resolution.to_bits() != self.conv.resolution().to_bits() {
            return Err(Error::InvalidArgument(format!(
                "the scan was traced for a map of {} m cells, this map's are {} m",
                fmt_num(scan.resolution),
                fmt_num(self.conv.resolution())
            )));
        }
        let volume = scan.volume;
        let mut updates: Vec<KeyUpdate> = Vec::with_capacity(volume.marked_bound());
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
            self.danger
                .record_seen_free(|code| volume.is_free(OcTreeKey::from_morton(code)));
        }
        self.apply_sorted_updates(&updates);
        Ok(InsertReport {
            rays: scan.rays,
            free_cells: updates.len() - hits.len(),
            occupied_cells: hits.len(),
        })
    }
}

/// Validate a scan; returns the sensor origin as OctoMap's float point and the key
/// box of the scan (`key_bounds`). A point off the map is accepted where `max_range`
/// cuts its ray on the map (OctoMap never keys such a point), unless the scan is to be
/// `discretize`d, which keys every point.
fn checked_scan(
    conv: &KeyConverter,
    points: &[[f64; 3]],
    origin: [f64; 3],
    max_range: Option<f64>,
    discretize: bool,
) -> Result<(Point3f, (OcTreeKey, OcTreeKey))> {
    if let Some(r) = max_range {
        if !(r.is_finite() && r > 0.0) {
            return Err(Error::InvalidArgument(format!(
                "max_range must be a positive distance in metres, got {}",
                fmt_num(r)
            )));
        }
    }
    if points.is_empty() {
        return Err(Error::InvalidArgument(
            "points is empty: a scan needs at least one point (skip frames without valid depth)"
                .into(),
        ));
    }
    let origin32 = to_f32(origin);
    conv.checked_key("sensor origin", origin)?;
    if conv.coord_to_key_checked(origin32).is_none() {
        return Err(conv.out_of_bounds("sensor origin", origin));
    }
    // One pass that vectorises (no early exit) tests every point and takes the
    // scan's bounds; the loop below only names the first bad point.
    let mut lo = origin32;
    let mut hi = origin32;
    let mut ok = true;
    for &p in points {
        let p = to_f32(p);
        ok &= conv.has_key(p);
        for a in 0..3 {
            // Comparisons, not `f32::min`, so that the loop vectorises (a NaN
            // fails `has_key` anyway).
            lo[a] = if p[a] < lo[a] { p[a] } else { lo[a] };
            hi[a] = if p[a] > hi[a] { p[a] } else { hi[a] };
        }
    }
    if ok {
        return Ok((origin32, key_bounds(conv, lo, hi)));
    }
    // Some point is off the map or not finite: name the first that matters, and take
    // the box of the rays' ends instead.
    let (mut lo, mut hi) = (origin32, origin32);
    for (i, &p) in points.iter().enumerate() {
        if !p.iter().all(|c| c.is_finite()) {
            return Err(Error::InvalidArgument(format!(
                "point {i} {} is not finite",
                fmt_point(&p)
            )));
        }
        // (A ray too long for float arithmetic has no direction to cut it along.)
        let long = !norm(sub(to_f32(p), origin32)).is_finite();
        let end = match max_range {
            Some(r) if !discretize => cut_at_range(origin32, to_f32(p), r).unwrap_or(to_f32(p)),
            _ => to_f32(p),
        };
        if long || !conv.has_key(end) {
            return Err(conv.out_of_bounds(if i == 0 { "point 0" } else { "a point" }, p));
        }
        for a in 0..3 {
            lo[a] = lo[a].min(end[a]);
            hi[a] = hi[a].max(end[a]);
        }
    }
    Ok((origin32, key_bounds(conv, lo, hi)))
}

/// Where a ray from `origin` to `p` ends when it is longer than `max_range`: cut there
/// (OctoMap's float arithmetic); `None` when it is not.
#[inline]
fn cut_at_range(origin: Point3f, p: Point3f, max_range: f64) -> Option<Point3f> {
    (norm(sub(p, origin)) > max_range)
        .then(|| point_at(origin, normalized(sub(p, origin)), max_range as f32))
}

/// OctoMap's `computeDiscreteUpdate`: one ray per distinct end cell, to its centre
/// (a float point, widened without loss). The cells are those of the scan, so its
/// key box still holds.
fn discretized(conv: &KeyConverter, points: &[[f64; 3]]) -> Vec<[f64; 3]> {
    let mut codes: Vec<u64> = points
        .iter()
        .filter_map(|&p| conv.coord_to_key_checked(to_f32(p)))
        .map(OcTreeKey::morton)
        .collect();
    codes.sort_unstable();
    codes.dedup();
    codes
        .into_iter()
        .map(|m| conv.key_to_point(OcTreeKey::from_morton(m)).map(f64::from))
        .collect()
}

/// How long a round of [`trace_scan`] runs before `interrupt` is asked, give or take
/// one chunk of rays a thread.
const ROUND: std::time::Duration = std::time::Duration::from_millis(100);

/// Rays per chunk: a chunk's buffers (float points, keys, lanes) stay in the cache
/// (4096 and 8192 ran alike).
const CHUNK: usize = 8192;

/// What one thread's share of a scan has traced so far.
struct TracePart {
    volume: KeyVolume,
    scratch: TraceScratch,
    /// Its chunks traced (the part's `k`-th chunk is the scan's `part + k × parts`).
    done: usize,
}

/// Mark the cells of every ray (OctoMap's `computeUpdate`), split over threads,
/// asking `interrupt` between rounds of `round` (give or take a chunk); `None` when it
/// asked to stop.
#[allow(clippy::too_many_arguments)]
fn trace(
    conv: &KeyConverter,
    points: &[[f64; 3]],
    origin: Point3f,
    (lo, hi): (OcTreeKey, OcTreeKey),
    max_range: Option<f64>,
    hits: bool,
    round: std::time::Duration,
    interrupt: &mut threads::Interrupt<'_>,
) -> Option<KeyVolume> {
    // One volume per thread (each covers the whole scan's box, so fewer is cheaper to
    // zero and merge); threads take interleaved chunks of the image rows, which
    // balances long and short rays between them. In a round each thread traces its
    // next chunks until `round` has passed; camera frames take one. Which thread
    // traces a chunk never changes, and the volumes are merged in order: the results
    // do not depend on the rounds.
    let chunks: Vec<&[[f64; 3]]> = points.chunks(CHUNK).collect();
    let count = threads::num_threads().clamp(1, chunks.len().max(1));
    let parts: Vec<std::sync::Mutex<TracePart>> = (0..count)
        .map(|_| {
            std::sync::Mutex::new(TracePart {
                volume: KeyVolume::with_bounds(lo, hi),
                scratch: TraceScratch::default(),
                done: 0,
            })
        })
        .collect();
    let indices: Vec<usize> = (0..count).collect();
    let left = |part: usize, done: usize| part + done * count < chunks.len();
    loop {
        let start = std::time::Instant::now();
        threads::map_parts(&indices, |&part| {
            // Each part's state is locked by one thread only: never contended.
            let mut state = parts[part].lock().unwrap_or_else(|e| e.into_inner());
            let TracePart {
                volume,
                scratch,
                done,
            } = &mut *state;
            while left(part, *done) {
                let chunk = chunks[part + *done * count];
                trace_part(conv, origin, chunk, max_range, hits, volume, scratch);
                *done += 1;
                if start.elapsed() >= round {
                    break;
                }
            }
        });
        let finished = parts.iter().enumerate().all(|(part, state)| {
            let state = state.lock().unwrap_or_else(|e| e.into_inner());
            !left(part, state.done)
        });
        if finished {
            break;
        }
        if interrupt() {
            return None;
        }
    }
    let volumes = threads::map_parts(&parts, |state| {
        let mut state = state.lock().unwrap_or_else(|e| e.into_inner());
        let mut volume = std::mem::take(&mut state.volume);
        volume.settle();
        volume
    });
    volumes.into_iter().reduce(KeyVolume::merge)
}

/// Key box of the metric box `[lo, hi]` (which holds the origin and every point), one
/// cell wider on each side (a ray's cells lie between its end cells, give or take
/// rounding).
fn key_bounds(conv: &KeyConverter, lo: Point3f, hi: Point3f) -> (OcTreeKey, OcTreeKey) {
    // Points were validated, so both corners map to keys; clamp the widened box.
    let key = |p: Point3f| conv.coord_to_key_checked(p).unwrap_or_default();
    let (klo, khi) = (key(lo), key(hi));
    (
        OcTreeKey(klo.0.map(|k| k.saturating_sub(1))),
        OcTreeKey(khi.0.map(|k| k.saturating_add(1))),
    )
}

/// Buffers `trace_part` reuses from chunk to chunk (fresh ones cost page faults).
#[derive(Default)]
struct TraceScratch {
    /// The part's points as OctoMap's float points; where each ray ends (cut at the
    /// maximum range), and the end's key.
    points: Vec<Point3f>,
    ends: Vec<Point3f>,
    /// With a maximum range: whether each ray ends at its point (not cut, so a hit).
    within: Vec<bool>,
    end_keys: Vec<Option<OcTreeKey>>,
}

/// The rays of one part of a scan (OctoMap's `computeUpdate`, float arithmetic as in
/// OctoMap): end cells marked occupied (unless `hits` is false), then every ray's
/// cells marked free.
fn trace_part(
    conv: &KeyConverter,
    origin: Point3f,
    raw: &[[f64; 3]],
    max_range: Option<f64>,
    hits: bool,
    volume: &mut KeyVolume,
    scratch: &mut TraceScratch,
) {
    let TraceScratch {
        points,
        ends,
        within,
        end_keys,
    } = scratch;
    // Converted part by part, so that the float points stay in the cache.
    points.clear();
    points.extend(raw.iter().map(|&p| to_f32(p)));
    let points: &[Point3f] = points;
    // Rays beyond `max_range` end there and mark no hit; within it they end at their
    // point (the common case needs no copy).
    let ends: &[Point3f] = match max_range {
        None => points,
        Some(r) => {
            ends.clear();
            within.clear();
            for &p in points {
                let end = cut_at_range(origin, p, r);
                ends.push(end.unwrap_or(p));
                within.push(end.is_none());
            }
            ends
        }
    };
    end_keys.clear();
    match max_range {
        // The scan was checked: every point has a key.
        None => end_keys.extend(ends.iter().map(|&p| Some(conv.key_of_checked_point(p)))),
        Some(_) => end_keys.extend(ends.iter().map(|&p| conv.coord_to_key_checked(p))),
    }
    if hits {
        let within = |i: usize| max_range.is_none() || within[i];
        volume.mark_all_occupied(
            end_keys
                .iter()
                .enumerate()
                .filter_map(|(i, k)| k.filter(|_| within(i))),
        );
    }
    // The batched walk takes the rays it can; the scalar walk does the rest. Rays with
    // a cell outside the dense box (rounding at its edge, or no box at all) are redone
    // through the general store; marking twice is harmless.
    let rest = volume.walk_rays(conv, origin, ends, end_keys);
    let mut redo: Vec<usize> = Vec::new();
    match volume.dense_marker() {
        Some(mut dense) => {
            for i in rest {
                if let RayPlan::Walk(start) = plan_ray(conv, origin, ends[i]) {
                    dense.outside = false;
                    walk_from(&start, &mut dense);
                    if dense.outside {
                        redo.push(i);
                    }
                }
            }
        }
        None => redo = rest,
    }
    for i in redo {
        compute_ray_keys(conv, origin, ends[i], |k| volume.mark_free(k));
    }
}

#[inline]
fn to_f32(p: [f64; 3]) -> Point3f {
    [p[0] as f32, p[1] as f32, p[2] as f32]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::Rng;
    use std::collections::BTreeSet;

    /// `n` points scattered over a box in front of the origin (0, 0, 1).
    fn scan(n: usize, seed: u64) -> Vec<[f64; 3]> {
        let mut rng = Rng::new(seed);
        (0..n)
            .map(|_| {
                [
                    rng.uniform(-2.0, 2.0),
                    rng.uniform(1.0, 3.0),
                    rng.uniform(0.0, 2.0),
                ]
            })
            .collect()
    }

    #[test]
    fn a_scan_traced_in_rounds_is_the_scan_traced_at_once() {
        let origin = [0.0, 0.0, 1.0];
        // Rounds of no time: each thread traces one chunk a round.
        let in_rounds = |conv: &KeyConverter,
                         points: &[[f64; 3]],
                         hits: bool,
                         stop: &mut threads::Interrupt<'_>| {
            let scan = Scan {
                points,
                origin,
                max_range: None,
                discretize: false,
                hits,
            };
            trace_scan_in_rounds(conv, scan, std::time::Duration::ZERO, stop).unwrap()
        };
        for threads in [1, 2] {
            threads::set_local_num_threads(Some(threads));
            let mut tree = OcTree::new(0.1).unwrap();
            tree.insert_point_cloud(&scan(5_000, 1), origin, None, false)
                .unwrap();
            // 5 chunks of 8192 rays a thread and one more: 6 rounds, asked after 5.
            let points = scan(threads * 5 * 8192 + 100, 2);
            let conv = *tree.key_converter();
            // Stopped at the first or the second question: nothing traced is returned.
            for (hits, stop_at) in [(true, 1), (true, 2), (false, 2)] {
                let mut asked = 0;
                let traced = in_rounds(&conv, &points, hits, &mut || {
                    asked += 1;
                    asked == stop_at
                });
                assert!(traced.is_none());
                assert_eq!(asked, stop_at);
            }
            // Never stopped: asked after every round but the last, and applied, the same
            // map as the plain insertion's.
            let mut plain = tree.clone();
            let expected = plain
                .insert_point_cloud(&points, origin, None, false)
                .unwrap();
            let mut asked = 0;
            let traced = in_rounds(&conv, &points, true, &mut || {
                asked += 1;
                false
            })
            .unwrap();
            assert_eq!(asked, 5);
            // The cells are the union of the chunks' traced one by one (a cell hit in any
            // of them occupied).
            let (mut occupied, mut free) = (BTreeSet::new(), BTreeSet::new());
            for piece in points.chunks(8192) {
                let one = trace_scan(&conv, piece, origin, None, false, true, &mut || false)
                    .unwrap()
                    .unwrap();
                one.volume.for_each_sorted(|code, hit| {
                    if hit {
                        occupied.insert(code)
                    } else {
                        free.insert(code)
                    };
                });
            }
            let free: BTreeSet<u64> = free.difference(&occupied).copied().collect();
            let (mut got_occupied, mut got_free) = (BTreeSet::new(), BTreeSet::new());
            traced.volume.for_each_sorted(|code, hit| {
                if hit {
                    got_occupied.insert(code)
                } else {
                    got_free.insert(code)
                };
            });
            assert!(
                got_occupied == occupied && got_free == free,
                "{threads} threads"
            );
            assert_eq!(tree.apply_scan(traced).unwrap(), expected);
            assert!(tree.write_state_bytes() == plain.write_state_bytes());
            // A scan traced for another resolution is refused, the tree unchanged.
            let other = OcTree::new(0.05).unwrap();
            let traced = trace_scan(
                other.key_converter(),
                &points,
                origin,
                None,
                false,
                true,
                &mut || false,
            )
            .unwrap()
            .unwrap();
            let before = tree.write_state_bytes();
            let error = tree.apply_scan(traced).unwrap_err().to_string();
            assert!(
                error.contains("0.05 m cells") && error.contains("0.1 m"),
                "{error}"
            );
            assert!(tree.write_state_bytes() == before);
            threads::set_local_num_threads(None);
        }
    }
}
