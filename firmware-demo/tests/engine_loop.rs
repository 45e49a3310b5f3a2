//! The loop with the real engine (tiny model, seeded synthetic weights) behind it.

use firmware_demo::scene::HOME;
use firmware_demo::{
    Calibration, ControlLoop, Dims, EnginePolicy, FRAME_SLOTS, Plant, PolicyPort, SimRobot,
    Stopwatch, Timing,
};
use scdp_engine::{ArenaPlan, Model, ModelConfig, Noise, Policy};
use weights_tool::writer::{AlignedBytes, aligned_copy};
use weights_tool::{Quant, synth_state_dict};

const CONFIG: ModelConfig = ModelConfig::TINY;

fn tiny_weights() -> AlignedBytes {
    let state_dict = synth_state_dict(&CONFIG, 1);
    let bytes = weights_tool::lowering::lower_to_weights_file(&CONFIG, &state_dict, Quant::F32)
        .expect("the tiny model lowers");
    aligned_copy(&bytes)
}

fn frame_bytes() -> usize {
    (CONFIG.image_width * CONFIG.image_height * 3) as usize
}

fn calibration() -> Calibration {
    Calibration::default_for(CONFIG.image_width, CONFIG.image_height)
}

/// Two different observations, rendered by the simulated camera before and after a move.
fn two_observations() -> [(Vec<u8>, Vec<f32>); 2] {
    let timing = Timing::panda(2, 4);
    let mut robot = SimRobot::new(&CONFIG, &timing, calibration()).unwrap();
    let capture = |robot: &mut SimRobot| {
        let mut image = vec![0u8; frame_bytes()];
        let mut state = vec![0f32; CONFIG.state_dim as usize];
        robot.capture(0, &mut image, &mut state);
        (image, state)
    };
    let first = capture(&mut robot);
    robot.command(0, Some(&[1.0, 1.0, 0.0, 0.0]));
    for tick in 0..100 {
        robot.robot_tick(tick * 1000);
    }
    let second = capture(&mut robot);
    assert_ne!(first.0, second.0, "the ball moved in the image");
    [first, second]
}

#[test]
fn first_push_fills_the_history_as_repeating_the_frame_would() {
    let weights = tiny_weights();
    let model = Model::from_bytes(weights.as_slice()).unwrap();
    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&CONFIG).arena_bytes);
    let mut policy = Policy::new(&model, arena.as_mut_slice()).unwrap();
    policy.set_camera(calibration().camera().unwrap());
    let [(image, state), (other_image, other_state)] = two_observations();

    policy.push_observation(&image, &state).unwrap();
    for level in 0..5 {
        let oldest = policy.feature_map(0, level).unwrap().to_vec();
        assert_eq!(
            oldest,
            policy.feature_map(1, level).unwrap(),
            "level {level}"
        );
    }
    let padded = policy.infer(Noise::Seed(3)).unwrap().action_pred().to_vec();

    policy.reset();
    policy.push_observation(&image, &state).unwrap();
    policy.push_observation(&image, &state).unwrap();
    let repeated = policy.infer(Noise::Seed(3)).unwrap().action_pred().to_vec();
    assert_eq!(bits(&padded), bits(&repeated));

    // A different newest frame changes the history and the result.
    policy.push_observation(&other_image, &other_state).unwrap();
    let oldest = policy.feature_map(0, 0).unwrap().to_vec();
    assert_ne!(oldest, policy.feature_map(1, 0).unwrap());
    let moved = policy.infer(Noise::Seed(3)).unwrap().action_pred().to_vec();
    assert_ne!(bits(&padded), bits(&moved));
}

fn bits(values: &[f32]) -> Vec<u32> {
    values.iter().map(|value| value.to_bits()).collect()
}

