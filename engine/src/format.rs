//! The weights file (docs/FORMAT.md): a validated, zero-copy view of borrowed bytes.
//!
//! Everything is checked once, at [`WeightsFile::parse`]: magic, version, sizes, checksum,
//! the config record and every table entry (offset, length, alignment, overlap). After that
//! tensors are read in place, so the bytes can live in flash.

use crate::config::{BackboneNorm, ModelConfig, UNET_LEVELS};
use crate::error::Error as LoadError;
use crate::shape::{int8_pair_stored_elements, int8_stored_elements};

/// First eight bytes of every weights file.
pub const MAGIC: [u8; 8] = *b"SCDPWTS\0";
/// The format version this engine reads and the tool writes. Version 2: int8 kernels of
/// 2-D convolutions are stored in input-channel quads; version 3: those of 1-D convolutions
/// too; version 4: the quads in blocks of 64 output channels; version 5: the U-Net's
/// transposed convolutions lowered to ordinary convolutions, stored like them (int8 where
/// the tool chooses; docs/FORMAT.md); version 6: those lowered to 2 taps, without the third
/// tap's zeros.
pub const VERSION: u32 = 6;
/// Every section and tensor starts at a multiple of this, so SIMD loads can be aligned.
pub const ALIGN: usize = 64;
pub const HEADER_BYTES: usize = 64;
pub const CONFIG_BYTES: usize = 256;
pub const ENTRY_BYTES: usize = 96;
pub const NAME_BYTES: usize = 56;
pub const MAX_RANK: usize = 4;
/// Byte range of the checksum inside the header; it is hashed as zeros.
pub const CHECKSUM_RANGE: core::ops::Range<usize> = 24..32;

/// Element type of a stored tensor.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u32)]
pub enum DType {
    F32 = 0,
    /// int8 weights whose layer quantizes its input to 15-bit codes (the precise scheme).
    I8 = 1,
    /// int8 weights whose layer quantizes its input to 8-bit unsigned codes, one byte a
    /// value: half the integer products of [`DType::I8`]'s trunk layers. Only the residual
    /// blocks' convolutions, whose inputs are ReLU outputs, take it (docs/QUANTIZATION.md).
    I8Narrow = 2,
    /// [`DType::I8`] with a second int8 plane after the first: the first plane's rounding
    /// error quantized again, with its own per-channel scales (the scale tensor is
    /// `[2, channels]`), so `value = q * scale + r * residual_scale`, about 15-bit weights.
    /// The layer runs its convolution once per plane on the same input codes. Only the
    /// residual blocks' convolutions take it.
    I8Refined = 3,
    /// [`DType::I8Narrow`]'s input codes with [`DType::I8Refined`]'s two weight planes.
    I8NarrowRefined = 4,
    /// The values of the 8-bit weight two entries before (its scales between), again in the
    /// pair layout (eight inputs a group, [`crate::shape::int8_pair_index`]), for the
    /// backends whose matrix multiplies take 2 x 8 operands. Optional; named
    /// `NAME.pairs`, with the weight's dims.
    I8Pairs = 5,
    /// [`DType::I8Pairs`] of a refined weight: both planes, each in the pair layout.
    I8RefinedPairs = 6,
}

impl DType {
    pub const fn from_code(code: u32) -> Option<DType> {
        match code {
            0 => Some(DType::F32),
            1 => Some(DType::I8),
            2 => Some(DType::I8Narrow),
            3 => Some(DType::I8Refined),
            4 => Some(DType::I8NarrowRefined),
            5 => Some(DType::I8Pairs),
            6 => Some(DType::I8RefinedPairs),
            _ => None,
        }
    }

    pub const fn size(self) -> usize {
        match self {
            DType::F32 => 4,
            DType::I8 | DType::I8Narrow | DType::I8Pairs => 1,
            DType::I8Refined | DType::I8NarrowRefined | DType::I8RefinedPairs => 2,
        }
    }

    /// Whether the tensor holds a second weight plane ([`DType::I8Refined`]).
    pub const fn is_refined(self) -> bool {
        matches!(
            self,
            DType::I8Refined | DType::I8NarrowRefined | DType::I8RefinedPairs
        )
    }

