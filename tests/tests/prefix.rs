//! A chunk conditioned on a committed prefix (docs/SPEC.md section 5.1): an empty prefix is
//! the plain inference bit for bit, a prefix comes back in its rows and changes the rest,
//! the SIMD backends agree on an int8 file's bits with one, and bad prefixes are errors.
//! The values themselves are pinned to the PyTorch reference by the golden `prefix-*`
//! fixtures (golden.rs, int8_fidelity.rs).

use scdp_engine::{
    ArenaPlan, Backend, Error, Model, ModelConfig, Noise, Policy, Prefix, PrefixMode,
};
use scdp_tests::{available_backends, frontal_camera, synthetic_weights_file_as};
use weights_tool::Quant;
use weights_tool::writer::AlignedBytes;

const MODES: [PrefixMode; 2] = [PrefixMode::Replace, PrefixMode::Noised];

/// A policy of `config` on `weights` with two observations pushed.
fn observed<'w, 'a>(
    model: &'w Model<'w>,
    arena: &'a mut AlignedBytes,
    backend: Backend,
) -> Policy<'w, 'a> {
    let config = *model.config();
    let mut policy = Policy::with_backend(model, arena.as_mut_slice(), backend).unwrap();
    policy.set_camera(frontal_camera(&config));
    let frame = (config.image_height * config.image_width * 3) as usize;
    for f in 0..2usize {
        let image: Vec<u8> = (0..frame).map(|i| ((i * 7 + f * 31) % 256) as u8).collect();
        let state: Vec<f32> = (0..config.state_dim)
            .map(|i| 0.03 * i as f32 - 0.02 + 0.01 * f as f32)
            .collect();
        policy.push_observation(&image, &state).unwrap();
    }
    policy
}

fn bits(values: &[f32]) -> Vec<u32> {
    values.iter().map(|v| v.to_bits()).collect()
}

/// `rows` actions in action units, plausible for the synthetic weights: the plain chunk's
/// own rows a step later, nudged so they are not what the chunk would have said anyway.
fn committed(plain: &[f32], config: &ModelConfig, rows: usize) -> Vec<f32> {
    let action_dim = config.action_dim as usize;
    let first = config.n_obs_steps as usize * action_dim;
    plain[first..first + rows * action_dim]
        .iter()
        .enumerate()
        .map(|(i, v)| v + 0.05 * ((i as f32) * 0.7).sin())
        .collect()
}

#[test]
fn an_empty_prefix_is_the_plain_inference_bit_for_bit() {
    for (config, quant) in [
        (ModelConfig::TINY, Quant::F32),
        (ModelConfig::TINY, Quant::Int8),
        (ModelConfig::METAWORLD, Quant::Int8),
    ] {
        let weights = synthetic_weights_file_as(&config, 3, quant).unwrap();
        let model = Model::from_bytes(weights.as_slice()).unwrap();
        let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&config).arena_bytes);
        for backend in available_backends() {
            let mut policy = observed(&model, &mut arena, backend);
            let plain = bits(policy.infer(Noise::Seed(9)).unwrap().action_pred());
            for mode in MODES {
                let empty = Prefix::new(&[], mode);
                let with = bits(
                    policy
                        .infer_with(Noise::Seed(9), empty)
                        .unwrap()
                        .action_pred(),
                );
                assert_eq!(with, plain, "{quant:?} {backend:?} {mode:?}");
            }
        }
    }
}

#[test]
fn a_prefix_comes_back_in_its_rows_and_steers_the_rest() {
    let config = ModelConfig::METAWORLD;
    let action_dim = config.action_dim as usize;
    let first = (config.n_obs_steps as usize - 1) * action_dim;
    let weights = synthetic_weights_file_as(&config, 3, Quant::F32).unwrap();
    let model = Model::from_bytes(weights.as_slice()).unwrap();
    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&config).arena_bytes);
    let mut policy = observed(&model, &mut arena, Backend::Auto);
    let plain = policy.infer(Noise::Seed(4)).unwrap().action_pred().to_vec();
    for rows in [1, 4, Prefix::max_rows(&config)] {
        let prefix = committed(&plain, &config, rows.min(8));
        let prefix: Vec<f32> = prefix
            .iter()
            .cycle()
            .take(rows * action_dim)
            .copied()
            .collect();
        let mut chunks = Vec::new();
        for mode in MODES {
            let actions = policy
                .infer_with(Noise::Seed(4), Prefix::new(&prefix, mode))
                .unwrap();
            let pred = actions.action_pred().to_vec();
            // The rows are the given actions, normalized and back: within a few f32 ulps.
            for (got, want) in pred[first..first + prefix.len()].iter().zip(&prefix) {
                assert!(
                    (got - want).abs() <= 1e-6 * want.abs().max(1.0),
                    "{mode:?} {rows} rows: {got} for {want}"
                );
            }
            let rest = first + prefix.len();
            if rest < pred.len() {
                assert_ne!(
                    bits(&pred[rest..]),
                    bits(&plain[rest..]),
                    "{mode:?}: the rows after the prefix ignore it"
                );
            }
            chunks.push(pred);
        }
        assert_ne!(bits(&chunks[0]), bits(&chunks[1]), "the modes differ");
    }
    // The old plan after the prefix pulls the rows after it and is not written over them.
    let prefix = committed(&plain, &config, 3);
    let planned: Vec<f32> = committed(&plain, &config, 6)[3 * action_dim..]
        .iter()
        .map(|v| v + 0.2)
        .collect();
    let held = policy
        .infer_with(Noise::Seed(4), Prefix::new(&prefix, PrefixMode::Replace))
        .unwrap()
        .action_pred()
        .to_vec();
    let pulled = policy
        .infer_with(
            Noise::Seed(4),
            Prefix::new(&prefix, PrefixMode::Replace).with_planned(&planned),
        )
        .unwrap()
        .action_pred()
        .to_vec();
    let after = first + prefix.len();
    assert_eq!(bits(&pulled[first..after]), bits(&held[first..after]));
    let distance = |chunk: &[f32]| -> f32 {
        chunk[after..after + planned.len()]
            .iter()
            .zip(&planned)
            .map(|(a, b)| (a - b).abs())
            .sum()
    };
    assert!(
        distance(&pulled) < distance(&held),
        "the planned rows pull: {} vs {}",
        distance(&pulled),
        distance(&held)
    );
    assert_ne!(bits(&pulled[after..after + planned.len()]), bits(&planned));
}

