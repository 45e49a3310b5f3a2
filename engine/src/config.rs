//! The model configuration of docs/SPEC.md section 7, as a plain `Copy` value usable in `const`
//! context, so firmware can plan its arena at compile time.

use crate::error::ConfigError;
// Re-exported: the map sizes here are written with it, and dependants found it here.
pub use crate::shape::conv_output;

/// Which normalization the ResNet-18 trunk was trained with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BackboneNorm {
    /// GroupNorm(C/16 groups): Diffusion Policy's choice; stays a runtime operation.
    Group,
    /// Eval-mode BatchNorm: folded into the preceding convolution by the weights tool.
    Batch,
}

/// Number of U-Net levels. The ConditionalUnet1D of docs/SPEC.md has three (`down_dims` has three
/// entries), so the horizon must be divisible by 4.
pub const UNET_LEVELS: usize = 3;

/// Number of feature-pyramid levels (C1..C5 of ResNet-18).
pub const PYRAMID_LEVELS: usize = 5;

/// ResNet's stem convolution: 7x7, stride 2, padding 3, over the three colours. Fixed by
/// torchvision's resnet18, not a field; every map size below follows from it.
pub const STEM_KERNEL: usize = 7;
pub const STEM_STRIDE: usize = 2;
pub const STEM_PADDING: usize = 3;

/// Diffusion Policy builds the U-Net head's Conv1dBlock without passing `n_groups`, so it
/// always has its default of 8 groups, and `down_dims[0]` must divide by it.
pub const FINAL_BLOCK_GROUPS: usize = 8;

/// Every hyper-parameter that shapes a model. Field names follow the TOML of docs/SPEC.md section 7.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ModelConfig {
    pub image_height: u32,
    pub image_width: u32,
    pub imagenet_norm: bool,
    pub backbone_norm: BackboneNorm,
    /// Channels of the first ResNet stage (64 in torchvision's resnet18; the later stages
    /// have 2x, 4x, 8x). A project extension of docs/SPEC.md section 7 so the tiny test model stays
    /// small; real checkpoints always have 64.
    pub backbone_width: u32,
    /// `d`: channels of each projected feature map.
    pub feature_dim: u32,
    /// `To`: frames of observation history.
    pub n_obs_steps: u32,
    pub horizon: u32,
    pub n_action_steps: u32,
    /// `s`: anchors reconstructed from the action chunk (the start point makes s + 1).
    pub reconstruction_horizon: u32,
    pub state_dim: u32,
    pub action_dim: u32,
    pub state_pos_index: [u32; 3],
    pub action_pos_index: [u32; 3],
    pub pos_scale: f32,
    /// U-Net widths; each a multiple of `n_groups`, the first also of 8 (the head's groups).
    pub down_dims: [u32; UNET_LEVELS],
    pub diffusion_step_embed_dim: u32,
    pub kernel_size: u32,
    pub n_groups: u32,
    pub num_train_timesteps: u32,
    pub num_inference_steps: u32,
    pub clip_sample: bool,
}

impl ModelConfig {
    /// The paper's real-robot configuration (docs/SPEC.md section 7).
    pub const PANDA: ModelConfig = ModelConfig {
        image_height: 240,
        image_width: 320,
        imagenet_norm: false,
        backbone_norm: BackboneNorm::Group,
        backbone_width: 64,
        feature_dim: 64,
        n_obs_steps: 2,
        horizon: 16,
        n_action_steps: 8,
        reconstruction_horizon: 8,
        state_dim: 8,
        action_dim: 10,
        state_pos_index: [0, 1, 2],
        action_pos_index: [0, 1, 2],
        pos_scale: 1.0,
        down_dims: [128, 256, 384],
        diffusion_step_embed_dim: 128,
        kernel_size: 5,
        n_groups: 8,
        num_train_timesteps: 100,
        num_inference_steps: 10,
        clip_sample: true,
    };

    /// The simulated benchmark configuration (docs/SPEC.md section 7).
    pub const METAWORLD: ModelConfig = ModelConfig {
        image_height: 128,
        image_width: 128,
        state_dim: 9,
        action_dim: 4,
        pos_scale: 0.01,
        ..ModelConfig::PANDA
    };

