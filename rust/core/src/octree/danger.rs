//! Per-voxel danger (Paper II, Eq. 1): reset to 0.999 on a hit, then
//! `C ← C + ln(C)·Δt·α` each frame until it reaches 0.
//!
//! Only voxels with C > 0 are stored (the active set), so closing a frame costs
//! O(active + hits), independent of the size of the occupancy map.

use rustc_hash::{FxHashMap, FxHashSet};

use crate::error::{Error, Result};

/// Danger given to a voxel hit in the current frame (Eq. 1's reset value).
pub const DANGER_ON_HIT: f32 = 0.999;

/// When an unhit voxel decays.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum DecayMode {
    /// Only in frames where some ray saw the voxel free: occluded danger persists,
    /// as in the paper's experiment where the robot hid the inner band.
    #[default]
    Observed,
    /// Every frame, seen or not.
    Always,
}

/// Danger decay parameters (Paper I, Eq. 1).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DangerParams {
    /// Decay speed α of Eq. 1 (Table I: 0.3).
    pub alpha: f64,
    /// When an unhit voxel decays.
    pub mode: DecayMode,
}

impl Default for DangerParams {
    fn default() -> Self {
        DangerParams {
            alpha: 0.3,
            mode: DecayMode::Observed,
        }
    }
}

/// What one `end_frame` did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FrameReport {
    /// Voxels hit during the frame (now at 0.999).
    pub hit: usize,
    /// Voxels whose danger decayed.
    pub decayed: usize,
    /// Voxels that reached 0 and left the active set.
    pub cleared: usize,
    /// Voxels still dangerous after the frame.
    pub active: usize,
}

/// One explicit-Euler step of Eq. 1 with clamping at 0.
#[inline]
pub fn decay_step(c: f32, dt_alpha: f64) -> f32 {
    let c = f64::from(c);
    let next = c + c.ln() * dt_alpha;
    if next > 0.0 {
        next as f32
    } else {
        0.0
    }
}

/// Per-voxel danger: 0.999 where a voxel is hit, decaying while it is not
/// (Paper I, Eq. 1). Cells are the finest octree cells, named by Morton code.
#[derive(Clone, Debug, Default)]
pub struct DangerMap {
    params: DangerParams,
    /// Morton code of the finest cell → danger in (0, 0.999].
    active: FxHashMap<u64, f32>,
    frame_hits: FxHashSet<u64>,
    frame_seen_free: FxHashSet<u64>,
    /// Cells hit during the last closed frame, sorted (the reflexes' binary map).
    last_obstacles: Vec<u64>,
}

impl DangerMap {
    /// The decay parameters.
    pub fn params(&self) -> DangerParams {
        self.params
    }

    /// Replace the decay parameters; errors when `alpha` is negative or not finite.
    pub fn set_params(&mut self, params: DangerParams) -> Result<()> {
        if !(params.alpha.is_finite() && params.alpha >= 0.0) {
            return Err(Error::InvalidArgument(format!(
                "alpha must be finite and ≥ 0, got {}",
                crate::geometry::fmt_num(params.alpha)
            )));
        }
        self.params = params;
        Ok(())
    }

    /// Forget every cell's danger and the open frame; the parameters stay.
    pub fn clear(&mut self) {
        *self = DangerMap {
            params: self.params,
            ..DangerMap::default()
        };
    }

    /// Mark cells as hit in the current frame (their danger becomes 0.999 at once).
    pub fn record_hits(&mut self, cells: impl IntoIterator<Item = u64>) {
        for m in cells {
            self.active.insert(m, DANGER_ON_HIT);
            self.frame_hits.insert(m);
        }
    }

    /// Note which dangerous cells a scan saw free (`seen_free(code)`), for `Observed` decay.
    pub fn record_seen_free(&mut self, seen_free: impl Fn(u64) -> bool) {
        for &m in self.active.keys() {
            if seen_free(m) {
                self.frame_seen_free.insert(m);
            }
        }
    }

    /// Close a frame lasting `dt` seconds: decay every unhit active cell per the mode.
    pub fn end_frame(&mut self, dt: f64) -> Result<FrameReport> {
        if !(dt.is_finite() && dt >= 0.0) {
            return Err(Error::InvalidArgument(format!(
                "dt must be a finite, non-negative time in seconds, got {}",
                crate::geometry::fmt_num(dt)
            )));
        }
        let dt_alpha = dt * self.params.alpha;
        let mut report = FrameReport {
            hit: self.frame_hits.len(),
            ..Default::default()
        };
        let always = self.params.mode == DecayMode::Always;
        let (hits, seen) = (&self.frame_hits, &self.frame_seen_free);
        self.active.retain(|m, c| {
            if hits.contains(m) || !(always || seen.contains(m)) {
                return true;
            }
            report.decayed += 1;
            *c = decay_step(*c, dt_alpha);
            if *c > 0.0 {
                true
            } else {
                report.cleared += 1;
                false
            }
        });
        self.last_obstacles = self.frame_hits.drain().collect();
        self.last_obstacles.sort_unstable();
        self.frame_seen_free.clear();
        report.active = self.active.len();
        Ok(report)
    }

    /// Danger of the finest cell with Morton code `m` (0 when not dangerous).
    #[inline]
    pub fn value(&self, m: u64) -> f32 {
        self.active.get(&m).copied().unwrap_or(0.0)
    }

