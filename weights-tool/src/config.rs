//! The model configuration TOML of docs/SPEC.md section 7, read into and written from the engine's
//! [`ModelConfig`].
//!
//! Parsing is in two passes over the same text: first as a plain table, so that every unknown
//! and every missing key can be listed at once (serde's `deny_unknown_fields` stops at the
//! first), then into a typed struct, so that type errors come with toml's line and column.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::Context as _;
use scdp_engine::error::ConfigError;
use scdp_engine::{BackboneNorm, ModelConfig};
use serde::{Deserialize, Serialize};

/// `backbone_width` is a project extension of docs/SPEC.md section 7; real checkpoints use 64.
pub const DEFAULT_BACKBONE_WIDTH: u32 = 64;

/// Every key the TOML may hold, in the order [`config_to_toml`] writes them.
/// Keep in sync with `ConfigToml`; `OPTIONAL_KEYS` lists the ones with defaults.
const KNOWN_KEYS: [&str; 24] = [
    "image_height",
    "image_width",
    "imagenet_norm",
    "backbone_norm",
    "backbone_width",
    "feature_dim",
    "n_obs_steps",
    "horizon",
    "n_action_steps",
    "reconstruction_horizon",
    "state_dim",
    "action_dim",
    "state_pos_index",
    "action_pos_index",
    "pos_scale",
    "down_dims",
    "diffusion_step_embed_dim",
    "kernel_size",
    "n_groups",
    "num_train_timesteps",
    "num_inference_steps",
    "beta_schedule",
    "clip_sample",
    "prediction_type",
];

/// Keys that may be left out.
const OPTIONAL_KEYS: [&str; 1] = ["backbone_width"];

/// Why a model config TOML was rejected.
#[derive(Debug, thiserror::Error)]
pub enum ConfigParseError {
    #[error("not valid TOML: {0}")]
    Syntax(String),
    #[error("{}", describe_key_sets(.unknown, .missing))]
    Keys {
        unknown: Vec<String>,
        missing: Vec<String>,
    },
    /// A key of the wrong type or an unsupported value, with the offending line.
    #[error("{0}")]
    Value(String),
    #[error("the config cannot run: {0}")]
    Invalid(ConfigError),
}

fn describe_key_sets(unknown: &[String], missing: &[String]) -> String {
    let mut text = String::new();
    if !unknown.is_empty() {
        let _ = write!(text, "unknown keys: {}", unknown.join(", "));
    }
    if !missing.is_empty() {
        if !text.is_empty() {
            text.push_str("; ");
        }
        let _ = write!(text, "missing keys: {}", missing.join(", "));
    }
    text
}

/// The only noise schedule the engine implements (docs/SPEC.md section 5).
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
enum BetaSchedule {
    #[serde(rename = "squaredcos_cap_v2")]
    SquaredcosCapV2,
}

/// The only denoiser output the engine implements (docs/SPEC.md section 5).
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
enum PredictionType {
    #[serde(rename = "epsilon")]
    Epsilon,
}

#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
enum NormName {
    Group,
    Batch,
}

/// The TOML's shape. Field order is the order of docs/SPEC.md section 7 and of the written file.
#[derive(Debug, Serialize, Deserialize)]
struct ConfigToml {
    image_height: u32,
    image_width: u32,
    imagenet_norm: bool,
    backbone_norm: NormName,
    #[serde(default = "default_backbone_width")]
    backbone_width: u32,
    feature_dim: u32,
    n_obs_steps: u32,
    horizon: u32,
    n_action_steps: u32,
    reconstruction_horizon: u32,
    state_dim: u32,
    action_dim: u32,
    state_pos_index: [u32; 3],
    action_pos_index: [u32; 3],
    pos_scale: f32,
    down_dims: [u32; 3],
    diffusion_step_embed_dim: u32,
    kernel_size: u32,
    n_groups: u32,
    num_train_timesteps: u32,
    num_inference_steps: u32,
    beta_schedule: BetaSchedule,
    clip_sample: bool,
    prediction_type: PredictionType,
}

fn default_backbone_width() -> u32 {
    DEFAULT_BACKBONE_WIDTH
}