    /// A model small enough that a debug-build test runs it instantly. Covers BatchNorm and
    /// ImageNet normalization, which the two named configurations do not.
    pub const TINY: ModelConfig = ModelConfig {
        image_height: 32,
        image_width: 48,
        imagenet_norm: true,
        backbone_norm: BackboneNorm::Batch,
        backbone_width: 8,
        feature_dim: 8,
        n_obs_steps: 2,
        horizon: 8,
        n_action_steps: 4,
        reconstruction_horizon: 4,
        state_dim: 5,
        action_dim: 4,
        state_pos_index: [0, 1, 2],
        action_pos_index: [0, 1, 2],
        pos_scale: 0.1,
        down_dims: [16, 32, 48],
        diffusion_step_embed_dim: 16,
        kernel_size: 3,
        n_groups: 4,
        num_train_timesteps: 100,
        num_inference_steps: 10,
        clip_sample: true,
    };

    /// Checks every rule on the fields the engine and the weights tool rely on.
    /// [`ModelConfig::validate`] adds the one rule that needs the arena plan (its size fits
    /// the address space); it is defined with the plan, in [`crate::plan`], so that this
    /// module stays below everything that is sized from a configuration.
    pub const fn validate_fields(&self) -> Result<(), ConfigError> {
        if self.image_height == 0 || self.image_width == 0 {
            return Err(ConfigError::ZeroImageSize);
        }
        if self.image_height > 4096 || self.image_width > 4096 {
            return Err(ConfigError::ImageTooLarge);
        }
        // GroupNorm needs C/16 groups of at least one channel; BatchNorm has no groups.
        let width_step = match self.backbone_norm {
            BackboneNorm::Group => 16,
            BackboneNorm::Batch => 8,
        };
        if self.backbone_width == 0
            || !self.backbone_width.is_multiple_of(width_step)
            || self.backbone_width > 256
        {
            return Err(ConfigError::BackboneWidth);
        }
        if self.feature_dim == 0 || self.feature_dim > 1024 {
            return Err(ConfigError::FeatureDim);
        }
        if self.n_obs_steps == 0 || self.n_obs_steps > MAX_OBS_STEPS as u32 {
            return Err(ConfigError::ObsSteps);
        }
        if self.horizon == 0 || !self.horizon.is_multiple_of(4) || self.horizon > 256 {
            return Err(ConfigError::HorizonNotMultipleOfFour);
        }
        // Compared with the room left after the history rather than summed: the values may come
        // from an untrusted file, and the sum could overflow.
        if self.n_action_steps == 0
            || self.n_action_steps > self.horizon.saturating_sub(self.n_obs_steps - 1)
        {
            return Err(ConfigError::ActionStepsBeyondHorizon);
        }
        if self.reconstruction_horizon == 0
            || self.reconstruction_horizon > MAX_ANCHOR_STEPS as u32
            || self.n_obs_steps - 1 + self.reconstruction_horizon > self.horizon
        {
            return Err(ConfigError::ReconstructionHorizon);
        }
        if self.state_dim == 0
            || self.state_dim > 256
            || self.action_dim == 0
            || self.action_dim > 256
        {
            return Err(ConfigError::StateOrActionDim);
        }
        let mut i = 0;
        while i < 3 {
            if self.state_pos_index[i] >= self.state_dim {
                return Err(ConfigError::StatePosIndex);
            }
            if self.action_pos_index[i] >= self.action_dim {
                return Err(ConfigError::ActionPosIndex);
            }
            i += 1;
        }
        if !self.pos_scale.is_finite() {
            return Err(ConfigError::PosScale);
        }
        if self.n_groups == 0 {
            return Err(ConfigError::Groups);
        }
        let mut level = 0;
        while level < UNET_LEVELS {
            let dim = self.down_dims[level];
            if dim == 0 || dim > 4096 || !dim.is_multiple_of(self.n_groups) {
                return Err(ConfigError::DownDims);
            }
            level += 1;
        }
        // The head's GroupNorm has Diffusion Policy's default 8 groups whatever n_groups is.
        if !self.down_dims[0].is_multiple_of(FINAL_BLOCK_GROUPS as u32) {
            return Err(ConfigError::DownDims);
        }
        if self.diffusion_step_embed_dim < 4
            || !self.diffusion_step_embed_dim.is_multiple_of(2)
            || self.diffusion_step_embed_dim > 4096
        {
            return Err(ConfigError::StepEmbedDim);
        }
        if self.kernel_size == 0 || self.kernel_size.is_multiple_of(2) || self.kernel_size > 15 {
            return Err(ConfigError::KernelSize);
        }
        if self.num_train_timesteps == 0 || self.num_train_timesteps > 10_000 {
            return Err(ConfigError::TrainTimesteps);
        }
        if self.num_inference_steps == 0
            || self.num_inference_steps > MAX_INFERENCE_STEPS as u32
            || self.num_inference_steps > self.num_train_timesteps
        {
            return Err(ConfigError::InferenceSteps);
        }
        Ok(())
    }

