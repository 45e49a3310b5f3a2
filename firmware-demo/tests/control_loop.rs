//! The loop's timing rules, driven by a fake policy whose compute time is scripted on a fake
//! clock. Every chunk action is `[inference index, action index]`, so the executed sequence
//! shows exactly which chunk and which action ran at each tick.

use std::cell::{Cell, RefCell};
use std::rc::Rc;

use firmware_demo::{ControlLoop, Dims, FRAME_SLOTS, Plant, PolicyPort, Stopwatch, Timing};

const DT: u64 = 100_000;
const ACTION_DIM: usize = 2;
const FRAME_BYTES: usize = 2 * 2 * 3;

#[derive(Clone, Default)]
struct FakeClock(Rc<Cell<u64>>);

impl FakeClock {
    fn advance(&self, micros: u64) {
        self.0.set(self.0.get() + micros);
    }
}

impl Stopwatch for FakeClock {
    fn now_us(&mut self) -> u64 {
        self.0.get()
    }
}

/// Models the engine's observation history, padding included, and records what each
/// inference saw.
struct FakePolicy {
    clock: FakeClock,
    n_obs_steps: usize,
    encode_us: u64,
    /// Compute time of inference `k`; the last entry repeats.
    infer_us: Vec<u64>,
    /// Capture times (seconds, from the state) of the frames in the history, oldest first.
    history: Vec<f32>,
    pushes: Vec<f32>,
    /// The history each inference saw.
    seen: Vec<Vec<f32>>,
    /// The committed prefix each inference was given.
    prefixes: Vec<Vec<f32>>,
    /// The planned actions after it.
    planned: Vec<Vec<f32>>,
}

impl FakePolicy {
    fn new(clock: &FakeClock, encode_us: u64, infer_us: &[u64]) -> Self {
        FakePolicy {
            clock: clock.clone(),
            n_obs_steps: 2,
            encode_us,
            infer_us: infer_us.to_vec(),
            history: Vec::new(),
            pushes: Vec::new(),
            seen: Vec::new(),
            prefixes: Vec::new(),
            planned: Vec::new(),
        }
    }
}

impl PolicyPort for FakePolicy {
    type Error = &'static str;

    fn push_observation(&mut self, image: &[u8], state: &[f32]) -> Result<(), Self::Error> {
        assert_eq!(image.len(), FRAME_BYTES);
        self.clock.advance(self.encode_us);
        let time = state[0];
        if self.history.is_empty() {
            self.history = vec![time; self.n_obs_steps];
        } else {
            self.history.remove(0);
            self.history.push(time);
        }
        self.pushes.push(time);
        Ok(())
    }

    fn infer(
        &mut self,
        prefix: &[f32],
        planned: &[f32],
        chunk: &mut [f32],
    ) -> Result<(), Self::Error> {
        self.planned.push(planned.to_vec());
        let index = self.seen.len();
        self.prefixes.push(prefix.to_vec());
        let cost = self.infer_us[index.min(self.infer_us.len() - 1)];
        self.clock.advance(cost);
        self.seen.push(self.history.clone());
        for (step, action) in chunk.chunks_exact_mut(ACTION_DIM).enumerate() {
            action.copy_from_slice(&[index as f32, step as f32]);
        }
        Ok(())
    }
}

/// What a control tick ran: `(inference, action index)`, or `None` for a hold.
type Executed = Vec<(u64, Option<(usize, usize)>)>;

#[derive(Default)]
struct FakePlant {
    executed: Rc<RefCell<Executed>>,
}

impl Plant for FakePlant {
    fn robot_tick(&mut self, _time_us: u64) {}

    fn command(&mut self, time_us: u64, action: Option<&[f32]>) {
        let ran = action.map(|values| (values[0] as usize, values[1] as usize));
        self.executed.borrow_mut().push((time_us, ran));
    }

    fn capture(&mut self, time_us: u64, image: &mut [u8], state: &mut [f32]) {
        image.fill((time_us / DT) as u8);
        state[0] = time_us as f32 / 1e6;
    }
}

fn timing(steps_per_inference: usize) -> Timing {
    Timing {
        steps_per_inference,
        ..Timing::panda(2, 8)
    }
}

