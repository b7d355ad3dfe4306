//! Long core calls stop on Ctrl-C: the call runs detached from the GIL and, between
//! bounded steps, briefly re-attaches to run Python's signal handlers.

use std::time::{Duration, Instant};

use pyo3::prelude::*;

/// How often a detached call runs Python's signal handlers: well under the second
/// a user waits for Ctrl-C, far above the microseconds re-attaching costs.
const POLL: Duration = Duration::from_millis(50);

/// Run `work` detached from the GIL, handing it the check a core call asks between
/// bounded steps on this thread. At most every [`POLL`] the check re-attaches and
/// runs Python's signal handlers (they run on the main thread only); when one raises
/// (`KeyboardInterrupt` on Ctrl-C) the check tells the work to stop, and its
/// exception is returned instead of the work's result.
pub fn detach_interruptible<T, F>(py: Python<'_>, work: F) -> PyResult<T>
where
    T: Send,
    F: FnOnce(&mut earcore_core::threads::Interrupt<'_>) -> T + Send,
{
    let mut raised: Option<PyErr> = None;
    let out = py.detach(|| {
        let mut last = Instant::now();
        let mut check = || {
            if raised.is_some() {
                return true;
            }
            if last.elapsed() < POLL {
                return false;
            }
            last = Instant::now();
            match Python::attach(|py| py.check_signals()) {
                Ok(()) => false,
                Err(e) => {
                    raised = Some(e);
                    true
                }
            }
        };
        work(&mut check)
    });
    match raised {
        Some(e) => Err(e),
        None => Ok(out),
    }
}
