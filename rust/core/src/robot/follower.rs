//! The trajectory follower: the control law that turns a timed motion into joint
//! velocity commands, and its roll-out from a moving start (Python:
//! `earcore.planning.follower`, which samples the motion and calls these).
//!
//! Feed-forward of the reference's velocity plus a feedback on the position error that
//! never asks for more speed than can be braked away before the error closes
//! (√(2·a·|e|)): no overshoot when the reference changes abruptly. Commands stay within
//! the speed limit and change by at most the acceleration limit per step. The roll-out
//! is what lets the executive check a new plan's way on before it switches: the arm's
//! velocity across the new path is braked away first, off the path.

use crate::error::{Error, Result};

/// Limits and gain of a follower, one limit per joint.
#[derive(Clone, Debug)]
pub struct Follower {
    max_velocity: Vec<f64>,
    max_acceleration: Vec<f64>,
    /// Position feedback gain (1/s).
    gain: f64,
}

/// The states a follower passes through from its start, one per step (row-major,
/// `steps + 1` rows of `dof`), until it is back on its motion or the reference ran out.
#[derive(Clone, Debug, PartialEq)]
pub struct Rollout {
    /// The states, row-major: `steps + 1` rows of `dof` joint positions.
    pub states: Vec<f64>,
    /// Whether the follower got back on its motion.
    pub rejoined: bool,
    /// Steps taken.
    pub steps: usize,
    /// Largest joint distance between a state and the reference then (rad).
    pub largest_error: f64,
}

fn finite(values: &[f64], name: &str) -> Result<()> {
    if values.iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(Error::InvalidArgument(format!("{name} must be finite")))
    }
}

fn sized(values: &[f64], dof: usize, name: &str) -> Result<()> {
    if values.len() != dof {
        return Err(Error::InvalidArgument(format!(
            "{name} has {} values for {dof} joints",
            values.len()
        )));
    }
    finite(values, name)
}

impl Follower {
    /// A follower with per-joint limits (rad/s, rad/s²) and position feedback `gain`
    /// (1/s). Errors unless the limits are one per joint, finite and positive, and the
    /// gain finite and ≥ 0.
    pub fn new(max_velocity: Vec<f64>, max_acceleration: Vec<f64>, gain: f64) -> Result<Self> {
        let positive = |v: &[f64]| v.iter().all(|x| x.is_finite() && *x > 0.0);
        if max_velocity.len() != max_acceleration.len() || max_velocity.is_empty() {
            return Err(Error::InvalidArgument(format!(
                "one velocity and one acceleration limit per joint, got {} and {}",
                max_velocity.len(),
                max_acceleration.len()
            )));
        }
        if !positive(&max_velocity) || !positive(&max_acceleration) {
            return Err(Error::InvalidArgument(
                "velocity and acceleration limits must be finite and > 0".into(),
            ));
        }
        if !(gain.is_finite() && gain >= 0.0) {
            return Err(Error::InvalidArgument(format!(
                "the feedback gain must be finite and >= 0, got {gain}"
            )));
        }
        Ok(Self {
            max_velocity,
            max_acceleration,
            gain,
        })
    }

    /// Number of joints.
    pub fn dof(&self) -> usize {
        self.max_velocity.len()
    }

    /// One step's command into `out`, unchecked (callers check once).
    fn step(
        &self,
        q: &[f64],
        last: &[f64],
        reference: Option<(&[f64], &[f64])>,
        dt: f64,
        out: &mut [f64],
    ) {
        for j in 0..out.len() {
            let (v, a) = (self.max_velocity[j], self.max_acceleration[j]);
            let desired = match reference {
                Some((now, ahead)) => {
                    let error = now[j] - q[j];
                    let bounded = (self.gain * error.abs()).min((2.0 * a * error.abs()).sqrt());
                    let sign = if error > 0.0 {
                        1.0
                    } else if error < 0.0 {
                        -1.0
                    } else {
                        0.0
                    };
                    (ahead[j] - now[j]) / dt + sign * bounded
                }
                None => 0.0,
            };
            let step = a * dt;
            out[j] = desired
                .max(last[j] - step)
                .min(last[j] + step)
                .max(-v)
                .min(v);
        }
    }

