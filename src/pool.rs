//! Worker pools that join their threads when dropped.
//!
//! Dropping a rayon `ThreadPool` only signals its workers, which then exit on their own time.
//! A host that unloads the library (`dlclose`, a Unity domain reload) right after freeing a
//! session would leave code of the unloaded library running, so libflame's pools wait.

use std::thread::JoinHandle;

use crate::error::{invalid_arg, Result};

/// A rayon pool of `threads` named workers, joined on drop.
pub struct WorkerPool {
    pool: Option<rayon::ThreadPool>,
    workers: Vec<JoinHandle<()>>,
}

impl WorkerPool {
    /// Starts `threads` workers (0 = one per core).
    pub fn new(threads: usize) -> Result<WorkerPool> {
        let threads = if threads == 0 {
            std::thread::available_parallelism().map_or(1, |n| n.get())
        } else {
            threads
        };
        let mut workers = Vec::with_capacity(threads);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("flame-worker-{i}"))
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
}
