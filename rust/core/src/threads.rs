//! How many threads the core's parallel loops use, the pool they run on, and how a
//! long call is stopped early.
//!
//! One process-wide setting: `set_num_threads(1)` runs everything on the calling
//! thread (the single-core figures in the benchmarks), `0` means all cores. A thread
//! may override it for the work it starts itself (`set_local_num_threads`), e.g. a
//! reflex that must not wait for the pool while a map update uses every core.
//!
//! The pool is the core's own (rayon's global pool is never used) and belongs to the
//! process that built it: a forked child, which inherits the pool's state but none of
//! its threads, builds a new one on its first parallel call (see [`before_fork`]).

use std::sync::atomic::{AtomicUsize, Ordering};

static NUM_THREADS: AtomicUsize = AtomicUsize::new(0);
static CORES: std::sync::OnceLock<usize> = std::sync::OnceLock::new();

/// The pool parallel loops run on, with the process that built it.
#[cfg(feature = "parallel")]
struct Pool {
    pid: u32,
    threads: usize,
    pool: std::sync::Arc<rayon::ThreadPool>,
}

#[cfg(feature = "parallel")]
type PoolSlot = std::sync::Mutex<Option<Pool>>;

#[cfg(feature = "parallel")]
static POOL: PoolSlot = std::sync::Mutex::new(None);

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

/// The pool of `n` threads for this process, built when missing, of another size or
/// inherited from the parent of a fork; `None` when no threads can be had.
#[cfg(feature = "parallel")]
fn pool(n: usize) -> Option<std::sync::Arc<rayon::ThreadPool>> {
    let pid = std::process::id();
    let mut guard = POOL.lock().unwrap_or_else(|e| e.into_inner());
    forget_if_inherited(&mut guard, pid);
    if let Some(p) = guard.as_ref().filter(|p| p.threads == n) {
        return Some(p.pool.clone());
    }
    let pool = std::sync::Arc::new(
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .ok()?,
    );
    *guard = Some(Pool {
        pid,
        threads: n,
        pool: pool.clone(),
    });
    Some(pool)
}

/// Drop a pool built by another process (the parent of a fork) without touching it:
/// its threads do not exist here, and dropping it would signal them through locks
/// one of them may have held when the process forked.
#[cfg(feature = "parallel")]
fn forget_if_inherited(slot: &mut Option<Pool>, pid: u32) {
    if slot.as_ref().is_some_and(|p| p.pid != pid) {
        std::mem::forget(slot.take());
    }
}

#[cfg(feature = "parallel")]
thread_local! {
    /// The pool's lock, held by the forking thread from [`before_fork`] to the
    /// `after_fork_*` call on either side.
    static FORK_GUARD: std::cell::RefCell<Option<std::sync::MutexGuard<'static, Option<Pool>>>> =
        const { std::cell::RefCell::new(None) };
}

/// Call in the thread about to fork (Python's `os.register_at_fork(before=...)`):
/// takes the pool's lock so that no other thread holds it at the instant of the
/// fork, which would leave it locked for ever in the child. Follow it with
/// [`after_fork_in_parent`] in the parent and [`after_fork_in_child`] in the child.
/// Without these calls a child still builds its own pool (the pool records its
/// process), unless another thread held the lock at that instant.
pub fn before_fork() {
    #[cfg(feature = "parallel")]
    {
        let guard = POOL.lock().unwrap_or_else(|e| e.into_inner());
        FORK_GUARD.with(|slot| *slot.borrow_mut() = Some(guard));
    }
}

/// Call in the parent after a fork (or a failed fork) begun with [`before_fork`]:
/// releases the pool's lock.
pub fn after_fork_in_parent() {
    #[cfg(feature = "parallel")]
    FORK_GUARD.with(|slot| drop(slot.borrow_mut().take()));
}