    /// Whether the tensor is a weight's pair layout ([`DType::I8Pairs`]).
    pub const fn is_pairs(self) -> bool {
        matches!(self, DType::I8Pairs | DType::I8RefinedPairs)
    }
}

/// How the weights of convolutions and linear layers are stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u32)]
pub enum Quant {
    F32 = 0,
    Int8 = 1,
}

/// FNV-1a over little-endian 64-bit words: simple enough to re-implement from the docs,
/// eight times faster than the byte-wise FNV on a 100 MB file. The checksum field is read
/// as zero.
pub fn checksum(bytes: &[u8]) -> u64 {
    const OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
    const PRIME: u64 = 0x0000_0100_0000_01b3;
    let mut hash = OFFSET;
    for (index, word) in bytes.chunks(8).enumerate() {
        let mut padded = [0u8; 8];
        padded[..word.len()].copy_from_slice(word);
        let value = if index == CHECKSUM_RANGE.start / 8 {
            0
        } else {
            u64::from_le_bytes(padded)
        };
        hash = (hash ^ value).wrapping_mul(PRIME);
    }
    hash
}

fn u32_at(bytes: &[u8], at: usize) -> u32 {
    let mut word = [0u8; 4];
    word.copy_from_slice(&bytes[at..at + 4]);
    u32::from_le_bytes(word)
}

fn u64_at(bytes: &[u8], at: usize) -> u64 {
    let mut word = [0u8; 8];
    word.copy_from_slice(&bytes[at..at + 8]);
    u64::from_le_bytes(word)
}

fn f32_at(bytes: &[u8], at: usize) -> f32 {
    f32::from_bits(u32_at(bytes, at))
}

/// The config record: 64 little-endian 32-bit slots, in the order below. Unused slots are 0.
pub fn encode_config(config: &ModelConfig) -> [u8; CONFIG_BYTES] {
    let mut slots = [0u32; CONFIG_BYTES / 4];
    let fields: [u32; 31] = [
        config.image_height,
        config.image_width,
        config.imagenet_norm as u32,
        match config.backbone_norm {
            BackboneNorm::Group => 0,
            BackboneNorm::Batch => 1,
        },
        config.backbone_width,
        config.feature_dim,
        config.n_obs_steps,
        config.horizon,
        config.n_action_steps,
        config.reconstruction_horizon,
        config.state_dim,
        config.action_dim,
        config.state_pos_index[0],
        config.state_pos_index[1],
        config.state_pos_index[2],
        config.action_pos_index[0],
        config.action_pos_index[1],
        config.action_pos_index[2],
        config.pos_scale.to_bits(),
        config.down_dims[0],
        config.down_dims[1],
        config.down_dims[2],
        config.diffusion_step_embed_dim,
        config.kernel_size,
        config.n_groups,
        config.num_train_timesteps,
        config.num_inference_steps,
        config.clip_sample as u32,
        // beta_schedule: 0 = squaredcos_cap_v2, prediction_type: 0 = epsilon (the only ones).
        0,
        0,
        UNET_LEVELS as u32,
    ];
    slots[..fields.len()].copy_from_slice(&fields);
    let mut bytes = [0u8; CONFIG_BYTES];
    for (chunk, slot) in bytes.chunks_exact_mut(4).zip(slots) {
        chunk.copy_from_slice(&slot.to_le_bytes());
    }
    bytes
}

fn decode_bool(value: u32) -> Result<bool, LoadError> {
    match value {
        0 => Ok(false),
        1 => Ok(true),
        _ => Err(LoadError::BadConfigRecord),
    }
}