/// Parses the TOML text of docs/SPEC.md section 7 and validates the result with
/// [`ModelConfig::validate`].
pub fn parse_config(text: &str) -> Result<ModelConfig, ConfigParseError> {
    let table: toml::Table =
        toml::from_str(text).map_err(|error| ConfigParseError::Syntax(one_line(text, &error)))?;
    let unknown: Vec<String> = table
        .keys()
        .filter(|key| !KNOWN_KEYS.contains(&key.as_str()))
        .cloned()
        .collect();
    let missing: Vec<String> = KNOWN_KEYS
        .into_iter()
        .filter(|key| !OPTIONAL_KEYS.contains(key) && !table.contains_key(*key))
        .map(str::to_owned)
        .collect();
    if !unknown.is_empty() || !missing.is_empty() {
        return Err(ConfigParseError::Keys { unknown, missing });
    }
    let parsed: ConfigToml =
        toml::from_str(text).map_err(|error| ConfigParseError::Value(one_line(text, &error)))?;
    let config = ModelConfig::from(&parsed);
    config.validate().map_err(ConfigParseError::Invalid)?;
    Ok(config)
}

/// toml's error as one line: `line N, `key = value`: message` (its own Display draws a
/// multi-line source snippet).
fn one_line(text: &str, error: &toml::de::Error) -> String {
    let message = error.message().trim_end();
    let Some(span) = error.span() else {
        return message.to_owned();
    };
    let start = span.start.min(text.len());
    let line_start = text[..start].rfind('\n').map_or(0, |newline| newline + 1);
    let line_end = text[start..]
        .find('\n')
        .map_or(text.len(), |newline| start + newline);
    let number = text[..start].matches('\n').count() + 1;
    let line = text[line_start..line_end].trim();
    format!("line {number}, `{line}`: {message}")
}

/// Reads and parses a config file; errors name the file.
pub fn load_config(path: &Path) -> anyhow::Result<ModelConfig> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("{}: cannot read the model config", path.display()))?;
    parse_config(&text).with_context(|| format!("{}: bad model config", path.display()))
}

/// Writes `config` as the TOML of docs/SPEC.md section 7 (with `backbone_width` always present), such
/// that [`parse_config`] gives back an equal config.
pub fn config_to_toml(config: &ModelConfig) -> String {
    // Serializing a plain struct of numbers, bools and arrays cannot fail.
    toml::to_string(&ConfigToml::from(config)).expect("a ModelConfig always serializes to TOML")
}

impl From<&ConfigToml> for ModelConfig {
    fn from(toml: &ConfigToml) -> Self {
        ModelConfig {
            image_height: toml.image_height,
            image_width: toml.image_width,
            imagenet_norm: toml.imagenet_norm,
            backbone_norm: match toml.backbone_norm {
                NormName::Group => BackboneNorm::Group,
                NormName::Batch => BackboneNorm::Batch,
            },
            backbone_width: toml.backbone_width,
            feature_dim: toml.feature_dim,
            n_obs_steps: toml.n_obs_steps,
            horizon: toml.horizon,
            n_action_steps: toml.n_action_steps,
            reconstruction_horizon: toml.reconstruction_horizon,
            state_dim: toml.state_dim,
            action_dim: toml.action_dim,
            state_pos_index: toml.state_pos_index,
            action_pos_index: toml.action_pos_index,
            pos_scale: toml.pos_scale,
            down_dims: toml.down_dims,
            diffusion_step_embed_dim: toml.diffusion_step_embed_dim,
            kernel_size: toml.kernel_size,
            n_groups: toml.n_groups,
            num_train_timesteps: toml.num_train_timesteps,
            num_inference_steps: toml.num_inference_steps,
            clip_sample: toml.clip_sample,
        }
    }
}