    /// Set a cell's danger directly (e.g. restoring a saved map); 0 removes it.
    pub fn set_value(&mut self, m: u64, c: f32) -> Result<()> {
        if !(c.is_finite() && (0.0..=1.0).contains(&c)) {
            return Err(Error::InvalidArgument(format!(
                "danger must lie in [0, 1], got {}",
                crate::geometry::fmt_num(f64::from(c))
            )));
        }
        if c > 0.0 {
            self.active.insert(m, c.min(DANGER_ON_HIT));
        } else {
            self.active.remove(&m);
        }
        Ok(())
    }

    /// Number of voxels with danger above 0.
    pub fn len(&self) -> usize {
        self.active.len()
    }

    /// Whether no voxel has danger.
    pub fn is_empty(&self) -> bool {
        self.active.is_empty()
    }

    /// Active cells sorted by Morton code (deterministic order for callers).
    pub fn sorted_cells(&self) -> Vec<(u64, f32)> {
        let mut v: Vec<(u64, f32)> = self.active.iter().map(|(&m, &c)| (m, c)).collect();
        v.sort_unstable_by_key(|&(m, _)| m);
        v
    }

    /// Cells hit during the last closed frame.
    pub fn current_obstacles(&self) -> &[u64] {
        &self.last_obstacles
    }

    /// Append the whole state (parameters, dangerous cells, the open frame's hits and
    /// free sightings, the last frame's obstacles) to `out`, sets in sorted order.
    pub(crate) fn write_state(&self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.params.alpha.to_le_bytes());
        out.push(match self.params.mode {
            DecayMode::Observed => 0,
            DecayMode::Always => 1,
        });
        let cells = self.sorted_cells();
        out.extend_from_slice(&(cells.len() as u64).to_le_bytes());
        for (m, c) in cells {
            out.extend_from_slice(&m.to_le_bytes());
            out.extend_from_slice(&c.to_le_bytes());
        }
        let sorted = |set: &FxHashSet<u64>| {
            let mut v: Vec<u64> = set.iter().copied().collect();
            v.sort_unstable();
            v
        };
        for codes in [
            sorted(&self.frame_hits),
            sorted(&self.frame_seen_free),
            self.last_obstacles.clone(),
        ] {
            out.extend_from_slice(&(codes.len() as u64).to_le_bytes());
            for m in codes {
                out.extend_from_slice(&m.to_le_bytes());
            }
        }
    }

    /// Read what `write_state` wrote, checking every value.
    pub(crate) fn read_state(r: &mut super::io::Reader<'_>) -> Result<DangerMap> {
        let bad = |what: String| Error::Format(format!("danger state: {what}"));
        let alpha = f64::from_le_bytes(r.take::<8>()?);
        let mode = match r.take::<1>()? {
            [0] => DecayMode::Observed,
            [1] => DecayMode::Always,
            _ => return Err(bad("unknown decay mode".into())),
        };
        let mut map = DangerMap::default();
        map.set_params(DangerParams { alpha, mode })
            .map_err(|e| bad(e.to_string()))?;
        // Morton codes of 16-bit keys have 48 bits.
        let code = |r: &mut super::io::Reader<'_>| {
            let m = u64::from_le_bytes(r.take::<8>()?);
            if m >> 48 == 0 {
                Ok(m)
            } else {
                Err(bad(format!("cell code {m:#x} has more than 48 bits")))
            }
        };
        let count = |r: &mut super::io::Reader<'_>| r.take::<8>().map(u64::from_le_bytes);
        for _ in 0..count(r)? {
            let m = code(r)?;
            let c = f32::from_le_bytes(r.take::<4>()?);
            if !(c > 0.0 && c <= DANGER_ON_HIT) {
                return Err(bad(format!("danger {c} outside (0, {DANGER_ON_HIT}]")));
            }
            map.active.insert(m, c);
        }
        let codes = |r: &mut super::io::Reader<'_>| -> Result<Vec<u64>> {
            (0..count(r)?).map(|_| code(r)).collect()
        };
        map.frame_hits = codes(r)?.into_iter().collect();
        map.frame_seen_free = codes(r)?.into_iter().collect();
        map.last_obstacles = codes(r)?;
        if !map.last_obstacles.is_sorted() {
            return Err(bad("last frame's obstacles are not sorted".into()));
        }
        Ok(map)
    }

    /// Bytes held by the map's tables, spare capacity included.
    pub fn memory_usage(&self) -> usize {
        (self.active.capacity() * 12)
            + (self.frame_hits.capacity() + self.frame_seen_free.capacity()) * 8
            + self.last_obstacles.capacity() * 8
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_decay_time_at_15_hz() {
        // α = 0.3, Δt = 1/15 s: explicit Euler reaches 0 after ≈ 21.4 s (digest §C.5).
        let mut c = DANGER_ON_HIT;
        let mut frames = 0;
        while c > 0.0 {
            c = decay_step(c, 0.3 / 15.0);
            frames += 1;
        }
        let seconds = frames as f64 / 15.0;
        assert!((seconds - 21.4).abs() <= 1.0 / 15.0 + 0.05, "{seconds}");
    }

    #[test]
    fn observed_mode_keeps_unseen_danger() {
        let mut d = DangerMap::default();
        d.record_hits([1, 2]);
        d.end_frame(0.1).unwrap();
        d.record_seen_free(|m| m == 1);
        d.end_frame(0.1).unwrap();
        assert!(d.value(1) < DANGER_ON_HIT);
        assert_eq!(d.value(2), DANGER_ON_HIT);
        assert_eq!(d.current_obstacles(), &[] as &[u64]);
    }
}
