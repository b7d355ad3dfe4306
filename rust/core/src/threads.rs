//! How many threads the core's parallel loops use.
//!
//! One process-wide setting: `set_num_threads(1)` runs everything on the calling
//! thread (the single-core figures in the benchmarks), `0` means all cores. A thread
//! may override it for the work it starts itself (`set_local_num_threads`), e.g. a
//! reflex that must not wait for the pool while a map update uses every core.

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

thread_local! {
    static LOCAL_NUM_THREADS: std::cell::Cell<Option<usize>> = const { std::cell::Cell::new(None) };
}

/// Override the number of worker threads for parallel loops started on the calling
/// thread only (`Some(0)` = one per core, capped at [`MAX_THREADS`] like the global
/// setting); `None` removes the override, so the global setting applies again.
/// Returns the previous override. Other threads and the global setting are unaffected.
pub fn set_local_num_threads(n: Option<usize>) -> Option<usize> {
    LOCAL_NUM_THREADS.with(|local| local.replace(n.map(|n| n.min(MAX_THREADS))))
}

/// The calling thread's override (see [`set_local_num_threads`]), if any.
pub fn local_num_threads() -> Option<usize> {
    LOCAL_NUM_THREADS.with(|local| local.get())
}

/// Threads that parallel loops started on the calling thread will use now: its
/// override if it has one, else the global setting.
pub fn num_threads() -> usize {
    let setting = local_num_threads().unwrap_or_else(|| NUM_THREADS.load(Ordering::Relaxed));
    match setting {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_local_override_stays_on_its_thread() {
        let before = num_threads();
        assert_eq!(set_local_num_threads(Some(1)), None);
        assert_eq!(num_threads(), 1);
        // Another thread sees the global setting.
        let other = std::thread::spawn(num_threads).join().unwrap();
        assert_eq!(other, before);
        assert_eq!(set_local_num_threads(Some(3)), Some(1));
        assert_eq!(num_threads(), 3);
        assert_eq!(set_local_num_threads(Some(MAX_THREADS + 5)), Some(3));
        assert_eq!(num_threads(), MAX_THREADS);
        assert_eq!(set_local_num_threads(None), Some(MAX_THREADS));
        assert_eq!(num_threads(), before);
        // The parallel map still returns results in order under an override.
        set_local_num_threads(Some(1));
        let parts: Vec<u32> = (0..10).collect();
        assert_eq!(
            map_parts(&parts, |x| x * 2),
            (0..10).map(|x| x * 2).collect::<Vec<_>>()
        );
        set_local_num_threads(None);
    }
}
