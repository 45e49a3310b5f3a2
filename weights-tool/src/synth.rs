//! The seeded weight generator of docs/SYNTHETIC.md. `tests/reference/synthetic.py`
//! implements the same contract in NumPy; the two must agree bit for bit, so every formula
//! below is evaluated in f64 in the order the document writes it and rounded to f32 once.

use scdp_engine::ModelConfig;
use sha2::{Digest, Sha256};

use crate::keys::expected_keys;
use crate::state_dict::{Source, StateDict, Tensor};

const FNV_OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
const FNV_PRIME: u64 = 0x0000_0100_0000_01b3;
const GOLDEN_GAMMA: u64 = 0x9e37_79b9_7f4a_7c15;

/// FNV-1a, 64-bit.
pub fn fnv1a64(bytes: &[u8]) -> u64 {
    bytes.iter().fold(FNV_OFFSET, |hash, &byte| {
        (hash ^ u64::from(byte)).wrapping_mul(FNV_PRIME)
    })
}

/// The splitmix64 output function.
pub fn mix64(z: u64) -> u64 {
    let z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    let z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Element `index` of the stream for `key`: uniform in [-1, 1) with 24-bit resolution.
fn uniform(base: u64, index: u64) -> f64 {
    let z = mix64(base.wrapping_add(index.wrapping_add(1).wrapping_mul(GOLDEN_GAMMA)));
    let u = (z >> 40) as f64 / (1u64 << 24) as f64;
    2.0 * u - 1.0
}

/// How a key's values are made from its stream (the first matching row of the doc's table).
#[derive(Clone, Copy, Debug, PartialEq)]
enum Rule {
    /// `offset + scale * r`.
    Affine { offset: f64, scale: f64 },
    /// `factor * (1 + 0.2 r)`: the normalizer scales.
    PositiveScale { factor: f64 },
    /// `gain * r / sqrt(fan_in)`.
    FanIn { gain: f64, fan_in: usize },
}

fn rule_for(key: &str, shape: &[usize], config: &ModelConfig) -> Rule {
    let affine = |offset, scale| Rule::Affine { offset, scale };
    if key.ends_with(".running_mean") {
        affine(0.0, 0.1)
    } else if key.ends_with(".running_var") {
        affine(1.0, 0.25)
    } else if key == "normalizer.params_dict.action.scale" {
        Rule::PositiveScale {
            factor: 25.0 * f64::from(config.pos_scale),
        }
    } else if key == "normalizer.params_dict.agent_pos.scale" {
        Rule::PositiveScale { factor: 1.0 }
    } else if key.starts_with("normalizer.params_dict.") && key.ends_with(".offset")
        || key.ends_with(".bias")
    {
        // Two rows of the doc's table with the same rule.
        affine(0.0, 0.1)
    } else if key.ends_with(".weight") && shape.len() == 1 {
        affine(1.0, 0.1)
    } else if key.ends_with(".weight") {
        Rule::FanIn {
            gain: gain(key),
            fan_in: shape[1..].iter().product(),
        }
    } else {
        // expected_keys lists nothing else; a new kind of key needs a row in the doc first.
        panic!("docs/SYNTHETIC.md has no rule for {key}")
    }
}

/// The doc's gain table is empty: every key has gain 1.
fn gain(_key: &str) -> f64 {
    1.0
}

impl Rule {
    fn value(self, r: f64) -> f32 {
        let value = match self {
            Rule::Affine { offset, scale } => offset + scale * r,
            Rule::PositiveScale { factor } => factor * (1.0 + 0.2 * r),
            Rule::FanIn { gain, fan_in } => gain * r / (fan_in as f64).sqrt(),
        };
        value as f32
    }
}

/// The values of one key.
pub fn synth_tensor(config: &ModelConfig, seed: u64, key: &str, shape: &[usize]) -> Tensor {
    let rule = rule_for(key, shape, config);
    let base = seed ^ fnv1a64(key.as_bytes());
    let numel: usize = shape.iter().product();
    let data = (0..numel as u64)
        .map(|index| rule.value(uniform(base, index)))
        .collect();
    Tensor::new(shape.to_vec(), data)
}

/// The full state dict of docs/SPEC.md section 6 for `(config, seed)`.
pub fn synth_state_dict(config: &ModelConfig, seed: u64) -> StateDict {
    let mut state_dict = StateDict::new(Source::Synthetic { seed });
    for (key, shape) in expected_keys(config) {
        let tensor = synth_tensor(config, seed, &key, &shape);
        state_dict.insert(key, tensor);
    }
    state_dict
}

/// The doc's checksum: for each key in bytewise order (`num_batches_tracked` excluded) the
/// key's UTF-8 bytes, a 0 byte, the rank and the dimensions as u64 LE, the values as f32 LE.
pub fn weights_sha256(state_dict: &StateDict) -> [u8; 32] {
    let mut hasher = Sha256::new();
    // BTreeMap<String, _> iterates in bytewise key order.
    for (key, tensor) in &state_dict.tensors {
        if key.ends_with(".num_batches_tracked") {
            continue;
        }
        hasher.update(key.as_bytes());
        hasher.update([0u8]);
        hasher.update((tensor.shape.len() as u64).to_le_bytes());
        for &dim in &tensor.shape {
            hasher.update((dim as u64).to_le_bytes());
        }
        for &value in &tensor.data {
            hasher.update(value.to_le_bytes());
        }
    }
    hasher.finalize().into()
}

/// Lower-case hex, as the fixtures record it.
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|byte| format!("{byte:02x}")).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fnv1a64_published_vectors() {
        // From the FNV reference test suite (Noll, "FNV hash" test vectors).
        assert_eq!(fnv1a64(b""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(fnv1a64(b"a"), 0xaf63_dc4c_8601_ec8c);
        assert_eq!(fnv1a64(b"foobar"), 0x8594_4171_f739_67e8);
    }

    #[test]
    fn mix64_is_splitmix64() {
        // splitmix64 seeded with 0 (Vigna's reference splitmix64.c): the generator adds the
        // golden gamma to its state and then mixes, so outputs are mix64(k * gamma).
        let expected = [
            0xe220_a839_7b1d_cdaf_u64,
            0x6e78_9e6a_a1b9_65f4,
            0x06c4_5d18_8009_454f,
        ];
        for (k, value) in expected.into_iter().enumerate() {
            assert_eq!(mix64(GOLDEN_GAMMA.wrapping_mul(k as u64 + 1)), value);
        }
    }

    #[test]
    fn uniform_is_24_bit_in_range() {
        let base = 7 ^ fnv1a64(b"x.weight");
        for index in 0..1000 {
            let r = uniform(base, index);
            assert!((-1.0..1.0).contains(&r));
            // 2u - 1 with u = m / 2^24: r * 2^23 is an integer.
            assert_eq!((r * f64::from(1 << 23)).fract(), 0.0);
        }
    }

    #[test]
    fn rules_follow_the_table() {
        let config = ModelConfig::TINY;
        let rule = |key, shape: &[usize]| rule_for(key, shape, &config);
        assert_eq!(
            rule("obs_encoder.backbone.bn1.running_var", &[8]),
            Rule::Affine {
                offset: 1.0,
                scale: 0.25
            }
        );
        assert_eq!(
            rule("obs_encoder.backbone.bn1.weight", &[8]),
            Rule::Affine {
                offset: 1.0,
                scale: 0.1
            }
        );
        assert_eq!(
            rule("obs_encoder.backbone.conv1.weight", &[8, 3, 7, 7]),
            Rule::FanIn {
                gain: 1.0,
                fan_in: 147
            }
        );
        assert_eq!(
            rule("normalizer.params_dict.action.offset", &[4]),
            Rule::Affine {
                offset: 0.0,
                scale: 0.1
            }
        );
        assert_eq!(
            rule("normalizer.params_dict.action.scale", &[4]),
            Rule::PositiveScale {
                factor: 25.0 * f64::from(0.1f32)
            }
        );
    }

    #[test]
    fn values_depend_on_key_seed_and_index_only() {
        let config = ModelConfig::TINY;
        let a = synth_tensor(&config, 1, "model.final_conv.1.bias", &[4]);
        let b = synth_tensor(&config, 1, "model.final_conv.1.bias", &[4]);
        let c = synth_tensor(&config, 2, "model.final_conv.1.bias", &[4]);
        assert_eq!(a, b);
        assert_ne!(a, c);
        let longer = synth_tensor(&config, 1, "model.final_conv.1.bias", &[8]);
        assert_eq!(a.data, longer.data[..4]);
    }

    #[test]
    fn first_value_by_hand() {
        // Element 0 of tiny seed 1's conv1 weight, from the doc's formulas step by step.
        let key = "obs_encoder.backbone.conv1.weight";
        let base = 1 ^ fnv1a64(key.as_bytes());
        let z = mix64(base.wrapping_add(GOLDEN_GAMMA));
        let r = 2.0 * ((z >> 40) as f64 / 16_777_216.0) - 1.0;
        let expected = (r / 147f64.sqrt()) as f32;
        let tensor = synth_tensor(&ModelConfig::TINY, 1, key, &[8, 3, 7, 7]);
        assert_eq!(tensor.data[0].to_bits(), expected.to_bits());
    }

    #[test]
    fn checksum_covers_keys_shapes_and_values() {
        let state_dict = synth_state_dict(&ModelConfig::TINY, 1);
        let digest = weights_sha256(&state_dict);
        let mut changed = state_dict.clone();
        changed
            .tensors
            .get_mut("model.final_conv.1.bias")
            .unwrap()
            .data[3] += 1.0;
        assert_ne!(weights_sha256(&changed), digest);
        let mut reshaped = state_dict.clone();
        reshaped
            .tensors
            .get_mut("model.final_conv.1.bias")
            .unwrap()
            .shape = vec![2, 2];
        assert_ne!(weights_sha256(&reshaped), digest);
        let mut counted = state_dict;
        counted.insert(
            "obs_encoder.backbone.bn1.num_batches_tracked".into(),
            Tensor::new(vec![], vec![0.0]),
        );
        assert_eq!(weights_sha256(&counted), digest);
    }

    #[test]
    fn sha256_of_empty_state_dict_is_sha256_of_nothing() {
        let empty = StateDict::new(Source::Safetensors);
        assert_eq!(
            hex(&weights_sha256(&empty)),
            "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855"
        );
    }
}