pub fn decode_config(bytes: &[u8]) -> Result<ModelConfig, LoadError> {
    if bytes.len() < CONFIG_BYTES {
        return Err(LoadError::BadConfigRecord);
    }
    let slot = |index: usize| u32_at(bytes, index * 4);
    if slot(28) != 0 || slot(29) != 0 || slot(30) != UNET_LEVELS as u32 {
        return Err(LoadError::BadConfigRecord);
    }
    if (31..CONFIG_BYTES / 4).any(|index| slot(index) != 0) {
        return Err(LoadError::BadConfigRecord);
    }
    let config = ModelConfig {
        image_height: slot(0),
        image_width: slot(1),
        imagenet_norm: decode_bool(slot(2))?,
        backbone_norm: match slot(3) {
            0 => BackboneNorm::Group,
            1 => BackboneNorm::Batch,
            _ => return Err(LoadError::BadConfigRecord),
        },
        backbone_width: slot(4),
        feature_dim: slot(5),
        n_obs_steps: slot(6),
        horizon: slot(7),
        n_action_steps: slot(8),
        reconstruction_horizon: slot(9),
        state_dim: slot(10),
        action_dim: slot(11),
        state_pos_index: [slot(12), slot(13), slot(14)],
        action_pos_index: [slot(15), slot(16), slot(17)],
        pos_scale: f32_at(bytes, 18 * 4),
        down_dims: [slot(19), slot(20), slot(21)],
        diffusion_step_embed_dim: slot(22),
        kernel_size: slot(23),
        n_groups: slot(24),
        num_train_timesteps: slot(25),
        num_inference_steps: slot(26),
        clip_sample: decode_bool(slot(27))?,
    };
    config.validate().map_err(LoadError::Config)?;
    Ok(config)
}

/// One row of the tensor table.
#[derive(Clone, Copy, Debug)]
pub struct TensorEntry<'w> {
    pub name: &'w str,
    pub dtype: DType,
    pub rank: usize,
    pub dims: [usize; MAX_RANK],
    pub offset: usize,
    pub byte_len: usize,
}

impl TensorEntry<'_> {
    pub fn dims(&self) -> &[usize] {
        &self.dims[..self.rank]
    }

    pub fn element_count(&self) -> usize {
        self.dims().iter().product()
    }
}

/// A parsed and fully validated weights file.
#[derive(Clone, Copy, Debug)]
pub struct WeightsFile<'w> {
    bytes: &'w [u8],
    config: ModelConfig,
    quant: Quant,
    table_offset: usize,
    tensor_count: usize,
}

impl<'w> WeightsFile<'w> {
    /// Validates everything about `bytes` that can be checked without knowing the model:
    /// header, checksum, config record and each table entry's bounds, alignment and overlap.
    pub fn parse(bytes: &'w [u8]) -> Result<Self, LoadError> {
        if !(bytes.as_ptr() as usize).is_multiple_of(ALIGN) {
            return Err(LoadError::MisalignedBuffer);
        }
        if bytes.len() < HEADER_BYTES {
            return Err(LoadError::Truncated);
        }
        if bytes[..8] != MAGIC {
            return Err(LoadError::BadMagic);
        }
        let version = u32_at(bytes, 8);
        if version != VERSION {
            return Err(LoadError::UnsupportedVersion {
                found: version,
                supported: VERSION,
            });
        }
        if u32_at(bytes, 12) as usize != HEADER_BYTES {
            return Err(LoadError::BadHeader);
        }
        let file_bytes = u64_at(bytes, 16);
        if file_bytes > bytes.len() as u64 {
            return Err(LoadError::Truncated);
        }
        if file_bytes < bytes.len() as u64 || !file_bytes.is_multiple_of(ALIGN as u64) {
            return Err(LoadError::BadHeader);
        }
        let stored = u64_at(bytes, CHECKSUM_RANGE.start);
        if checksum(bytes) != stored {
            return Err(LoadError::ChecksumMismatch);
        }
        let config_offset = u32_at(bytes, 32) as usize;
        let config_len = u32_at(bytes, 36) as usize;
        let table_offset = u32_at(bytes, 40) as usize;
        let tensor_count = u32_at(bytes, 44) as usize;
        let quant = match u32_at(bytes, 48) {
            0 => Quant::F32,
            1 => Quant::Int8,
            _ => return Err(LoadError::BadHeader),
        };
        if bytes[52..64].iter().any(|&b| b != 0) {
            return Err(LoadError::BadHeader);
        }
        if config_offset != HEADER_BYTES || config_len != CONFIG_BYTES {
            return Err(LoadError::BadHeader);
        }
        if bytes.len() < HEADER_BYTES + CONFIG_BYTES {
            return Err(LoadError::Truncated);
        }
        let config = decode_config(&bytes[config_offset..config_offset + CONFIG_BYTES])?;
        if table_offset != HEADER_BYTES + CONFIG_BYTES || tensor_count > 100_000 {
            return Err(LoadError::BadHeader);
        }
        let table_end = table_offset + tensor_count * ENTRY_BYTES;
        if table_end > bytes.len() {
            return Err(LoadError::Truncated);
        }
        let file = WeightsFile {
            bytes,
            config,
            quant,
            table_offset,
            tensor_count,
        };
        // Tensors must follow the table in order, each aligned, inside the file, without
        // overlap: checking each against the end of the previous one covers all of that.
        let mut previous_end = table_end;
        for index in 0..tensor_count {
            let entry = file.entry(index)?;
            if entry.offset % ALIGN != 0 || entry.offset < previous_end {
                return Err(LoadError::BadTensorEntry { index });
            }
            let end = entry
                .offset
                .checked_add(entry.byte_len)
                .ok_or(LoadError::BadTensorEntry { index })?;
            if end > bytes.len() {
                return Err(LoadError::BadTensorEntry { index });
            }
            previous_end = end;
        }
        Ok(file)
    }