#[test]
fn engine_port_returns_the_executed_rows_with_fresh_noise_each_time() {
    let weights = tiny_weights();
    let model = Model::from_bytes(weights.as_slice()).unwrap();
    let chunk_len = (CONFIG.n_action_steps * CONFIG.action_dim) as usize;
    let [(image, state), _] = two_observations();

    let mut direct_arena = AlignedBytes::zeroed(ArenaPlan::new(&CONFIG).arena_bytes);
    let mut direct = Policy::new(&model, direct_arena.as_mut_slice()).unwrap();
    direct.set_camera(calibration().camera().unwrap());
    direct.push_observation(&image, &state).unwrap();
    let expected: Vec<[u32; 2]> = (0..2)
        .map(|seed| {
            let actions = direct.infer(Noise::Seed(10 + seed)).unwrap();
            [actions.action()[0].to_bits(), actions.action().len() as u32]
        })
        .collect();

    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&CONFIG).arena_bytes);
    let mut policy = Policy::new(&model, arena.as_mut_slice()).unwrap();
    policy.set_camera(calibration().camera().unwrap());
    let mut port = EnginePolicy::new(policy, 10, None, false);
    port.push_observation(&image, &state).unwrap();
    let mut chunk = vec![0f32; chunk_len];
    for expected in expected {
        port.infer(&[], &[], &mut chunk).unwrap();
        assert_eq!([chunk[0].to_bits(), chunk.len() as u32], expected);
    }
    let path = port.last_path().unwrap();
    assert!(path.start.iter().chain(&path.end).all(|v| v.is_finite()));
}

/// Every engine call "takes" the same time, so a run is reproducible.
struct FixedCost {
    now: u64,
    calls: u64,
    cost_us: u64,
}

impl Stopwatch for FixedCost {
    fn now_us(&mut self) -> u64 {
        // Called before and after each engine call: every second reading is later.
        self.calls += 1;
        if self.calls.is_multiple_of(2) {
            self.now += self.cost_us;
        }
        self.now
    }
}

fn run_loop(seconds: u64) -> (firmware_demo::LoopStats, [f32; 3]) {
    let weights = tiny_weights();
    let model = Model::from_bytes(weights.as_slice()).unwrap();
    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&CONFIG).arena_bytes);
    let mut policy = Policy::new(&model, arena.as_mut_slice()).unwrap();
    policy.set_camera(calibration().camera().unwrap());
    let timing = Timing::panda(2, 4);
    let robot = SimRobot::new(&CONFIG, &timing, calibration()).unwrap();
    let dims = Dims {
        frame_bytes: frame_bytes(),
        state_dim: CONFIG.state_dim as usize,
        action_dim: CONFIG.action_dim as usize,
    };
    let mut frames = vec![0u8; FRAME_SLOTS * dims.frame_bytes];
    let stopwatch = FixedCost {
        now: 0,
        calls: 0,
        cost_us: 20_000,
    };
    let mut control = ControlLoop::new(
        timing,
        dims,
        EnginePolicy::new(policy, 5, None, false),
        stopwatch,
        robot,
        &mut frames,
    )
    .unwrap();
    control.run_until(seconds * 1_000_000).unwrap();
    (control.stats().clone(), control.plant().position())
}

#[test]
fn the_robot_follows_the_policy_reproducibly() {
    let (stats, position) = run_loop(3);
    // Inference ticks every 2 control ticks; 40 ms per chunk (encode + infer) is in time.
    assert_eq!(stats.inferences, 15);
    assert_eq!(stats.deadline_misses, 0);
    assert_eq!(stats.ticks_held, 0);
    assert_eq!(stats.startup_ticks, 1);
    assert_eq!(stats.actions_executed, 29);
    assert_eq!(stats.latency.max(), 40_000);
    assert_ne!(
        position, HOME,
        "the executed actions moved the end effector"
    );
    let (again_stats, again_position) = run_loop(3);
    assert_eq!(again_position.map(f32::to_bits), position.map(f32::to_bits));
    assert_eq!(again_stats.stale_actions, stats.stale_actions);
}
