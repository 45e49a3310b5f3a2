//! Workers: whatever runs pieces of one kernel call on several cores. The engine knows only
//! this contract, so firmware maps it onto its RTOS tasks or cores and hosted code onto
//! threads (the `scdp-threads` crate's `ThreadPool`, beside the engine in `engine/threads`);
//! [`super::split::Split`] decides the pieces.

/// Runs the pieces of a piece of work, possibly at the same time on different cores.
///
/// `run(pieces, work)` must call `work(piece)` exactly once for each `piece` in
/// `0..pieces`, in any order and on any of its cores (the calling one included), and
/// return only when every call has returned. The engine gives each piece a disjoint part
/// of the output, so which core runs which piece never changes a result.
pub trait Workers: Sync {
    /// How many pieces can run at once: the engine cuts a call into this many.
    fn count(&self) -> usize;

    /// Calls `work(piece)` for every piece in `0..pieces` and returns when all are done.
    fn run(&self, pieces: usize, work: &(dyn Fn(usize) + Sync));
}

/// One worker: the calling core runs every piece, one after the other. A policy given it
/// runs exactly as one given no workers.
#[derive(Clone, Copy, Debug, Default)]
pub struct Sequential;

impl Workers for Sequential {
    fn count(&self) -> usize {
        1
    }

    fn run(&self, pieces: usize, work: &(dyn Fn(usize) + Sync)) {
        (0..pieces).for_each(work)
    }
}

/// Runs `work` on each of `items`, one piece an item, over `workers`: each piece changes its
/// own item alone.
pub fn run_each<T: Send>(workers: &dyn Workers, items: &mut [T], work: &(dyn Fn(&mut T) + Sync)) {
    let (start, len) = (Items(items.as_mut_ptr()), items.len());
    let start = &start;
    workers.run(len, &|piece| {
        if piece < len {
            // SAFETY: `Workers::run` calls each piece once, so each item is lent to one
            // piece, while `items` stays borrowed until every piece has returned.
            work(unsafe { &mut *start.item(piece) })
        }
    });
}

/// The items' start, lent to the pieces.
struct Items<T>(*mut T);

impl<T> Items<T> {
    /// Item `index`'s place (inside the items: the caller checks).
    fn item(&self, index: usize) -> *mut T {
        self.0.wrapping_add(index)
    }
}

// SAFETY: each piece takes its own item (`run_each`); `T: Send` lets it go to that piece's
// thread.
unsafe impl<T: Send> Sync for Items<T> {}
