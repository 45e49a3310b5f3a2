//! Error values. Every failure the engine can meet on bad input is one of these; it never
//! panics on input.

use core::fmt;

/// A model configuration the engine cannot run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum ConfigError {
    ZeroImageSize,
    ImageTooLarge,
    BackboneWidth,
    FeatureDim,
    ObsSteps,
    HorizonNotMultipleOfFour,
    ActionStepsBeyondHorizon,
    ReconstructionHorizon,
    StateOrActionDim,
    StatePosIndex,
    ActionPosIndex,
    PosScale,
    DownDims,
    Groups,
    StepEmbedDim,
    KernelSize,
    TrainTimesteps,
    InferenceSteps,
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::ZeroImageSize => "image_height and image_width must be positive",
            Self::ImageTooLarge => "image_height and image_width must be at most 4096",
            Self::BackboneWidth => {
                "backbone_width must be a positive multiple of 16 (GroupNorm) or 8 (BatchNorm), at most 256"
            }
            Self::FeatureDim => "feature_dim must be in 1..=1024",
            Self::ObsSteps => "n_obs_steps must be in 1..=8",
            Self::HorizonNotMultipleOfFour => "horizon must be a positive multiple of 4, at most 256",
            Self::ActionStepsBeyondHorizon => {
                "n_obs_steps - 1 + n_action_steps must not exceed horizon"
            }
            Self::ReconstructionHorizon => {
                "reconstruction_horizon must be in 1..=32 and n_obs_steps - 1 + reconstruction_horizon must not exceed horizon"
            }
            Self::StateOrActionDim => "state_dim and action_dim must be in 1..=256",
            Self::StatePosIndex => "state_pos_index entries must be below state_dim",
            Self::ActionPosIndex => "action_pos_index entries must be below action_dim",
            Self::PosScale => "pos_scale must be finite",
            Self::DownDims => "down_dims entries must be positive multiples of n_groups, at most 4096",
            Self::Groups => "n_groups must be positive",
            Self::StepEmbedDim => "diffusion_step_embed_dim must be even, in 4..=4096",
            Self::KernelSize => "kernel_size must be odd, at most 15",
            Self::TrainTimesteps => "num_train_timesteps must be in 1..=10000",
            Self::InferenceSteps => {
                "num_inference_steps must be in 1..=100 and at most num_train_timesteps"
            }
        })
    }
}

impl core::error::Error for ConfigError {}
