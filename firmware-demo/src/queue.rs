//! The time-stamped action queue between the policy and the control tick.
//!
//! Hand-over rule: when a chunk arrives, its actions whose time has passed are dropped
//! (stale). The chunk takes over at its first still-valid timestamp: queued actions stamped
//! before that time stay and run as planned, queued actions stamped at or after it are
//! replaced by the chunk's. Every tick therefore runs exactly one action stamped for that tick
//! (or holds when there is none): time never runs backwards, no tick runs two chunks' actions,
//! and the newest observation decides every tick it still can.

use heapless::Deque;

/// Largest `action_dim` the queue stores inline.
pub const MAX_ACTION_DIM: usize = 16;
/// Largest `n_action_steps`.
pub const MAX_CHUNK: usize = 32;
/// Room for the unreplaced remainder of one chunk plus a whole new chunk.
pub const QUEUE_CAPACITY: usize = 2 * MAX_CHUNK;

/// One action and the control tick it is for.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TimedAction {
    pub time_us: u64,
    values: [f32; MAX_ACTION_DIM],
    dim: usize,
}

impl TimedAction {
    /// `values.len()` must be at most [`MAX_ACTION_DIM`]; the control loop checks it once.
    pub fn new(time_us: u64, values: &[f32]) -> TimedAction {
        let mut stored = [0.0; MAX_ACTION_DIM];
        stored[..values.len()].copy_from_slice(values);
        TimedAction {
            time_us,
            values: stored,
            dim: values.len(),
        }
    }

    pub fn values(&self) -> &[f32] {
        &self.values[..self.dim]
    }
}

/// What one hand-over did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct HandOver {
    /// Actions of the chunk whose time had passed at arrival.
    pub stale: usize,
    /// Queued actions of older chunks the new chunk superseded.
    pub replaced: usize,
    /// Actions of the chunk now queued.
    pub queued: usize,
    /// Actions that did not fit (cannot happen while chunks are at most [`MAX_CHUNK`] long).
    pub overflowed: usize,
}

/// What a control tick gets from the queue.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Due {
    Run(TimedAction),
    /// No action is stamped for this tick: the robot holds still.
    Hold,
}

#[derive(Clone, Debug, Default)]
pub struct ActionQueue {
    /// Sorted by time, one action per tick at most.
    actions: Deque<TimedAction, QUEUE_CAPACITY>,
}

impl ActionQueue {
    pub const fn new() -> ActionQueue {
        ActionQueue {
            actions: Deque::new(),
        }
    }

    pub fn len(&self) -> usize {
        self.actions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.actions.is_empty()
    }

    pub fn iter(&self) -> impl Iterator<Item = &TimedAction> {
        self.actions.iter()
    }

    /// Time of the last queued action.
    pub fn last_time_us(&self) -> Option<u64> {
        self.actions.back().map(|action| action.time_us)
    }

    /// Merges a chunk `[n, action_dim]` computed from an observation taken at `observed_us`
    /// (action `i` is for `observed_us + i * period_us`) that becomes available at
    /// `arrival_us`. An action for exactly `arrival_us` is still valid: the tick at that time
    /// runs after the arrival.
    pub fn hand_over(
        &mut self,
        chunk: &[f32],
        action_dim: usize,
        observed_us: u64,
        period_us: u64,
        arrival_us: u64,
    ) -> HandOver {
        let steps = chunk.len() / action_dim;
        let time_of = |index: usize| observed_us + index as u64 * period_us;
        let first_valid = (0..steps)
            .find(|&index| time_of(index) >= arrival_us)
            .unwrap_or(steps);
        let mut report = HandOver {
            stale: first_valid,
            ..HandOver::default()
        };
        if first_valid == steps {
            return report;
        }
        let takeover_us = time_of(first_valid);
        while self
            .actions
            .back()
            .is_some_and(|action| action.time_us >= takeover_us)
        {
            self.actions.pop_back();
            report.replaced += 1;
        }
        for (index, values) in chunk.chunks_exact(action_dim).enumerate().skip(first_valid) {
            match self
                .actions
                .push_back(TimedAction::new(time_of(index), values))
            {
                Ok(()) => report.queued += 1,
                Err(_) => report.overflowed += 1,
            }
        }
        report
    }

