//! A chain of layers as one call of the workers: the first piece to start runs the layers
//! (the chain), the others help. They take the pieces of the chain's cut calls ([`Board`]
//! is itself [`Workers`]) and, in between, chunks of work the chain posted to run in the
//! background and collects later ([`Board::with_background`]: a denoising step's FiLM
//! products, which depend on the step's condition alone). A fork-join call for each layer
//! leaves the other workers idle while the calling thread runs what is not cut (a layer's
//! quantization, the small calls) and while the slower half of each call finishes; here
//! that time goes to the background work.
//!
//! A thread waits only for work another has claimed, never for a piece to start, so any
//! [`Workers`] (pieces one after the other on one core included) runs it to the end.

use core::cell::UnsafeCell;
use core::ops::Range;
use core::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use super::workers::Workers;

/// Background chunks a step can post at most.
pub const MAX_CHUNKS: usize = 256;

/// A call of the chain ([`Workers::run`]) being handed out.
type Job = (*const (dyn Fn(usize) + Sync), usize);

/// Background work: `work(chunk, values)` for each chunk, its values its range of the
/// output.
type ChunkWork<'w> = dyn Fn(usize, &mut [f32]) + Sync + 'w;

/// Helps the chain by running the pieces of its calls and its background chunks; see the
/// module documentation.
pub struct Board {
    count: usize,
    /// Bumped for each call the chain hands out.
    generation: AtomicUsize,
    job: UnsafeCell<Option<Job>>,
    /// Whether the current call still hands out pieces.
    open: AtomicBool,
    /// Helpers between seeing a call and being done with it: the chain writes the next
    /// call only when none is.
    entered: AtomicUsize,
    next: AtomicUsize,
    done: AtomicUsize,
    /// A call is being handed out: another one meanwhile (from a piece, or from work in
    /// the background) runs its pieces itself.
    calling: AtomicBool,
    /// The chain has returned: helpers leave.
    finished: AtomicBool,
    background: Background,
}

// SAFETY: `job` is written by one call at a time (`calling`) only while no helper has
// entered (`entered` is 0) and no call is open, and read by helpers only between entering
// and leaving while `open`; the background's cells are written only while no chunks are
// posted and no helper runs one. Every other field is atomic; the closures they point to
// are `Sync`.
unsafe impl Sync for Board {}

/// The background chunks posted by [`Board::with_background`].
struct Background {
    /// Chunks posted; 0 when none are.
    chunks: AtomicUsize,
    /// Chunks are being posted or are posted: another `with_background` meanwhile runs its
    /// chunks first, itself.
    posting: AtomicBool,
    /// The next chunk to claim.
    next: AtomicUsize,
    /// Whether each chunk has been run.
    done: [AtomicBool; MAX_CHUNKS],
    /// The work and the output's start, set while chunks are posted.
    work: UnsafeCell<Option<(*const ChunkWork<'static>, *mut f32)>>,
    ranges: UnsafeCell<[Range<usize>; MAX_CHUNKS]>,
    /// Helpers running a chunk: the chain takes the work down only when none is.
    running: AtomicUsize,
}

impl Board {
    fn new(count: usize) -> Self {
        Board {
            count,
            generation: AtomicUsize::new(0),
            job: UnsafeCell::new(None),
            open: AtomicBool::new(false),
            entered: AtomicUsize::new(0),
            next: AtomicUsize::new(0),
            done: AtomicUsize::new(0),
            calling: AtomicBool::new(false),
            finished: AtomicBool::new(false),
            background: Background {
                chunks: AtomicUsize::new(0),
                posting: AtomicBool::new(false),
                next: AtomicUsize::new(0),
                done: [const { AtomicBool::new(false) }; MAX_CHUNKS],
                work: UnsafeCell::new(None),
                ranges: UnsafeCell::new([const { 0..0 }; MAX_CHUNKS]),
                running: AtomicUsize::new(0),
            },
        }
    }

    /// Runs `chain(board)` with `workers`' other cores helping ([`Board`]); with one worker,
    /// `chain` runs alone on a board of one.
    pub fn lead(workers: &dyn Workers, chain: impl FnOnce(&Board) + Send) {
        let board = Board::new(workers.count().max(1));
        if board.count == 1 {
            return chain(&board);
        }
        let chain = Once(UnsafeCell::new(Some(chain)), AtomicBool::new(false));
        workers.run(board.count, &|_| match chain.take() {
            Some(chain) => {
                chain(&board);
                board.finished.store(true, Ordering::Release);
            }
            None => board.help(),
        });
    }

