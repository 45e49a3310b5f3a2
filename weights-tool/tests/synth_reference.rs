//! The Rust generator against values printed by the NumPy one:
//! `python tests/reference/synthetic.py tests/configs/<config>.toml <seed>`.

use scdp_engine::ModelConfig;
use weights_tool::synth::{hex, synth_state_dict, weights_sha256};

#[test]
fn tiny_seed_1_first_values_match_numpy() {
    let state_dict = synth_state_dict(&ModelConfig::TINY, 1);
    let conv1 = &state_dict
        .get("obs_encoder.backbone.conv1.weight")
        .unwrap()
        .data;
    let bits: Vec<u32> = conv1[..4].iter().map(|v| v.to_bits()).collect();
    assert_eq!(bits, [0xbc0c9b70, 0xbd8814b2, 0xbd2dcccf, 0x3cc16028]);
}

#[test]
fn checksums_match_numpy() {
    let cases = [
        (
            ModelConfig::TINY,
            0,
            "d2a286ccc81b4798a0a31191e070558fde768c74770f589777539951255589b0",
        ),
        (
            ModelConfig::TINY,
            1,
            "2e01e33705dbee9408bf9b96acde6f2a80a111b39e42a1ad8b2ed74d72f78a04",
        ),
        (
            ModelConfig::TINY,
            7,
            "13499375444dc25cb77ac961b067d8c52f8f34f04fbfdae11a25b01285d7090b",
        ),
        (
            ModelConfig::TINY,
            u64::MAX,
            "28beecd1cd5ac21be3b98ab928cc33806a9cabfbbbbe13ce9272c44461064375",
        ),
        (
            ModelConfig::PANDA,
            1,
            "931e5fa54e01cc2bb8db746cb2150dc96066ea4cf6225719eccf4ce78765ad26",
        ),
        (
            ModelConfig::METAWORLD,
            1,
            "d0b6b38b15b4a5a3fa5d739889ddc1bf2874548cce56dbf710261466668b1321",
        ),
    ];
    for (config, seed, expected) in cases {
        let digest = hex(&weights_sha256(&synth_state_dict(&config, seed)));
        assert_eq!(digest, expected, "seed {seed}, {config:?}");
    }
}