struct Run {
    stats: firmware_demo::LoopStats,
    executed: Executed,
    pushes: Vec<f32>,
    seen: Vec<Vec<f32>>,
    prefixes: Vec<Vec<f32>>,
    planned: Vec<Vec<f32>>,
}

fn run(timing: Timing, encode_us: u64, infer_us: &[u64], until_us: u64) -> Run {
    let clock = FakeClock::default();
    let plant = FakePlant::default();
    let executed = plant.executed.clone();
    let mut frames = vec![0u8; FRAME_SLOTS * FRAME_BYTES];
    let dims = Dims {
        frame_bytes: FRAME_BYTES,
        state_dim: 1,
        action_dim: ACTION_DIM,
    };
    let policy = FakePolicy::new(&clock, encode_us, infer_us);
    let mut control =
        ControlLoop::new(timing, dims, policy, clock, plant, &mut frames).expect("a valid setup");
    control
        .run_until(until_us)
        .expect("the fake policy never fails");
    assert_eq!(control.now_us(), until_us);
    let policy = control.policy();
    Run {
        stats: control.stats().clone(),
        executed: executed.take(),
        pushes: policy.pushes.clone(),
        seen: policy.seen.clone(),
        prefixes: policy.prefixes.clone(),
        planned: policy.planned.clone(),
    }
}

fn held_ticks(run: &Run) -> Vec<u64> {
    run.executed
        .iter()
        .filter(|(_, ran)| ran.is_none())
        .map(|&(time, _)| time)
        .collect()
}

/// Every executed action ran at its own timestamp: the observation time of its chunk (the
/// newest frame its inference saw) plus `index * dt`.
fn assert_actions_run_at_their_time(run: &Run) {
    for &(time, ran) in &run.executed {
        if let Some((inference, index)) = ran {
            let newest_frame = *run.seen[inference].last().unwrap();
            let observed = (f64::from(newest_frame) * 1e6).round() as u64;
            assert_eq!(
                time,
                observed + index as u64 * DT,
                "chunk {inference} action {index}"
            );
        }
    }
}

/// Each inference's committed prefix is what the robot ran at its first times: row `i` is
/// the action executed at the observation time plus `i dt`, and it reaches up to the tick
/// the previous inference's compute time says the chunk arrives by.
#[test]
fn the_committed_prefix_is_what_runs_before_the_chunk_arrives() {
    // Inferences take 150 ms (1.5 ticks) every 4 ticks: from the second on, the prefix has
    // the ticks at the observation and one after it (the observation tick's action comes
    // from the old chunk, the next ends before 150 ms); the old chunk's last 2 actions are
    // planned.
    let run = run(timing(4), 1_000, &[150_000], 6_000_000);
    assert_actions_run_at_their_time(&run);
    assert!(
        run.prefixes[0].is_empty(),
        "nothing runs before the first chunk"
    );
    let mut checked = 0;
    for (inference, prefix) in run.prefixes.iter().enumerate().skip(1) {
        let newest_frame = *run.seen[inference].last().unwrap();
        let observed = (f64::from(newest_frame) * 1e6).round() as u64;
        assert_eq!(prefix.len(), 2 * ACTION_DIM, "inference {inference}");
        for (row, values) in prefix.chunks_exact(ACTION_DIM).enumerate() {
            let time = observed + row as u64 * DT;
            let ran = run
                .executed
                .iter()
                .find(|(at, _)| *at == time)
                .map(|&(_, ran)| ran);
            assert_eq!(
                ran,
                Some(Some((values[0] as usize, values[1] as usize))),
                "inference {inference} row {row}"
            );
            checked += 1;
        }
    }
    assert!(checked >= 24, "{checked}");
    // The planned rows are the old chunk's queued actions for the times after the prefix,
    // which the new chunk replaces: all of the old chunk's that are left.
    for (inference, planned) in run.planned.iter().enumerate().skip(1) {
        let newest_frame = *run.seen[inference].last().unwrap();
        let observed = (f64::from(newest_frame) * 1e6).round() as u64;
        let rows = run.prefixes[inference].len() / ACTION_DIM;
        assert_eq!(planned.len(), 2 * ACTION_DIM, "inference {inference}");
        for (row, values) in planned.chunks_exact(ACTION_DIM).enumerate() {
            let time = observed + (rows + row) as u64 * DT;
            // Stamped for `time` by the chunk before: its observation plus the index.
            let before = inference - 1;
            let before_observed =
                (f64::from(*run.seen[before].last().unwrap()) * 1e6).round() as u64;
            assert_eq!(
                values[0] as usize, before,
                "inference {inference} row {row}"
            );
            assert_eq!(
                before_observed + values[1] as u64 * DT,
                time,
                "inference {inference} row {row}"
            );
        }
    }
    assert_eq!(
        run.stats.prefix_rows,
        run.prefixes
            .iter()
            .map(|p| (p.len() / ACTION_DIM) as u64)
            .sum::<u64>()
    );
    assert_eq!(run.stats.seams.count, run.stats.inferences - 1);
}

