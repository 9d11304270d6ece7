//! The pool's worker threads (with std): started once, parked between tasks, each task run
//! by every thread, the caller's included.

use crate::{Error, Result};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// A closure every thread runs, the caller's included.
type Task<'a> = dyn Fn() + Sync + 'a;

/// What a worker thread runs from start to shutdown.
type Work = Box<dyn FnOnce() + Send>;

/// How long a worker polls for the next task, and the caller for the workers to finish,
/// before sleeping on a condition variable. The layers of one network call follow each
/// other within microseconds, and waking a sleeping thread costs tens of microseconds on a
/// VM: more than a whole transition step. Between calls the threads sleep.
const SPIN: Duration = Duration::from_micros(200);

pub(crate) struct Pool {
    shared: Arc<Shared>,
    workers: Vec<JoinHandle<()>>,
}

struct Shared {
    /// The number of the latest task (or `u64::MAX` for shutdown); polled while spinning.
    generation: AtomicU64,
    /// Workers still running the current task.
    running: AtomicUsize,
    /// A worker's task panicked; the caller re-raises it.
    panicked: AtomicBool,
    state: Mutex<State>,
    /// Signals sleeping workers that a new task (or shutdown) was posted.
    posted: Condvar,
    /// Signals the caller that the last worker finished (or, at start, that one is ready).
    finished: Condvar,
}

struct State {
    /// The current task, erased to `'static`: it lives on the stack of [`Pool::run`], which
    /// does not return before every worker is done with it.
    task: Option<*const Task<'static>>,
    /// Workers asleep on `posted`: only then does posting a task need a system call.
    sleeping: usize,
    /// The caller sleeps on `finished`.
    caller_sleeping: bool,
    /// Workers that have started and wait for tasks.
    ready: usize,
}

// SAFETY: the task pointer is only dereferenced while `Pool::run` keeps the closure alive, and
// the closure is `Sync`.
unsafe impl Send for State {}

const SHUTDOWN: u64 = u64::MAX;

/// Polls `done` for up to [`SPIN`]; true if it became true.
fn spin_until(done: impl Fn() -> bool) -> bool {
    let start = Instant::now();
    loop {
        for _ in 0..64 {
            if done() {
                return true;
            }
            std::hint::spin_loop();
        }
        if start.elapsed() > SPIN {
            return done();
        }
    }
}

impl Pool {
    /// A pool in which `threads` threads (the caller included) share each task, planned before
    /// anything is allocated: more than [`super::MAX_THREADS`] is [`Error::Config`], memory
    /// for the workers' handles that cannot be reserved [`Error::OutOfMemory`], and a thread
    /// the system will not start [`Error::Threads`] (those that were are stopped and joined
    /// before the error returns).
    pub fn new(threads: usize) -> Result<Pool> {
        Pool::start(threads, |index, work| {
            std::thread::Builder::new()
                .name(format!("drivesim-{index}"))
                .spawn(work)
        })
    }

    /// [`Pool::new`] with the worker threads started by `spawn`.
    fn start(threads: usize, spawn: impl Fn(usize, Work) -> std::io::Result<JoinHandle<()>>) -> Result<Pool> {
        let threads = super::check_threads(threads)?;
        let mut workers = Vec::new();
        workers.try_reserve_exact(threads - 1).map_err(|_| Error::OutOfMemory {
            what: "the thread pool",
            bytes: (threads - 1).checked_mul(core::mem::size_of::<JoinHandle<()>>()),
        })?;
        let shared = Arc::new(Shared {
            generation: AtomicU64::new(0),
            running: AtomicUsize::new(0),
            panicked: AtomicBool::new(false),
            state: Mutex::new(State {
                task: None,
                sleeping: 0,
                caller_sleeping: false,
                ready: 0,
            }),
            posted: Condvar::new(),
            finished: Condvar::new(),
        });
        let mut pool = Pool { shared, workers };
        for index in 1..threads {
            let shared = Arc::clone(&pool.shared);
            // On failure, dropping `pool` shuts down and joins the workers started so far.
            let handle = spawn(index, Box::new(move || worker(&shared))).map_err(|source| Error::Threads {
                requested: threads,
                source,
            })?;
            pool.workers.push(handle);
        }
        // Wait until every worker is parked: a thread's start-up allocates, and it must not
        // do so during the simulator's first call.
        let mut state = lock(&pool.shared.state);
        while state.ready < pool.workers.len() {
            state = pool.shared.finished.wait(state).unwrap_or_else(|e| e.into_inner());
        }
        drop(state);
        Ok(pool)
    }

    /// Threads that share a task, the caller included.
    pub fn threads(&self) -> usize {
        self.workers.len() + 1
    }