    /// The next velocity command from position `q` and the last command, tracking the
    /// reference at `now` and one step `ahead`; no reference: stop (every joint brakes at
    /// its limit).
    pub fn command(
        &self,
        q: &[f64],
        last: &[f64],
        reference: Option<(&[f64], &[f64])>,
        dt: f64,
    ) -> Result<Vec<f64>> {
        self.check_state(q, last, dt)?;
        if let Some((now, ahead)) = reference {
            sized(now, self.dof(), "the reference")?;
            sized(ahead, self.dof(), "the reference ahead")?;
        }
        let mut out = vec![0.0; self.dof()];
        self.step(q, last, reference, dt, &mut out);
        Ok(out)
    }

    /// The robot's state (position, last command) and the step, as `step` needs them.
    fn check_state(&self, q: &[f64], last: &[f64], dt: f64) -> Result<()> {
        sized(q, self.dof(), "q")?;
        sized(last, self.dof(), "the last command")?;
        if !(dt.is_finite() && dt > 0.0) {
            return Err(Error::InvalidArgument(format!(
                "dt must be finite and > 0, got {dt}"
            )));
        }
        Ok(())
    }

    /// Follow the `reference` (row-major, one row per step from the start, at least 3
    /// rows) from `q` moving at `command`, as the cell integrates it: q ← clamp(q +
    /// command·dt, lower, upper). Back on the motion ("rejoined"): every joint within
    /// `tolerance` of the reference and its command within one step's acceleration of
    /// the reference's next velocity (without the velocity condition an arm crossing
    /// the reference at speed would count as on it). Runs `rows - 2` steps at most.
    #[allow(clippy::too_many_arguments)]
    pub fn rollout(
        &self,
        reference: &[f64],
        q: &[f64],
        command: &[f64],
        dt: f64,
        lower: &[f64],
        upper: &[f64],
        tolerance: f64,
    ) -> Result<Rollout> {
        let dof = self.dof();
        if !reference.len().is_multiple_of(dof) || reference.len() < 3 * dof {
            return Err(Error::InvalidArgument(format!(
                "the reference must be at least 3 rows of {dof} joint values, got {} values",
                reference.len()
            )));
        }
        finite(reference, "the reference")?;
        self.check_state(q, command, dt)?;
        let mut q = q.to_vec();
        let mut command = command.to_vec();
        sized(lower, dof, "the lower joint limits")?;
        sized(upper, dof, "the upper joint limits")?;
        if tolerance.is_nan() {
            return Err(Error::InvalidArgument(
                "the tolerance must be a number".into(),
            ));
        }
        if let Some(j) =
            (0..dof).find(|&j| lower[j].is_nan() || upper[j].is_nan() || lower[j] > upper[j])
        {
            return Err(Error::InvalidArgument(format!(
                "joint {j}'s limits are not an interval: [{}, {}]",
                lower[j], upper[j]
            )));
        }
        let row = |k: usize| &reference[k * dof..(k + 1) * dof];
        let steps = reference.len() / dof - 2;
        let mut states = Vec::with_capacity((steps + 1) * dof);
        states.extend_from_slice(&q);
        let mut largest = (0..dof)
            .map(|j| (row(0)[j] - q[j]).abs())
            .fold(0.0, f64::max);
        let mut next = vec![0.0; dof];
        for k in 0..steps {
            self.step(&q, &command, Some((row(k), row(k + 1))), dt, &mut next);
            command.copy_from_slice(&next);
            let mut error = 0.0f64;
            let mut matched = true;
            for j in 0..dof {
                q[j] = (q[j] + command[j] * dt).max(lower[j]).min(upper[j]);
                error = error.max((row(k + 1)[j] - q[j]).abs());
                let velocity = (row(k + 2)[j] - row(k + 1)[j]) / dt;
                matched &= (command[j] - velocity).abs() <= self.max_acceleration[j] * dt;
            }
            states.extend_from_slice(&q);
            largest = largest.max(error);
            if error < tolerance && matched {
                return Ok(Rollout {
                    states,
                    rejoined: true,
                    steps: k + 1,
                    largest_error: largest,
                });
            }
        }
        Ok(Rollout {
            states,
            rejoined: false,
            steps,
            largest_error: largest,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ur5_like() -> Follower {
        Follower::new(vec![1.57; 6], vec![1.8; 6], 8.0).unwrap()
    }

    #[test]
    fn commands_stay_within_the_limits_and_brake_without_a_reference() {
        let f = ur5_like();
        let dt = 1.0 / 30.0;
        let mut seed = 7u64;
        let mut rand = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        for _ in 0..500 {
            let q: Vec<f64> = (0..6).map(|_| 3.0 * rand()).collect();
            let now: Vec<f64> = (0..6).map(|_| 3.0 * rand()).collect();
            let ahead: Vec<f64> = now.iter().map(|x| x + 0.1 * rand()).collect();
            let last: Vec<f64> = (0..6).map(|_| 1.57 * rand()).collect();
            let c = f.command(&q, &last, Some((&now, &ahead)), dt).unwrap();
            for j in 0..6 {
                assert!(c[j].abs() <= 1.57 + 1e-12);
                assert!((c[j] - last[j]).abs() <= 1.8 * dt + 1e-12);
            }
        }
        let last = [1.0, -0.5, 0.03, 0.0, -0.06, 0.2];
        let c = f.command(&[0.0; 6], &last, None, dt).unwrap();
        for j in 0..6 {
            let want = last[j].signum() * (last[j].abs() - 1.8 * dt).max(0.0);
            assert!((c[j] - want).abs() < 1e-15, "{j}: {} vs {want}", c[j]);
        }
    }

    #[test]
    fn a_still_reference_from_rest_is_held_and_a_still_arm_rejoins_at_once() {
        let f = ur5_like();
        let q = [0.1, -1.0, 1.0, 0.0, 0.5, 0.0];
        let reference: Vec<f64> = (0..5).flat_map(|_| q).collect();
        let r = f
            .rollout(&reference, &q, &[0.0; 6], 0.1, &[-7.0; 6], &[7.0; 6], 1e-3)
            .unwrap();
        assert!(r.rejoined && r.steps == 1 && r.largest_error == 0.0);
        assert_eq!(&r.states[6..], &q);
    }

    #[test]
    fn a_moving_arm_brakes_onto_a_still_reference_and_comes_back() {
        // One joint at 1 rad/s, the reference resting where it is: the arm runs on
        // v²/2a = 0.28 rad (less the discrete steps' share), comes back and stops.
        let f = Follower::new(vec![2.0], vec![1.8], 8.0).unwrap();
        let reference = vec![0.0; 200];
        let brake = |upper: f64| {
            f.rollout(
                &reference,
                &[0.0],
                &[1.0],
                1.0 / 30.0,
                &[-1.0],
                &[upper],
                1e-3,
            )
            .unwrap()
        };
        let r = brake(1.0);
        assert!(r.rejoined);
        let peak = r.states.iter().cloned().fold(f64::MIN, f64::max);
        assert!(
            peak > 0.2 && peak <= 1.0 / (2.0 * 1.8) + 1.0 / 30.0,
            "peak {peak}"
        );
        // Past the reference only by what 30 Hz steps add (0.011 rad here).
        assert!(
            r.states.iter().all(|x| *x >= -0.015),
            "swung past the reference"
        );
        // A joint limit stops it there, as the cell clamps it.
        let r = brake(0.1);
        assert!(r.states.iter().all(|x| *x <= 0.1));
        assert!(r.states.contains(&0.1));
    }

    #[test]
    fn bad_input_is_an_error() {
        let f = ur5_like();
        let q = [0.0; 6];
        assert!(Follower::new(vec![1.0], vec![0.0], 8.0).is_err());
        assert!(Follower::new(vec![1.0, 1.0], vec![1.0], 8.0).is_err());
        assert!(Follower::new(vec![1.0], vec![1.0], f64::NAN).is_err());
        assert!(f.command(&q, &[f64::NAN; 6], None, 0.1).is_err());
        assert!(f.command(&q, &q, None, 0.0).is_err());
        assert!(f.command(&q[..5], &q, None, 0.1).is_err());
        let short = vec![0.0; 12];
        assert!(f
            .rollout(&short, &q, &q, 0.1, &[-1.0; 6], &[1.0; 6], 1e-3)
            .is_err());
        let mut bad = vec![0.0; 18];
        bad[4] = f64::INFINITY;
        assert!(f
            .rollout(&bad, &q, &q, 0.1, &[-1.0; 6], &[1.0; 6], 1e-3)
            .is_err());
    }
}