    /// The action for the tick at `tick_us`. Actions stamped earlier can only be left over if
    /// a tick was skipped; they are discarded and counted in the second value.
    pub fn take_due(&mut self, tick_us: u64) -> (Due, usize) {
        let mut expired = 0;
        while self
            .actions
            .front()
            .is_some_and(|action| action.time_us < tick_us)
        {
            self.actions.pop_front();
            expired += 1;
        }
        let due = match self.actions.front() {
            Some(action) if action.time_us == tick_us => {
                let action = *action;
                self.actions.pop_front();
                Due::Run(action)
            }
            _ => Due::Hold,
        };
        (due, expired)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DT: u64 = 100_000;

    /// A chunk whose action `i` is `[base + i]`.
    fn chunk(base: f32, steps: usize) -> heapless::Vec<f32, MAX_CHUNK> {
        (0..steps).map(|index| base + index as f32).collect()
    }

    fn queued(queue: &ActionQueue) -> heapless::Vec<(u64, f32), QUEUE_CAPACITY> {
        queue
            .iter()
            .map(|action| (action.time_us, action.values()[0]))
            .collect()
    }

    #[test]
    fn stale_actions_are_exactly_those_whose_time_passed() {
        let mut queue = ActionQueue::new();
        // Observation at 1.0 s, chunk arrives 250 ms later: actions for 1.0, 1.1, 1.2 s passed.
        let report = queue.hand_over(&chunk(0.0, 8), 1, 1_000_000, DT, 1_250_000);
        assert_eq!(report.stale, 3);
        assert_eq!(report.queued, 5);
        assert_eq!(queue.iter().next().map(|a| a.time_us), Some(1_300_000));
        assert_eq!(queue.iter().next().map(|a| a.values()[0]), Some(3.0));
    }

    #[test]
    fn an_action_for_the_arrival_instant_is_kept() {
        let mut queue = ActionQueue::new();
        let report = queue.hand_over(&chunk(0.0, 4), 1, 0, DT, 2 * DT);
        assert_eq!((report.stale, report.queued), (2, 2));
    }

    #[test]
    fn new_chunk_replaces_from_its_first_valid_time_on() {
        let mut queue = ActionQueue::new();
        queue.hand_over(&chunk(10.0, 8), 1, 0, DT, 1);
        // Old chunk: 0.1 s .. 0.7 s. New observation at 0.5 s, arrival at 0.65 s: the new
        // chunk's 0.5 and 0.6 s actions are stale, it takes over at 0.7 s.
        let report = queue.hand_over(&chunk(20.0, 8), 1, 5 * DT, DT, 650_000);
        assert_eq!(report.stale, 2);
        assert_eq!(report.replaced, 1);
        assert_eq!(report.queued, 6);
        let expected = [
            (DT, 11.0),
            (2 * DT, 12.0),
            (3 * DT, 13.0),
            (4 * DT, 14.0),
            (5 * DT, 15.0),
            (6 * DT, 16.0),
            (7 * DT, 22.0),
            (8 * DT, 23.0),
        ];
        assert_eq!(&queued(&queue)[..8], &expected);
        assert_eq!(queue.len(), 12);
    }

    #[test]
    fn fully_stale_chunk_leaves_the_queue_alone() {
        let mut queue = ActionQueue::new();
        queue.hand_over(&chunk(10.0, 4), 1, 0, DT, 0);
        let before = queued(&queue);
        let report = queue.hand_over(&chunk(20.0, 4), 1, 0, DT, 5 * DT);
        assert_eq!(report.stale, 4);
        assert_eq!(report.replaced, 0);
        assert_eq!(queued(&queue), before);
    }

    #[test]
    fn take_due_runs_the_action_for_the_tick_or_holds() {
        let mut queue = ActionQueue::new();
        queue.hand_over(&chunk(0.0, 3), 1, DT, DT, DT);
        assert_eq!(queue.take_due(0), (Due::Hold, 0));
        assert!(matches!(queue.take_due(DT), (Due::Run(a), 0) if a.values() == [0.0]));
        // Skipping the 0.2 s tick discards its action rather than running it late.
        assert!(matches!(queue.take_due(3 * DT), (Due::Run(a), 1) if a.values() == [2.0]));
        assert_eq!(queue.take_due(4 * DT), (Due::Hold, 0));
    }
}
