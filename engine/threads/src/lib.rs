//! The engine's [`Workers`] on threads: `count - 1` threads spawned once, beside the calling thread,
//! which runs its own share of every call. Kernel calls come a few microseconds apart
//! during an inference, far less than waking a parked thread takes, so the threads spin
//! on the next call for a while (half a millisecond) and park only when none comes: between
//! inferences. A call creates no thread and allocates nothing.
//!
//! The caller waits only for the pieces a thread has claimed, never for a thread to show
//! up: a thread the OS has taken off its core (other programs on the computer, more
//! threads than cores) leaves its share to the others instead of stalling every call
//! until it is scheduled again.

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

/// A value on cache lines of its own, so that writing it does not take the others' lines
/// from the threads reading those: a call's cost is its lines' trips between cores
/// (`benches/benches/pool.rs`). 128 bytes, as Intel cores fetch lines in pairs.
#[repr(align(128))]
struct Line<T>(T);

impl<T> core::ops::Deref for Line<T> {
    type Target = T;

    fn deref(&self) -> &T {
        &self.0
    }
}

struct Shared {
    /// Bumped by each call: wakes the threads. Beside it the rest of what a call publishes
    /// (`job`, `open`, `panicked`) and what never changes during one (`stop`, `count`),
    /// so a thread that sees the bump reads them from the lines it just fetched.
    generation: AtomicUsize,
    job: UnsafeCell<Option<Job>>,
    /// Whether the job may be entered: set once a call has written it, cleared when the
    /// call returns.
    open: AtomicBool,
    panicked: AtomicBool,
    stop: AtomicBool,
    /// Workers, the caller included.
    count: usize,
    /// Threads (not counting the caller) inside a call: from before they look at `open`
    /// until they have stopped taking pieces. The job is not rewritten while one is.
    entered: Line<AtomicUsize>,
    /// The next piece of the current call nobody has taken: each worker, the caller
    /// included, takes pieces until none is left, so a worker that starts late or runs
    /// slower (its inputs in the other core's cache) takes fewer, and one that does not
    /// start at all takes none.
    next: Line<AtomicUsize>,
    /// Pieces of the current call that have returned.
    done: Line<AtomicUsize>,
}

// SAFETY: `job` is written only by the caller of `run`, holding `ThreadPool::calls`, while
// no thread reads it: with `entered` at zero and `open` false. A thread reads it only
// after counting itself in `entered` and then finding `open` set (both sequentially
// consistent, against the caller's check of `entered` and its store to `open`), and
// calls the work only for a piece it claimed, while the caller waits for that piece.
// The work it points to is `Sync`.
unsafe impl Sync for Shared {}
// SAFETY: as above; the raw pointer is only the erased `&(dyn Fn(usize) + Sync)`.
unsafe impl Send for Shared {}

/// A fixed set of worker threads for `scdp_engine::Policy::with_workers`.
pub struct ThreadPool {
    shared: Arc<Shared>,
    threads: Vec<JoinHandle<()>>,
    /// One call at a time (the policy makes them one after the other anyway); with the
    /// `timing` feature, the calls' tally.
    calls: Mutex<Tally>,
}

/// Where the calling thread's time went, from one [`ThreadPool::take_timing`] to the next
/// (feature `timing`). The four parts add up to the time between the two.
#[cfg(feature = "timing")]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Timing {
    /// Calls handed out (those of more than one piece).
    pub calls: usize,
    /// Outside the calls: what runs whole on the calling thread (the model's own work and
    /// kernel calls too small to cut).
    pub between: Duration,
    /// From a call's start until its first piece: waiting for the threads to have left the
    /// previous call, and publishing this one.
    pub publishing: Duration,
    /// Running pieces: the calling thread's own, and any no thread had claimed.
    pub pieces: Duration,
    /// Waiting for the pieces the other threads claimed.
    pub waiting: Duration,
}

/// Two spans' timings as one: each part, and the calls, added.
#[cfg(feature = "timing")]
impl core::ops::Add for Timing {
    type Output = Timing;

    fn add(self, other: Timing) -> Timing {
        Timing {
            calls: self.calls + other.calls,
            between: self.between + other.between,
            publishing: self.publishing + other.publishing,
            pieces: self.pieces + other.pieces,
            waiting: self.waiting + other.waiting,
        }
    }
}

#[cfg(feature = "timing")]
#[derive(Debug, Default)]
struct Tally {
    timing: Timing,
    /// When the last call (or the last `take_timing`) returned.
    since: Option<Instant>,
}