    /// Anchors per denoising step: the current position plus `s` reconstructed ones.
    pub const fn anchor_count(&self) -> usize {
        self.reconstruction_horizon as usize + 1
    }

    /// Length of one frame's pooled context: `5 d`.
    pub const fn context_dim(&self) -> usize {
        PYRAMID_LEVELS * self.feature_dim as usize
    }

    /// Length of the global condition `g`: `To (5 d + state_dim)`.
    pub const fn global_cond_dim(&self) -> usize {
        self.n_obs_steps as usize * (self.context_dim() + self.state_dim as usize)
    }

    /// Length of the U-Net condition `[temb, g]`.
    pub const fn cond_dim(&self) -> usize {
        self.diffusion_step_embed_dim as usize + self.global_cond_dim()
    }

    /// Channels of ResNet stage `stage` (0 = stem and layer1, 3 = layer4).
    pub const fn stage_channels(&self, stage: usize) -> usize {
        (self.backbone_width as usize) << stage
    }

    /// Channels of pyramid tap C(level + 1): C1 and C2 have the stem width, then x2 per stage.
    pub const fn pyramid_channels(&self, level: usize) -> usize {
        if level == 0 {
            self.stage_channels(0)
        } else {
            self.stage_channels(level - 1)
        }
    }

    /// `(height, width)` of the stem convolution's output (stride 2).
    pub const fn stem_size(&self) -> (usize, usize) {
        (
            conv_output(
                self.image_height as usize,
                STEM_KERNEL,
                STEM_STRIDE,
                STEM_PADDING,
            ),
            conv_output(
                self.image_width as usize,
                STEM_KERNEL,
                STEM_STRIDE,
                STEM_PADDING,
            ),
        )
    }

    /// `(height, width)` of pyramid tap C(level + 1), by PyTorch's convolution arithmetic.
    pub const fn pyramid_size(&self, level: usize) -> (usize, usize) {
        let (stem_height, stem_width) = self.stem_size();
        // C1 is the 3x3 stride-2 max pool of the stem; C2 keeps its size; C3..C5 halve it.
        let mut height = conv_output(stem_height, 3, 2, 1);
        let mut width = conv_output(stem_width, 3, 2, 1);
        let mut stage = 2;
        while stage <= level {
            height = conv_output(height, 3, 2, 1);
            width = conv_output(width, 3, 2, 1);
            stage += 1;
        }
        (height, width)
    }

    /// Values of one frame's five projected maps together.
    pub const fn feature_frame_len(&self) -> usize {
        let mut total = 0;
        let mut level = 0;
        while level < PYRAMID_LEVELS {
            let (height, width) = self.pyramid_size(level);
            total += height * width;
            level += 1;
        }
        total * self.feature_dim as usize
    }

    /// Whether projection F(level + 1) is evaluated only at the cells the anchors sample
    /// (on demand, cached per frame) instead of over the whole map at encode time: when the
    /// map has more cells than one inference can touch (steps x points x 4 neighbours).
    pub const fn projection_on_demand(&self, level: usize) -> bool {
        let (height, width) = self.pyramid_size(level);
        height * width > self.num_inference_steps as usize * self.anchor_count() * 4
    }

    /// Groups of a trunk GroupNorm over `channels` (docs/SPEC.md section 2: C/16).
    pub const fn backbone_groups(channels: usize) -> usize {
        channels / 16
    }
}

/// Upper bounds that size fixed arrays inside the engine.
pub const MAX_OBS_STEPS: usize = 8;
pub const MAX_ANCHOR_STEPS: usize = 32;
pub const MAX_INFERENCE_STEPS: usize = 100;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn huge_counts_from_a_file_are_errors_not_overflows() {
        let mut config = ModelConfig::PANDA;
        config.n_action_steps = u32::MAX;
        assert_eq!(
            config.validate(),
            Err(ConfigError::ActionStepsBeyondHorizon)
        );
        config = ModelConfig::PANDA;
        config.reconstruction_horizon = u32::MAX;
        assert_eq!(config.validate(), Err(ConfigError::ReconstructionHorizon));
        config = ModelConfig::PANDA;
        config.n_obs_steps = 8;
        config.horizon = 4;
        config.n_action_steps = 1;
        assert_eq!(
            config.validate(),
            Err(ConfigError::ActionStepsBeyondHorizon)
        );
        assert_eq!(ModelConfig::PANDA.validate(), Ok(()));
    }
}