    pub fn config(&self) -> &ModelConfig {
        &self.config
    }

    pub fn quant(&self) -> Quant {
        self.quant
    }

    pub fn tensor_count(&self) -> usize {
        self.tensor_count
    }

    pub fn len(&self) -> usize {
        self.bytes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.bytes.is_empty()
    }

    /// Table row `index`, with its name, dtype and dims checked for consistency.
    pub fn entry(&self, index: usize) -> Result<TensorEntry<'w>, LoadError> {
        if index >= self.tensor_count {
            return Err(LoadError::MissingTensor { index });
        }
        let bad = LoadError::BadTensorEntry { index };
        let at = self.table_offset + index * ENTRY_BYTES;
        let row = &self.bytes[at..at + ENTRY_BYTES];
        let name_field = &row[..NAME_BYTES];
        let name_len = name_field
            .iter()
            .position(|&b| b == 0)
            .unwrap_or(NAME_BYTES);
        if name_field[name_len..].iter().any(|&b| b != 0) {
            return Err(bad);
        }
        let name = core::str::from_utf8(&name_field[..name_len]).map_err(|_| bad)?;
        let dtype = DType::from_code(u32_at(row, 56)).ok_or(bad)?;
        let rank = u32_at(row, 60) as usize;
        if rank == 0 || rank > MAX_RANK {
            return Err(bad);
        }
        let mut dims = [1usize; MAX_RANK];
        let mut elements: usize = 1;
        for (axis, dim) in dims.iter_mut().enumerate() {
            let value = u32_at(row, 64 + axis * 4) as usize;
            if axis < rank {
                *dim = value;
                elements = elements.checked_mul(value).ok_or(bad)?;
            } else if value != 0 {
                return Err(bad);
            }
        }
        let offset = usize::try_from(u64_at(row, 80)).map_err(|_| bad)?;
        let byte_len = usize::try_from(u64_at(row, 88)).map_err(|_| bad)?;
        // An int8 convolution kernel is stored in input-channel quads, `in` padded to a
        // multiple of 4 (crate::shape::int8_quad_index), its pair layout in eights.
        let stored = match dtype {
            DType::F32 => elements,
            _ if dtype.is_pairs() => int8_pair_stored_elements(&dims[..rank]).ok_or(bad)?,
            _ => int8_stored_elements(&dims[..rank]).ok_or(bad)?,
        };
        if stored.checked_mul(dtype.size()) != Some(byte_len) {
            return Err(bad);
        }
        Ok(TensorEntry {
            name,
            dtype,
            rank,
            dims,
            offset,
            byte_len,
        })
    }

    /// The stored bytes of a validated entry.
    pub fn data(&self, entry: &TensorEntry<'w>) -> &'w [u8] {
        &self.bytes[entry.offset..entry.offset + entry.byte_len]
    }
}