#[cfg(not(feature = "timing"))]
#[derive(Debug, Default)]
struct Tally;

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
    #[cfg_attr(
        not(feature = "timing"),
        allow(clippy::default_constructed_unit_structs)
    )]
    pub fn new(count: usize) -> std::io::Result<Self> {
        let count = count.max(1);
        let shared = Arc::new(Shared {
            generation: AtomicUsize::new(0),
            job: UnsafeCell::new(None),
            open: AtomicBool::new(false),
            entered: Line(AtomicUsize::new(0)),
            next: Line(AtomicUsize::new(0)),
            done: Line(AtomicUsize::new(0)),
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
            calls: Mutex::new(Tally::default()),
        })
    }

    /// The calling thread's time since the last call of this, and starts counting again.
    /// The first call gives the calls since the pool started, and the time between them.
    #[cfg(feature = "timing")]
    pub fn take_timing(&self) -> Timing {
        let mut tally = self
            .calls
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        let now = Instant::now();
        if let Some(since) = tally.since {
            tally.timing.between += now - since;
        }
        tally.since = Some(now);
        core::mem::take(&mut tally.timing)
    }
}

/// Runs pieces of the current call until none is left; a panic is recorded for the
/// caller, and its piece still counts as done.
fn take_pieces(shared: &Shared, pieces: usize, work: &(dyn Fn(usize) + Sync)) {
    loop {
        let piece = shared.next.fetch_add(1, Ordering::Relaxed);
        if piece >= pieces {
            return;
        }
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| work(piece)));
        if result.is_err() {
            shared.panicked.store(true, Ordering::Relaxed);
        }
        // Publishes the piece's writes to the caller, which waits for the count.
        shared.done.fetch_add(1, Ordering::Release);
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
        shared.entered.fetch_add(1, Ordering::SeqCst);
        if shared.open.load(Ordering::SeqCst) {
            // SAFETY: `open` was set after the job was written, and the job is not
            // rewritten before this thread leaves `entered` (see `Shared`).
            if let Some((work, pieces)) = unsafe { *shared.job.get() } {
                // SAFETY: the work is called only for a piece claimed before the last one
                // was done, and its call waits for that piece, so the work is alive.
                take_pieces(shared, pieces, unsafe { &*work });
            }
        }
        shared.entered.fetch_sub(1, Ordering::Release);
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
        #[cfg(feature = "timing")]
        let entered = Instant::now();
        // A poisoned lock only means an earlier call panicked; the pool's state is whole.
        #[cfg_attr(not(feature = "timing"), allow(unused_mut, unused_variables))]
        let mut tally = self
            .calls
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        // Threads still inside the previous call found it closed or without pieces and
        // are on their way out (unless taken off their core right there).
        wait_for(|| shared.entered.load(Ordering::SeqCst) == 0);
        // SAFETY: erases the work's lifetime for the threads; they call it only for pieces
        // claimed before this call returns, and it does not return (nor unwind: the pieces'
        // panics are caught) before every piece is done.
        let erased: *const (dyn Fn(usize) + Sync + 'static) = unsafe {
            core::mem::transmute::<*const (dyn Fn(usize) + Sync + '_), _>(work as *const _)
        };
        // SAFETY: no thread reads the job now: none is inside a call (checked above), and
        // one that enters from here on finds `open` false until the store below.
        unsafe { *shared.job.get() = Some((erased, pieces)) };
        shared.next.store(0, Ordering::Relaxed);
        shared.done.store(0, Ordering::Relaxed);
        shared.panicked.store(false, Ordering::Relaxed);
        shared.open.store(true, Ordering::SeqCst);
        shared.generation.fetch_add(1, Ordering::Release);
        for thread in &self.threads {
            thread.thread().unpark();
        }
        #[cfg(feature = "timing")]
        let published = Instant::now();
        take_pieces(shared, pieces, work);
        #[cfg(feature = "timing")]
        let ran = Instant::now();
        // Only pieces another thread claimed and is running are left to wait for.
        wait_for(|| shared.done.load(Ordering::Acquire) == pieces);
        shared.open.store(false, Ordering::SeqCst);
        #[cfg(feature = "timing")]
        {
            let returned = Instant::now();
            let since = tally.since.unwrap_or(entered);
            let timing = &mut tally.timing;
            timing.calls += 1;
            timing.between += entered.saturating_duration_since(since);
            timing.publishing += published - entered;
            timing.pieces += ran - published;
            timing.waiting += returned - ran;
            tally.since = Some(returned);
        }
        assert!(
            !shared.panicked.load(Ordering::Relaxed),
            "a piece of the work panicked"
        );
    }
}

/// Spins until `ready`; past a short spin, offers the core to the thread being waited for
/// (taken off its core mid-piece: more threads than cores).
fn wait_for(ready: impl Fn() -> bool) {
    let mut spins = 0u32;
    while !ready() {
        spins = spins.saturating_add(1);
        if spins < 4096 {
            core::hint::spin_loop();
        } else {
            thread::yield_now();
        }
    }
}