/// The int8 convolutions are exact on every backend and the SIMD backends share their f32
/// order (the scalar reference's f32 parts differ in the last bits): one answer per file.
#[test]
fn simd_backends_agree_on_an_int8_chunk_with_a_prefix() {
    let config = ModelConfig::METAWORLD;
    let weights = synthetic_weights_file_as(&config, 3, Quant::Int8).unwrap();
    let model = Model::from_bytes(weights.as_slice()).unwrap();
    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&config).arena_bytes);
    let simd: Vec<Backend> = available_backends()
        .into_iter()
        .filter(|backend| *backend != Backend::Scalar)
        .collect();
    let plain = observed(&model, &mut arena, Backend::Scalar)
        .infer(Noise::Seed(6))
        .unwrap()
        .action_pred()
        .to_vec();
    let prefix = committed(&plain, &config, 4);
    for mode in MODES {
        let mut answers = Vec::new();
        for &backend in &simd {
            let mut policy = observed(&model, &mut arena, backend);
            let actions = policy
                .infer_with(Noise::Seed(6), Prefix::new(&prefix, mode))
                .unwrap();
            answers.push((backend, bits(actions.action_pred())));
        }
        for (backend, answer) in &answers[1..] {
            assert_eq!(
                answer, &answers[0].1,
                "{mode:?}: {backend:?} and {:?}",
                answers[0].0
            );
        }
    }
}

#[test]
fn bad_prefixes_are_errors() {
    let config = ModelConfig::TINY;
    let action_dim = config.action_dim as usize;
    let max_rows = Prefix::max_rows(&config);
    assert_eq!(max_rows, (config.horizon - config.n_obs_steps + 1) as usize);
    let weights = synthetic_weights_file_as(&config, 3, Quant::F32).unwrap();
    let model = Model::from_bytes(weights.as_slice()).unwrap();
    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&config).arena_bytes);
    let mut policy = observed(&model, &mut arena, Backend::Auto);
    let size_error = |found| Error::PrefixSize {
        max_rows,
        action_dim,
        found,
    };
    for (values, expected) in [
        (vec![0.1; action_dim + 1], size_error(action_dim + 1)),
        (
            vec![0.1; (max_rows + 1) * action_dim],
            size_error((max_rows + 1) * action_dim),
        ),
        (vec![0.1, f32::NAN, 0.2, 0.3], Error::NonFinitePrefix),
        (vec![f32::INFINITY; action_dim], Error::NonFinitePrefix),
    ] {
        for mode in MODES {
            let result = policy.infer_with(Noise::Seed(1), Prefix::new(&values, mode));
            assert_eq!(result.err(), Some(expected), "{values:?} {mode:?}");
        }
    }
    // The planned rows count with the committed ones and are checked the same way.
    let full = vec![0.1; max_rows * action_dim];
    let one = vec![0.1; action_dim];
    for (committed, planned, expected) in [
        (&full[..], &one[..], size_error((max_rows + 1) * action_dim)),
        (&one[..], &one[..1], size_error(action_dim + 1)),
        (
            &one[..],
            &[0.0, f32::NAN, 0.0, 0.0][..],
            Error::NonFinitePrefix,
        ),
    ] {
        let prefix = Prefix::new(committed, PrefixMode::Replace).with_planned(planned);
        let result = policy.infer_with(Noise::Seed(1), prefix);
        assert_eq!(result.err(), Some(expected), "{committed:?} {planned:?}");
    }
    // The longest prefix is accepted.
    let longest = vec![0.01; max_rows * action_dim];
    assert!(
        policy
            .infer_with(Noise::Seed(1), Prefix::new(&longest, PrefixMode::Noised))
            .is_ok()
    );
}
