//! Worker pools that join their threads when dropped.
//!
//! Dropping a rayon `ThreadPool` only signals its workers, which then exit on their own time.
//! A host that unloads the library (`dlclose`, a Unity domain reload) right after freeing a
//! session would leave code of the unloaded library running, so libflame's pools wait.

use std::cell::Cell;
use std::thread::JoinHandle;

use crate::error::{invalid_arg, Result};

/// The most worker threads one pool starts (C: `FLAME_MAX_THREADS`). More would only add
/// scheduling overhead on any machine libflame targets, and each thread costs a stack.
pub const MAX_THREADS: usize = 256;

thread_local! {
    static WORKER: Cell<bool> = const { Cell::new(false) };
}

/// Whether the calling thread is a worker of a libflame pool (the C ABI's panic hook keeps
/// their panics quiet: they reach the caller's thread, where the entry point reports them).
pub(crate) fn is_worker_thread() -> bool {
    WORKER.with(Cell::get)
}

/// A rayon pool of `threads` named workers, joined on drop.
pub struct WorkerPool {
    pool: Option<rayon::ThreadPool>,
    workers: Vec<JoinHandle<()>>,
}

impl WorkerPool {
    /// Starts `threads` workers: 1..=[`MAX_THREADS`], or 0 for one per core (at most
    /// [`MAX_THREADS`]). Above the bound: [`crate::Error::InvalidArgument`], before any thread
    /// is started.
    pub fn new(threads: usize) -> Result<WorkerPool> {
        if threads > MAX_THREADS {
            return Err(invalid_arg!(
                "threads {threads} is above the limit of {MAX_THREADS}"
            ));
        }
        let threads = if threads == 0 {
            std::thread::available_parallelism().map_or(1, |n| n.get().min(MAX_THREADS))
        } else {
            threads
        };
        let mut workers = Vec::with_capacity(threads);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("flame-worker-{i}"))
            .start_handler(|_| WORKER.with(|w| w.set(true)))
            .spawn_handler(|t| {
                let mut b = std::thread::Builder::new();
                if let Some(name) = t.name() {
                    b = b.name(name.to_owned());
                }
                if let Some(size) = t.stack_size() {
                    b = b.stack_size(size);
                }
                workers.push(b.spawn(|| t.run())?);
                Ok(())
            })
            .build()
            .map_err(|e| invalid_arg!("cannot start {threads} worker threads: {e}"))?;
        Ok(WorkerPool {
            pool: Some(pool),
            workers,
        })
    }

    /// Runs `f` on the pool (the calling thread waits).
    pub fn install<R: Send>(&self, f: impl FnOnce() -> R + Send) -> R {
        self.pool
            .as_ref()
            .expect("pool lives until drop")
            .install(f)
    }

    /// Worker threads in the pool (what `threads` = 0 resolved to, or the count asked for).
    pub fn threads(&self) -> usize {
        self.workers.len()
    }
}

impl Drop for WorkerPool {
    fn drop(&mut self) {
        drop(self.pool.take());
        for w in self.workers.drain(..) {
            let _ = w.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;

    #[test]
    fn workers_are_gone_when_the_pool_is_dropped() {
        let alive = Arc::new(AtomicUsize::new(0));
        let pool = WorkerPool::new(3).unwrap();
        assert_eq!(pool.threads(), 3);
        assert_eq!(pool.install(rayon::current_num_threads), 3);
        // Each worker holds a clone of `alive` in a thread-local that is dropped at thread exit.
        struct Guard(Arc<AtomicUsize>);
        impl Drop for Guard {
            fn drop(&mut self) {
                self.0.fetch_sub(1, Ordering::SeqCst);
            }
        }
        thread_local!(static GUARD: std::cell::RefCell<Option<Guard>> = const { std::cell::RefCell::new(None) });
        pool.install(|| {
            rayon::broadcast(|_| {
                alive.fetch_add(1, Ordering::SeqCst);
                GUARD.with(|g| *g.borrow_mut() = Some(Guard(Arc::clone(&alive))));
            })
        });
        assert_eq!(alive.load(Ordering::SeqCst), 3);
        drop(pool);
        assert_eq!(
            alive.load(Ordering::SeqCst),
            0,
            "every worker exited before drop returned"
        );
    }

    #[test]
    fn thread_counts_are_bounded() {
        assert_eq!(crate::ffi::FLAME_MAX_THREADS as usize, MAX_THREADS);
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        assert_eq!(
            WorkerPool::new(0).unwrap().threads(),
            cores.min(MAX_THREADS)
        );
        assert_eq!(WorkerPool::new(MAX_THREADS).unwrap().threads(), MAX_THREADS);
        for n in [MAX_THREADS + 1, u32::MAX as usize, usize::MAX] {
            let e = WorkerPool::new(n).err().expect("refused").to_string();
            assert_eq!(
                e,
                format!("invalid argument: threads {n} is above the limit of 256")
            );
        }
    }
}
