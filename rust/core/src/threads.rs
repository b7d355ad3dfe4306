//! How many threads the core's parallel loops use.
//!
//! One process-wide setting: `set_num_threads(1)` runs everything on the calling
//! thread (the single-core figures in the benchmarks), `0` means all cores.

use std::sync::atomic::{AtomicUsize, Ordering};

static NUM_THREADS: AtomicUsize = AtomicUsize::new(0);
static CORES: std::sync::OnceLock<usize> = std::sync::OnceLock::new();

#[cfg(feature = "parallel")]
static POOL: std::sync::Mutex<Option<(usize, std::sync::Arc<rayon::ThreadPool>)>> =
    std::sync::Mutex::new(None);

/// Most worker threads that may be asked for: far beyond any machine's cores, far
/// below the thousands whose spawning took minutes.
pub const MAX_THREADS: usize = 1024;

/// Set the number of worker threads (0 = one per core; more than [`MAX_THREADS`] is
/// taken as that many: the bindings reject such values before they get here).
pub fn set_num_threads(n: usize) {
    NUM_THREADS.store(n.min(MAX_THREADS), Ordering::Relaxed);
}

/// Threads that parallel loops will use now.
pub fn num_threads() -> usize {
    match NUM_THREADS.load(Ordering::Relaxed) {
        // available_parallelism() reads cgroup files on Linux (~30 µs): ask once.
        0 => *CORES.get_or_init(|| {
            std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1)
        }),
        n => n,
    }
}

/// Map `f` over `parts` (in parallel when more than one thread is allowed) and
/// return the results in order.
pub fn map_parts<T: Sync, R: Send>(parts: &[T], f: impl Fn(&T) -> R + Sync + Send) -> Vec<R> {
    let n = num_threads();
    if n <= 1 || parts.len() <= 1 {
        return parts.iter().map(f).collect();
    }
    #[cfg(feature = "parallel")]
    {
        use rayon::prelude::*;
        let pool = {
            let mut guard = POOL.lock().unwrap_or_else(|e| e.into_inner());
            match guard.as_ref() {
                Some((size, pool)) if *size == n => pool.clone(),
                _ => match rayon::ThreadPoolBuilder::new().num_threads(n).build() {
                    Ok(pool) => {
                        let pool = std::sync::Arc::new(pool);
                        *guard = Some((n, pool.clone()));
                        pool
                    }
                    // No threads to be had: run on the caller's thread.
                    Err(_) => return parts.iter().map(f).collect(),
                },
            }
        };
        pool.install(|| parts.par_iter().map(f).collect())
    }
    #[cfg(not(feature = "parallel"))]
    {
        parts.iter().map(f).collect()
    }
}
