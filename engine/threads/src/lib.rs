//! The engine's [`Workers`] on threads: `count - 1` threads spawned once, beside the calling thread,
//! which runs its own share of every call. Kernel calls come a few microseconds apart
//! during an inference, far less than waking a parked thread takes, so the threads spin
//! on the next call for a while ([`SPIN`]) and park only when none comes: between
//! inferences. A call creates no thread and allocates nothing.

use std::cell::UnsafeCell;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

pub use scdp_engine::kernels::{Sequential, Workers};

/// How long an idle thread waits for the next call before parking.
const SPIN: Duration = Duration::from_micros(500);

/// The call in progress: its work (its lifetime erased, see [`ThreadPool::run`]) and how
/// many pieces it has.
type Job = (*const (dyn Fn(usize) + Sync), usize);

struct Shared {
    /// Bumped by each call; a thread runs the job of every generation it sees.
    generation: AtomicUsize,
    job: UnsafeCell<Option<Job>>,
    /// Threads (not counting the caller) that have not finished the current call.
    running: AtomicUsize,
    /// The next piece of the current call nobody has taken: each worker, the caller
    /// included, takes pieces until none is left, so a worker that starts late or runs
    /// slower (its inputs in the other core's cache) takes fewer.
    next: AtomicUsize,
    panicked: AtomicBool,
    stop: AtomicBool,
    /// Workers, the caller included.
    count: usize,
}

// SAFETY: `job` is written only by the caller of `run`, holding `ThreadPool::calls`, while
// no thread reads it (before the generation's release store that publishes it, and after
// every thread has reported with a release decrement of `running`); the threads read it
// only between those two points. The work it points to is `Sync`.
unsafe impl Sync for Shared {}
// SAFETY: as above; the raw pointer is only the erased `&(dyn Fn(usize) + Sync)`.
unsafe impl Send for Shared {}

/// A fixed set of worker threads for `scdp_engine::Policy::with_workers`.
pub struct ThreadPool {
    shared: Arc<Shared>,
    threads: Vec<JoinHandle<()>>,
    /// One call at a time (the policy makes them one after the other anyway).
    calls: Mutex<()>,
}

impl core::fmt::Debug for ThreadPool {
    fn fmt(&self, formatter: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        formatter
            .debug_struct("ThreadPool")
            .field("count", &self.shared.count)
            .finish()
    }
}

impl ThreadPool {
    /// `count` workers (at least one): the calling thread and `count - 1` new threads.
    ///
    /// # Errors
    /// When the OS cannot create a thread.
    pub fn new(count: usize) -> std::io::Result<Self> {
        let count = count.max(1);
        let shared = Arc::new(Shared {
            generation: AtomicUsize::new(0),
            job: UnsafeCell::new(None),
            running: AtomicUsize::new(0),
            next: AtomicUsize::new(0),
            panicked: AtomicBool::new(false),
            stop: AtomicBool::new(false),
            count,
        });
        let mut threads = Vec::with_capacity(count - 1);
        for worker in 1..count {
            let mine = Arc::clone(&shared);
            let thread = thread::Builder::new()
                .name(format!("scdp-worker-{worker}"))
                .spawn(move || work_loop(&mine));
            match thread {
                Ok(thread) => threads.push(thread),
                Err(error) => {
                    stop(&shared, &threads);
                    return Err(error);
                }
            }
        }
        Ok(ThreadPool {
            shared,
            threads,
            calls: Mutex::new(()),
        })
    }
}

/// Runs pieces of the current call until none is left.
fn take_pieces(shared: &Shared, pieces: usize, work: &(dyn Fn(usize) + Sync)) {
    loop {
        let piece = shared.next.fetch_add(1, Ordering::Relaxed);
        if piece >= pieces {
            return;
        }
        work(piece);
    }
}

/// Runs pieces of each call until told to stop.
fn work_loop(shared: &Shared) {
    let mut seen = 0;
    loop {
        let waiting = Instant::now();
        let mut spins = 0u32;
        loop {
            if shared.stop.load(Ordering::Acquire) {
                return;
            }
            let generation = shared.generation.load(Ordering::Acquire);
            if generation != seen {
                seen = generation;
                break;
            }
            spins = spins.wrapping_add(1);
            if !spins.is_multiple_of(64) || waiting.elapsed() < SPIN {
                core::hint::spin_loop();
            } else {
                // `run` unparks every thread after publishing a call, so a call published
                // between the check above and this park only makes it return at once.
                thread::park();
            }
        }
        // SAFETY: the generation's acquire load above saw the release store that followed
        // writing the job, and the caller does not touch it again before this thread
        // decrements `running` below.
        let (work, pieces) = unsafe { (*shared.job.get()).expect("a published call") };
        // SAFETY: the caller of `run` keeps the work alive until `running` reaches zero.
        let work = unsafe { &*work };
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            take_pieces(shared, pieces, work)
        }));
        if result.is_err() {
            shared.panicked.store(true, Ordering::Relaxed);
        }
        shared.running.fetch_sub(1, Ordering::Release);
    }
}

fn stop(shared: &Shared, threads: &[JoinHandle<()>]) {
    shared.stop.store(true, Ordering::Release);
    for thread in threads {
        thread.thread().unpark();
    }
}

impl Drop for ThreadPool {
    fn drop(&mut self) {
        stop(&self.shared, &self.threads);
        for thread in self.threads.drain(..) {
            // A thread's panics were caught and reported by `run`.
            let _ = thread.join();
        }
    }
}

impl Workers for ThreadPool {
    fn count(&self) -> usize {
        self.shared.count
    }

    /// # Panics
    /// When a piece panicked (after every piece has returned).
    fn run(&self, pieces: usize, work: &(dyn Fn(usize) + Sync)) {
        let shared = &*self.shared;
        if pieces <= 1 || self.threads.is_empty() {
            return (0..pieces).for_each(work);
        }
        // A poisoned lock only means an earlier call panicked; the pool's state is whole.
        let _call = self
            .calls
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        // SAFETY: erases the work's lifetime for the threads; this function does not return
        // (nor unwind) before every thread has finished with it (`running` back to zero),
        // and clears the job before returning.
        let erased: *const (dyn Fn(usize) + Sync + 'static) = unsafe {
            core::mem::transmute::<*const (dyn Fn(usize) + Sync + '_), _>(work as *const _)
        };
        // SAFETY: no thread reads the job now: every one has reported the previous call.
        unsafe { *shared.job.get() = Some((erased, pieces)) };
        shared.running.store(self.threads.len(), Ordering::Relaxed);
        shared.next.store(0, Ordering::Relaxed);
        shared.panicked.store(false, Ordering::Relaxed);
        shared.generation.fetch_add(1, Ordering::Release);
        for thread in &self.threads {
            thread.thread().unpark();
        }
        let mine = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            take_pieces(shared, pieces, work)
        }));
        let mut spins = 0u32;
        while shared.running.load(Ordering::Acquire) != 0 {
            // A thread taken off its core (more threads than cores) finishes only once the
            // OS runs it again: past a short spin, offer it this core.
            spins = spins.saturating_add(1);
            if spins < 4096 {
                core::hint::spin_loop();
            } else {
                thread::yield_now();
            }
        }
        // SAFETY: every thread has reported (the acquire load above); none reads it again
        // before the next generation.
        unsafe { *shared.job.get() = None };
        if let Err(panic) = mine {
            std::panic::resume_unwind(panic);
        }
        assert!(
            !shared.panicked.load(Ordering::Relaxed),
            "a worker thread panicked"
        );
    }
}