#[test]
fn first_observation_fills_the_history_and_the_first_inference_does_not_wait() {
    let run = run(timing(6), 1_000, &[2_000], 650_000);
    // The first inference ran right after the first frame, on a history padded with it.
    assert_eq!(run.seen[0], vec![0.0, 0.0]);
    // Only the frames an inference looks at were encoded: ticks 0, then 5 and 6.
    assert_eq!(run.pushes, vec![0.0, 0.5, 0.6]);
    assert_eq!(run.seen[1], vec![0.5, 0.6]);
    assert_eq!(run.stats.inferences, 2);
    // Tick 0 came before any chunk; from then on the first chunk ran, action 0 stale.
    assert_eq!(run.executed[0], (0, None));
    assert_eq!(run.executed[1], (DT, Some((0, 1))));
    assert_eq!(run.stats.frames_captured, 20);
}

#[test]
fn slow_inference_drops_exactly_the_actions_whose_time_passed() {
    // Inference 2 (observation at 1.2 s) takes 350 ms: it arrives at 1.551 s, after the
    // ticks of its actions 0..=3 (1.2 .. 1.5 s).
    let run = run(
        timing(6),
        1_000,
        &[10_000, 10_000, 350_000, 10_000],
        2_400_000,
    );
    assert_actions_run_at_their_time(&run);
    let from_slow: Vec<usize> = run
        .executed
        .iter()
        .filter_map(|&(_, ran)| ran.filter(|&(inference, _)| inference == 2))
        .map(|(_, index)| index)
        .collect();
    assert_eq!(from_slow, vec![4, 5, 6]);
    // Each fast chunk loses only action 0; the slow one loses 4.
    assert_eq!(run.stats.inferences, 4);
    assert_eq!(run.stats.stale_actions, 3 + 4);
    assert_eq!(run.stats.latency.max(), 351_000);
}

#[test]
fn a_hold_while_an_inference_is_outstanding_is_a_deadline_miss() {
    let slow = run(
        timing(6),
        1_000,
        &[10_000, 10_000, 350_000, 10_000],
        2_400_000,
    );
    // The previous chunk ends at 1.3 s; the slow one starts at 1.6 s.
    assert_eq!(held_ticks(&slow), vec![0, 1_400_000, 1_500_000]);
    assert_eq!(slow.stats.deadline_misses, 1);
    assert_eq!(slow.stats.ticks_held, 2);
    assert_eq!(slow.stats.startup_ticks, 1);

    // 190 ms is inside the budget: one control period after the observation's own tick.
    let in_budget = run(timing(6), 1_000, &[190_000], 2_400_000);
    assert_eq!(in_budget.stats.ticks_held, 0);
    assert_eq!(in_budget.stats.deadline_misses, 0);
    // Before the first chunk the robot waits; those ticks are start-up, not misses.
    assert_eq!(held_ticks(&in_budget), vec![0, 100_000]);
    assert_eq!(in_budget.stats.startup_ticks, 2);

    // One control period more than the budget: every chunk but the first is late.
    let over_budget = run(timing(6), 1_000, &[290_000], 2_400_000);
    assert_eq!(over_budget.stats.inferences, 4);
    assert_eq!(over_budget.stats.deadline_misses, 3);
    assert_eq!(over_budget.stats.ticks_held, 3);
}