impl From<&ModelConfig> for ConfigToml {
    fn from(config: &ModelConfig) -> Self {
        ConfigToml {
            image_height: config.image_height,
            image_width: config.image_width,
            imagenet_norm: config.imagenet_norm,
            backbone_norm: match config.backbone_norm {
                BackboneNorm::Group => NormName::Group,
                BackboneNorm::Batch => NormName::Batch,
            },
            backbone_width: config.backbone_width,
            feature_dim: config.feature_dim,
            n_obs_steps: config.n_obs_steps,
            horizon: config.horizon,
            n_action_steps: config.n_action_steps,
            reconstruction_horizon: config.reconstruction_horizon,
            state_dim: config.state_dim,
            action_dim: config.action_dim,
            state_pos_index: config.state_pos_index,
            action_pos_index: config.action_pos_index,
            pos_scale: config.pos_scale,
            down_dims: config.down_dims,
            diffusion_step_embed_dim: config.diffusion_step_embed_dim,
            kernel_size: config.kernel_size,
            n_groups: config.n_groups,
            num_train_timesteps: config.num_train_timesteps,
            num_inference_steps: config.num_inference_steps,
            beta_schedule: BetaSchedule::SquaredcosCapV2,
            clip_sample: config.clip_sample,
            prediction_type: PredictionType::Epsilon,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TINY: &str = include_str!("../../tests/configs/tiny.toml");
    const PANDA: &str = include_str!("../../tests/configs/panda.toml");
    const METAWORLD: &str = include_str!("../../tests/configs/metaworld.toml");

    #[test]
    fn named_configs_parse_to_the_engine_constants() {
        assert_eq!(parse_config(TINY).unwrap(), ModelConfig::TINY);
        assert_eq!(parse_config(PANDA).unwrap(), ModelConfig::PANDA);
        assert_eq!(parse_config(METAWORLD).unwrap(), ModelConfig::METAWORLD);
    }

    #[test]
    fn backbone_width_defaults_to_64() {
        assert!(!PANDA.contains("backbone_width"));
        assert_eq!(parse_config(PANDA).unwrap().backbone_width, 64);
    }

    #[test]
    fn written_toml_parses_back_equal() {
        for config in [
            ModelConfig::TINY,
            ModelConfig::PANDA,
            ModelConfig::METAWORLD,
        ] {
            let text = config_to_toml(&config);
            assert_eq!(parse_config(&text).unwrap(), config, "{text}");
        }
    }

    #[test]
    fn unknown_and_missing_keys_are_all_listed() {
        let text = TINY
            .replace("horizon = 8\n", "horizn = 8\n")
            .replace("kernel_size = 3\n", "")
            .replace(
                "clip_sample = true\n",
                "clip_sample = true\ncolour = \"red\"\n",
            );
        let message = parse_config(&text).unwrap_err().to_string();
        assert_eq!(
            message,
            "unknown keys: colour, horizn; missing keys: horizon, kernel_size"
        );
    }

    #[test]
    fn horizon_not_divisible_by_four_reports_the_engine_rule() {
        let text = TINY.replace("horizon = 8\n", "horizon = 18\n");
        let message = parse_config(&text).unwrap_err().to_string();
        assert!(
            message.contains("horizon must be a positive multiple of 4"),
            "{message}"
        );
    }

    #[test]
    fn wrong_type_names_the_key_expected_and_found() {
        let text = TINY.replace("horizon = 8\n", "horizon = \"eight\"\n");
        let message = parse_config(&text).unwrap_err().to_string();
        assert_eq!(
            message,
            "line 11, `horizon = \"eight\"`: invalid type: string \"eight\", expected u32"
        );
    }

    #[test]
    fn syntax_errors_are_one_line() {
        let message = parse_config("horizon = = 8").unwrap_err().to_string();
        assert!(
            message.starts_with("not valid TOML: line 1, `horizon = = 8`"),
            "{message}"
        );
        assert!(!message.contains('\n'), "{message}");
    }

    #[test]
    fn unsupported_schedule_and_prediction_are_rejected() {
        let text = TINY.replace("\"squaredcos_cap_v2\"", "\"linear\"");
        let message = parse_config(&text).unwrap_err().to_string();
        assert!(message.contains("squaredcos_cap_v2"), "{message}");
        let text = TINY.replace("\"epsilon\"", "\"sample\"");
        let message = parse_config(&text).unwrap_err().to_string();
        assert!(message.contains("epsilon"), "{message}");
    }

    #[test]
    fn integer_pos_scale_is_accepted() {
        let text = PANDA.replace("pos_scale = 1.0", "pos_scale = 1");
        assert_eq!(parse_config(&text).unwrap(), ModelConfig::PANDA);
    }

    #[test]
    fn unknown_backbone_norm_is_rejected() {
        let text = TINY.replace("backbone_norm = \"batch\"", "backbone_norm = \"layer\"");
        let message = parse_config(&text).unwrap_err().to_string();
        assert!(message.contains("backbone_norm"), "{message}");
    }
}