    /// A helper's loop: the chain's calls first, then background chunks, until the chain
    /// is done.
    fn help(&self) {
        let mut seen = self.generation.load(Ordering::Acquire);
        while !self.finished.load(Ordering::Acquire) {
            let generation = self.generation.load(Ordering::Acquire);
            if generation != seen {
                seen = generation;
                self.entered.fetch_add(1, Ordering::SeqCst);
                if self.open.load(Ordering::SeqCst) {
                    // SAFETY: the call is open and this thread has entered, so the chain
                    // does not write `job` until it leaves.
                    if let Some((work, pieces)) = unsafe { *self.job.get() } {
                        // SAFETY: the chain's `run` keeps `work` alive until every piece
                        // claimed is done, which includes this thread's.
                        self.take_pieces(pieces, unsafe { &*work });
                    }
                }
                self.entered.fetch_sub(1, Ordering::Release);
                continue;
            }
            if !self.background.run_one(usize::MAX) {
                core::hint::spin_loop();
            }
        }
    }

    /// Runs unclaimed pieces of the current call until none is left.
    fn take_pieces(&self, pieces: usize, work: &(dyn Fn(usize) + Sync)) {
        loop {
            let piece = self.next.fetch_add(1, Ordering::Relaxed);
            if piece >= pieces {
                return;
            }
            work(piece);
            self.done.fetch_add(1, Ordering::Release);
        }
    }

    /// Posts `chunks` (ranges of `output`, in order, at most [`MAX_CHUNKS`]) of
    /// `work(chunk, values)` for the helpers to run while `rest(board, done)` runs;
    /// `done.complete(chunk)` runs or waits for every chunk up to `chunk` and returns the
    /// output up to its end. Every chunk has run when this returns. Too many chunks, or
    /// ranges out of order or outside `output`, and the chunks run first, on this thread.
    pub fn with_background(
        &self,
        output: &mut [f32],
        chunks: &[Range<usize>],
        work: &ChunkWork<'_>,
        rest: impl FnOnce(&Board, &Collected<'_>),
    ) {
        let ordered = chunks.len() <= MAX_CHUNKS
            && chunks.windows(2).all(|pair| pair[0].end <= pair[1].start)
            && chunks
                .iter()
                .all(|range| range.start <= range.end && range.end <= output.len());
        let background = &self.background;
        if !ordered || self.count == 1 || background.posting.swap(true, Ordering::Acquire) {
            for (chunk, range) in chunks.iter().enumerate() {
                if let Some(values) = output.get_mut(range.clone()) {
                    work(chunk, values);
                }
            }
            return rest(self, &Collected::whole(output, chunks));
        }
        // SAFETY: no chunks are posted (they are only while this runs), so no helper reads
        // these cells.
        unsafe {
            let ranges = &mut *background.ranges.get();
            ranges[..chunks.len()].clone_from_slice(chunks);
            // The work outlives every use of it: this function takes it down before it
            // returns, once no helper runs a chunk.
            let work: *const ChunkWork<'_> = work;
            let work =
                core::mem::transmute::<*const ChunkWork<'_>, *const ChunkWork<'static>>(work);
            *background.work.get() = Some((work, output.as_mut_ptr()));
        }
        for done in &background.done[..chunks.len()] {
            done.store(false, Ordering::Relaxed);
        }
        background.next.store(0, Ordering::Relaxed);
        background.chunks.store(chunks.len(), Ordering::Release);
        let collected = Collected {
            background: Some(background),
            output: output.as_mut_ptr(),
            len: output.len(),
            ranges: chunks,
        };
        rest(self, &collected);
        collected.complete(chunks.len().saturating_sub(1));
        // Sequentially consistent with the helpers' `running` then `chunks`: either a
        // helper sees no chunks, or this sees it running.
        background.chunks.store(0, Ordering::SeqCst);
        wait_for(|| background.running.load(Ordering::SeqCst) == 0);
        // SAFETY: no chunks are posted and no helper runs one.
        unsafe { *background.work.get() = None };
        background.posting.store(false, Ordering::Release);
    }
}

impl Background {
    /// Runs the next unclaimed chunk if it is below `below`; `false` when there is none.
    fn run_one(&self, below: usize) -> bool {
        let posted = self.chunks.load(Ordering::Relaxed);
        if posted == 0 || self.next.load(Ordering::Relaxed) >= posted.min(below) {
            return false;
        }
        self.running.fetch_add(1, Ordering::SeqCst);
        let chunks = self.chunks.load(Ordering::SeqCst);
        let mut ran = false;
        if chunks > 0 {
            let limit = chunks.min(below);
            let claim = self
                .next
                .fetch_update(Ordering::AcqRel, Ordering::Acquire, |next| {
                    (next < limit).then_some(next + 1)
                });
            if let Ok(chunk) = claim {
                // SAFETY: chunks are posted, so the work, the output and the ranges stay as
                // `with_background` set them until `running` is back to 0; this thread
                // alone claimed `chunk`, whose range no other chunk overlaps and which
                // nobody reads before its `done` is set.
                unsafe {
                    if let Some((work, output)) = *self.work.get() {
                        let range = (*self.ranges.get())[chunk].clone();
                        let values =
                            core::slice::from_raw_parts_mut(output.add(range.start), range.len());
                        (*work)(chunk, values);
                    }
                }
                self.done[chunk].store(true, Ordering::Release);
                ran = true;
            }
        }
        self.running.fetch_sub(1, Ordering::Release);
        ran
    }
}

/// The background chunks' output, as they complete.
pub struct Collected<'c> {
    /// `None` where the chunks ran before the rest.
    background: Option<&'c Background>,
    output: *mut f32,
    len: usize,
    ranges: &'c [Range<usize>],
}

impl<'c> Collected<'c> {
    /// Chunks already run, on one thread: `complete` has nothing left to do.
    fn whole(output: &'c mut [f32], ranges: &'c [Range<usize>]) -> Self {
        Collected {
            background: None,
            output: output.as_mut_ptr(),
            len: output.len(),
            ranges,
        }
    }