    /// Runs `task` on every thread at once, and returns when all are done.
    pub fn run(&self, task: &Task<'_>) {
        if self.workers.is_empty() {
            return task();
        }
        let shared = &*self.shared;
        {
            let mut state = lock(&shared.state);
            // SAFETY: only the lifetime is erased; this function waits below until every
            // worker has finished with the task before `task` can go out of scope.
            let erased: *const Task<'static> = unsafe { core::mem::transmute(task as *const Task<'_>) };
            state.task = Some(erased);
            shared.running.store(self.workers.len(), Ordering::Relaxed);
            // Published under the lock, so a worker about to sleep sees it or is counted.
            shared.generation.fetch_add(1, Ordering::Release);
            if state.sleeping > 0 {
                shared.posted.notify_all();
            }
        }
        // Waits for the workers even if the caller's `task` panics, so none outlives it.
        let wait = WaitForWorkers(shared);
        task();
        drop(wait);
        if shared.panicked.swap(false, Ordering::Relaxed) {
            panic!("a drivesim worker thread panicked");
        }
    }
}

struct WaitForWorkers<'a>(&'a Shared);

impl Drop for WaitForWorkers<'_> {
    fn drop(&mut self) {
        let shared = self.0;
        let done = || shared.running.load(Ordering::Acquire) == 0;
        if !spin_until(done) {
            let mut state = lock(&shared.state);
            state.caller_sleeping = true;
            // The last worker takes the lock after counting down, so it cannot signal
            // between this check and the wait.
            while !done() {
                state = shared.finished.wait(state).unwrap_or_else(|e| e.into_inner());
            }
            state.caller_sleeping = false;
        }
        lock(&shared.state).task = None;
    }
}

impl Drop for Pool {
    fn drop(&mut self) {
        {
            let _state = lock(&self.shared.state);
            self.shared.generation.store(SHUTDOWN, Ordering::Release);
            self.shared.posted.notify_all();
        }
        for worker in self.workers.drain(..) {
            let _ = worker.join();
        }
    }
}

fn worker(shared: &Shared) {
    let mut seen = 0;
    lock(&shared.state).ready += 1;
    shared.finished.notify_all();
    loop {
        let posted = || shared.generation.load(Ordering::Acquire) != seen;
        let task = {
            let spun = spin_until(posted);
            let mut state = lock(&shared.state);
            if !spun {
                state.sleeping += 1;
                while !posted() {
                    state = shared.posted.wait(state).unwrap_or_else(|e| e.into_inner());
                }
                state.sleeping -= 1;
            }
            seen = shared.generation.load(Ordering::Acquire);
            if seen == SHUTDOWN {
                return;
            }
            state.task.expect("a posted task")
        };
        // SAFETY: `Pool::run` keeps the closure alive until `running` drops to zero below.
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| unsafe { (*task)() }));
        if result.is_err() {
            shared.panicked.store(true, Ordering::Relaxed);
        }
        if shared.running.fetch_sub(1, Ordering::AcqRel) == 1 {
            let state = lock(&shared.state);
            if state.caller_sleeping {
                shared.finished.notify_one();
            }
        }
    }
}

/// A poisoned lock only means another thread panicked mid-task; the state is still consistent.
fn lock(m: &Mutex<State>) -> MutexGuard<'_, State> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pool whose third worker cannot start stops and joins the two that did.
    #[test]
    fn failed_start_joins_the_started_workers() {
        let exited = Arc::new(AtomicUsize::new(0));
        let result = Pool::start(5, |index, work| {
            if index == 3 {
                return Err(std::io::Error::other("no more threads"));
            }
            let exited = Arc::clone(&exited);
            std::thread::Builder::new().spawn(move || {
                work();
                exited.fetch_add(1, Ordering::SeqCst);
            })
        });
        assert!(matches!(result, Err(Error::Threads { requested: 5, .. })));
        assert_eq!(exited.load(Ordering::SeqCst), 2, "workers left running");
    }

    /// Too many threads is an error before any memory is reserved or any thread started
    /// (issue 46: 2**32 threads aborted the process in `Vec::with_capacity`).
    #[test]
    fn too_many_threads_fail_before_anything_starts() {
        let spawned = AtomicUsize::new(0);
        for threads in [super::super::MAX_THREADS + 1, 1 << 32, usize::MAX] {
            let result = Pool::start(threads, |_, _| {
                spawned.fetch_add(1, Ordering::SeqCst);
                Err(std::io::Error::other("must not be called"))
            });
            match result {
                Err(Error::Config {
                    field: "threads",
                    found,
                    ..
                }) => assert_eq!(found, threads),
                other => panic!("{threads} threads: {:?}", other.map(|p| p.threads())),
            }
        }
        assert_eq!(spawned.load(Ordering::SeqCst), 0);
        assert_eq!(Pool::new(0).map(|p| p.threads()).ok(), Some(1));
    }
}
