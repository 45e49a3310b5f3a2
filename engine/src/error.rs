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
    /// The buffers of one inference exceed the address space (32-bit targets).
    ArenaTooLarge,
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
            Self::DownDims => "down_dims entries must be positive multiples of n_groups (the first also of 8), at most 4096",
            Self::Groups => "n_groups must be positive",
            Self::StepEmbedDim => "diffusion_step_embed_dim must be even, in 4..=4096",
            Self::KernelSize => "kernel_size must be odd, at most 15",
            Self::TrainTimesteps => "num_train_timesteps must be in 1..=10000",
            Self::InferenceSteps => {
                "num_inference_steps must be in 1..=100 and at most num_train_timesteps"
            }
            Self::ArenaTooLarge => {
                "the arena this configuration needs exceeds the address space"
            }
        })
    }
}

impl core::error::Error for ConfigError {}

/// Everything that can go wrong when loading weights or running the policy.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum Error {
    /// The weights bytes do not start at a 64-byte boundary (wrap them in `Aligned`).
    MisalignedBuffer,
    /// The weights bytes end before the header, table or a tensor says they do.
    Truncated,
    /// Not a weights file.
    BadMagic,
    /// A weights file from another format version than the one this engine reads
    /// (`supported`, [`crate::format::VERSION`]).
    UnsupportedVersion { found: u32, supported: u32 },
    /// Inconsistent header fields.
    BadHeader,
    /// The bytes were altered after the tool wrote them.
    ChecksumMismatch,
    /// The config record has values no config can have.
    BadConfigRecord,
    /// The config record decodes but cannot run.
    Config(ConfigError),
    /// Table row `index` points outside the file, overlaps, is misaligned or inconsistent.
    BadTensorEntry { index: usize },
    /// The table ends before tensor `index` the model needs.
    MissingTensor { index: usize },
    /// Tensor `index` is not the one the model needs at that position (name, dtype or dims).
    UnexpectedTensor { index: usize },
    /// The table holds more tensors than the model uses.
    ExtraTensors,
    /// The weights were made for another config than the one the caller planned for.
    ConfigMismatch,
    /// The arena is smaller than the plan for this config.
    ArenaTooSmall { needed: usize, found: usize },
    /// The arena does not start at a 64-byte boundary.
    MisalignedArena,
    /// The requested kernel backend cannot run on this CPU.
    BackendUnavailable,
    /// An image of the wrong byte length for `image_height x image_width x 3`.
    ImageSize { expected: usize, found: usize },
    /// A state vector of the wrong length.
    StateSize { expected: usize, found: usize },
    /// A noise array of the wrong length.
    NoiseSize { expected: usize, found: usize },
    /// NaN or infinity in a state vector.
    NonFiniteState,
    /// NaN or infinity in the given noise.
    NonFiniteNoise,
    /// A committed prefix or planned continuation that is not whole rows of `action_dim`
    /// values, or the two with more rows than the horizon holds after the observation steps
    /// (`horizon - n_obs_steps + 1`).
    PrefixSize {
        max_rows: usize,
        action_dim: usize,
        found: usize,
    },
    /// NaN or infinity in a committed prefix or its planned rows.
    NonFinitePrefix,
    /// Intrinsics with a non-positive or non-finite focal length, or non-finite centre.
    BadIntrinsics,
    /// Extrinsics that are not a finite rigid transform.
    BadExtrinsics,
    /// `infer` before a camera was set.
    NoCamera,
    /// `infer` before any observation was pushed.
    NoObservation,
    /// Denoising step `step` produced NaN or infinity; no action is returned.
    NonFiniteResult { step: usize },
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::MisalignedBuffer => f.write_str("weights buffer is not 64-byte aligned"),
            Self::Truncated => f.write_str("weights file is truncated"),
            Self::BadMagic => f.write_str("not an SCDP weights file (bad magic)"),
            Self::UnsupportedVersion { found, supported } => write!(
                f,
                "weights file format version {found}; this engine reads version {supported}"
            ),
            Self::BadHeader => f.write_str("weights file header is inconsistent"),
            Self::ChecksumMismatch => f.write_str("weights file checksum does not match"),
            Self::BadConfigRecord => f.write_str("weights file config record is invalid"),
            Self::Config(error) => write!(f, "weights file config cannot run: {error}"),
            Self::BadTensorEntry { index } => write!(f, "weights tensor entry {index} is invalid"),
            Self::MissingTensor { index } => write!(f, "weights file lacks tensor {index}"),
            Self::UnexpectedTensor { index } => {
                write!(
                    f,
                    "weights tensor {index} is not the one this model needs there"
                )
            }
            Self::ExtraTensors => f.write_str("weights file has more tensors than the model uses"),
            Self::ConfigMismatch => {
                f.write_str("weights file config differs from the config the arena was planned for")
            }
            Self::ArenaTooSmall { needed, found } => {
                write!(f, "arena has {found} bytes; the plan needs {needed}")
            }
            Self::MisalignedArena => f.write_str("arena is not 64-byte aligned"),
            Self::BackendUnavailable => {
                f.write_str("the requested kernel backend cannot run on this CPU")
            }
            Self::ImageSize { expected, found } => {
                write!(
                    f,
                    "image has {found} bytes; expected {expected} (H x W x 3)"
                )
            }
            Self::StateSize { expected, found } => {
                write!(f, "state has {found} values; expected {expected}")
            }
            Self::NoiseSize { expected, found } => {
                write!(f, "noise has {found} values; expected {expected}")
            }
            Self::NonFiniteState => f.write_str("state contains NaN or infinity"),
            Self::NonFiniteNoise => f.write_str("noise contains NaN or infinity"),
            Self::PrefixSize {
                max_rows,
                action_dim,
                found,
            } => write!(
                f,
                "prefix has {found} values; expected whole rows of {action_dim}, at most {max_rows} rows with the planned ones"
            ),
            Self::NonFinitePrefix => {
                f.write_str("prefix or planned actions contain NaN or infinity")
            }
            Self::BadIntrinsics => f.write_str("camera intrinsics are not a valid pinhole matrix"),
            Self::BadExtrinsics => {
                f.write_str("camera extrinsics are not a finite rigid transform")
            }
            Self::NoCamera => f.write_str("no camera calibration has been set"),
            Self::NoObservation => f.write_str("no observation has been pushed"),
            Self::NonFiniteResult { step } => {
                write!(f, "denoising step {step} produced non-finite values")
            }
        }
    }
}

impl core::error::Error for Error {}

impl From<ConfigError> for Error {
    fn from(error: ConfigError) -> Self {
        Error::Config(error)
    }
}