#[test]
fn new_chunk_takes_over_from_its_first_valid_timestamp() {
    // Fast: chunk k (observed at 0.6 k s) is in time for its action 1, which replaces action 7
    // of chunk k - 1 for the same tick.
    let fast = run(timing(6), 1_000, &[10_000], 2_400_000);
    assert_actions_run_at_their_time(&fast);
    assert_eq!(fast.stats.inferences, 4);
    assert_eq!(fast.stats.replaced_actions, 3);
    let at = |run: &Run, time: u64| run.executed.iter().find(|(t, _)| *t == time).unwrap().1;
    assert_eq!(at(&fast, 600_000), Some((0, 6)));
    assert_eq!(at(&fast, 700_000), Some((1, 1)));

    // 150 ms: chunk k arrives after its action-1 tick, so action 7 of chunk k - 1 runs there
    // and nothing is replaced; chunk k takes over at action 2 with no tick held.
    let late = run(timing(6), 1_000, &[150_000], 2_400_000);
    assert_actions_run_at_their_time(&late);
    assert_eq!(late.stats.replaced_actions, 0);
    assert_eq!(at(&late, 700_000), Some((0, 7)));
    assert_eq!(at(&late, 800_000), Some((1, 2)));
    assert_eq!(held_ticks(&late), vec![0, 100_000]);
    assert_eq!(late.stats.ticks_held, 0);

    // Every tick ran exactly once, in order, whatever the latency.
    for run in [&fast, &late] {
        let times: Vec<u64> = run.executed.iter().map(|&(time, _)| time).collect();
        let expected: Vec<u64> = (0..24).map(|tick| tick * DT).collect();
        assert_eq!(times, expected);
        let stats = &run.stats;
        assert_eq!(
            stats.actions_executed + stats.ticks_held + stats.startup_ticks,
            24
        );
    }
}

#[test]
fn an_overloaded_processor_skips_inferences_and_drops_frames() {
    // Inference takes 1.3 s with a new one due every 0.6 s: while one runs, the next waits and
    // the one after finds it still waiting.
    let run = run(timing(6), 1_000, &[1_300_000], 6_000_000);
    // Inference 0 runs 0.001 .. 1.301 s. Meanwhile the frames of 0.5 and 0.6 s wait, and are
    // dropped for those of 1.1 and 1.2 s; the inference due at 0.6 s still waits at 1.2 s, so
    // that one is skipped. Waiting frames go first, so inference 1 sees the newest ones.
    assert_eq!(run.seen[0], vec![0.0, 0.0]);
    assert_eq!(run.seen[1], vec![1.1, 1.2]);
    assert_eq!(run.seen[2], vec![2.3, 2.4]);
    assert_eq!(run.stats.inferences, 4);
    assert_eq!(run.stats.skipped_inferences, 4);
    assert_eq!(run.stats.frames_dropped, 9);
    // Two encodes and an inference (1.302 s) per two inference periods (1.2 s): the latency
    // grows by 0.102 s per chunk, 1.301, 1.403, 1.505, 1.607 s.
    assert_eq!(run.stats.latency.max(), 1_607_000);
    // 1.4 s is longer than a whole chunk: every action is stale on arrival.
    assert_eq!(run.stats.actions_executed, 0);
    assert_eq!(run.stats.stale_actions, 4 * 8);
    assert_eq!(run.stats.deadline_misses, 3);
}

#[test]
fn a_processor_too_slow_for_every_frame_still_infers() {
    // Two 400 ms encodes per 600 ms inference period: frames alone would keep the processor
    // busy for ever. At most one history (2 frames) goes ahead of a waiting inference.
    let run = run(timing(6), 400_000, &[10_000], 6_000_000);
    assert!(run.stats.inferences >= 4, "{:?}", run.stats);
    assert!(run.stats.frames_dropped > 0);
    for history in &run.seen {
        assert!(history[0] <= history[1], "{history:?}");
    }
}