/// Call in the child after a fork begun with [`before_fork`]: forgets the parent's
/// pool (the next parallel call builds one here) and releases the lock.
pub fn after_fork_in_child() {
    #[cfg(feature = "parallel")]
    FORK_GUARD.with(|slot| {
        if let Some(mut guard) = slot.borrow_mut().take() {
            forget_if_inherited(&mut guard, std::process::id());
        }
    });
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
        match pool(n) {
            Some(pool) => pool.install(|| parts.par_iter().map(f).collect()),
            // No threads to be had: run on the caller's thread.
            None => parts.iter().map(f).collect(),
        }
    }
    #[cfg(not(feature = "parallel"))]
    {
        parts.iter().map(f).collect()
    }
}

/// Asked by a long call between bounded steps, on the thread that made the call:
/// `true` stops the call early. The bindings run Python's signal handlers here, so
/// that Ctrl-C stops the call.
pub type Interrupt<'a> = dyn FnMut() -> bool + 'a;

/// Items per part for a parallel map whose items cost about `cost` units each (e.g.
/// a neighbour count): about `budget` units a part, at least one item, at most `most`,
/// so that a round of [`map_parts_interruptible`] stays short whatever the cost.
pub fn items_per_part(cost: usize, budget: usize, most: usize) -> usize {
    (budget / cost.max(1)).clamp(1, most)
}

/// [`map_parts`] in rounds of a few parts per thread, asking `interrupt` on the
/// calling thread after each round; `None` when it asked to stop (the parts left
/// are not computed). Size the parts so that a round takes milliseconds.
pub fn map_parts_interruptible<T: Sync, R: Send>(
    parts: &[T],
    f: impl Fn(&T) -> R + Sync + Send,
    interrupt: &mut Interrupt<'_>,
) -> Option<Vec<R>> {
    let round = num_threads().max(1) * 4;
    let mut out = Vec::with_capacity(parts.len());
    for chunk in parts.chunks(round) {
        out.extend(map_parts(chunk, &f));
        if interrupt() {
            return None;
        }
    }
    Some(out)
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

    #[test]
    fn an_interrupted_map_stops_between_rounds() {
        set_local_num_threads(Some(2));
        let parts: Vec<u32> = (0..100).collect();
        let done = std::sync::atomic::AtomicUsize::new(0);
        let f = |x: &u32| {
            done.fetch_add(1, Ordering::Relaxed);
            x * 3
        };
        // Never asked to stop: every part, in order.
        assert_eq!(
            map_parts_interruptible(&parts, f, &mut || false),
            Some((0..100).map(|x| x * 3).collect())
        );
        // Asked to stop after the second round: two rounds computed, nothing returned.
        done.store(0, Ordering::Relaxed);
        let mut asked = 0;
        let stop = map_parts_interruptible(&parts, f, &mut || {
            asked += 1;
            asked == 2
        });
        assert_eq!(stop, None);
        assert_eq!(asked, 2);
        assert_eq!(done.load(Ordering::Relaxed), 2 * 2 * 4);
        set_local_num_threads(None);
    }

    #[cfg(feature = "parallel")]
    #[test]
    fn a_pool_built_by_another_process_is_replaced_not_used() {
        let inherited = std::sync::Arc::new(
            rayon::ThreadPoolBuilder::new()
                .num_threads(2)
                .build()
                .unwrap(),
        );
        let mut slot = Some(Pool {
            pid: std::process::id().wrapping_add(1),
            threads: 2,
            pool: inherited.clone(),
        });
        forget_if_inherited(&mut slot, std::process::id());
        assert!(slot.is_none());
        // Forgotten, not dropped: the reference it held is still counted.
        assert_eq!(std::sync::Arc::strong_count(&inherited), 2);
        // This process's own pool is kept.
        let own = std::sync::Arc::new(
            rayon::ThreadPoolBuilder::new()
                .num_threads(2)
                .build()
                .unwrap(),
        );
        let mut slot = Some(Pool {
            pid: std::process::id(),
            threads: 2,
            pool: own,
        });
        forget_if_inherited(&mut slot, std::process::id());
        assert!(slot.is_some());
    }
}