    /// Runs what is left of chunks `0..=chunk` on this thread and waits for those others
    /// have claimed; returns the output up to the end of `chunk`'s range.
    pub fn complete(&self, chunk: usize) -> &[f32] {
        let Some(range) = self.ranges.get(chunk) else {
            return &[];
        };
        if let Some(background) = self.background {
            while background.run_one(chunk + 1) {}
            for done in &background.done[..=chunk] {
                wait_for(|| done.load(Ordering::Acquire));
            }
        }
        // SAFETY: every chunk up to `chunk` is done and none is run again, and the later
        // chunks write only past `range.end` (the ranges are in order), so nothing writes
        // these values while the result lives.
        unsafe { core::slice::from_raw_parts(self.output, range.end.min(self.len)) }
    }
}

impl Workers for Board {
    fn count(&self) -> usize {
        self.count
    }

    fn run(&self, pieces: usize, work: &(dyn Fn(usize) + Sync)) {
        if pieces <= 1 || self.count == 1 || self.calling.swap(true, Ordering::Acquire) {
            return (0..pieces).for_each(work);
        }
        wait_for(|| self.entered.load(Ordering::SeqCst) == 0);
        // SAFETY: the lifetime is erased for the helpers, who call `work` only for pieces
        // they claim, all of which are done before this returns.
        let erased: *const (dyn Fn(usize) + Sync + 'static) = unsafe {
            core::mem::transmute::<*const (dyn Fn(usize) + Sync + '_), _>(work as *const _)
        };
        // SAFETY: no helper has entered (waited for above) and the last call is closed.
        unsafe { *self.job.get() = Some((erased, pieces)) };
        self.next.store(0, Ordering::Relaxed);
        self.done.store(0, Ordering::Relaxed);
        self.open.store(true, Ordering::SeqCst);
        self.generation.fetch_add(1, Ordering::Release);
        self.take_pieces(pieces, work);
        // Background chunks while a helper finishes its pieces: that work is due anyway.
        while self.done.load(Ordering::Acquire) != pieces {
            if !self.background.run_one(usize::MAX) {
                core::hint::spin_loop();
            }
        }
        self.open.store(false, Ordering::SeqCst);
        self.calling.store(false, Ordering::Release);
    }
}

/// The chain, taken by the first piece to start.
struct Once<F>(UnsafeCell<Option<F>>, AtomicBool);

impl<F> Once<F> {
    /// The value for the first caller, `None` for every later one.
    fn take(&self) -> Option<F> {
        if self.1.swap(true, Ordering::AcqRel) {
            return None;
        }
        // SAFETY: the swap above lets one caller alone reach this.
        unsafe { (*self.0.get()).take() }
    }
}

// SAFETY: the cell is taken once, by the caller that wins the flag; `F: Send` moves it to
// that caller's thread.
unsafe impl<F: Send> Sync for Once<F> {}

/// Spins until `ready`.
fn wait_for(ready: impl Fn() -> bool) {
    while !ready() {
        core::hint::spin_loop();
    }
}
