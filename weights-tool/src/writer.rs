//! Writes the engine's weights file (docs/FORMAT.md). The tensor order is not decided here:
//! it is recorded from the engine's own binder ([`ModelWeights::bind`]), so the writer and
//! the reader cannot disagree.

use core::fmt;
use std::collections::BTreeMap;

use anyhow::{Result, bail, ensure};
use scdp_engine::Error as EngineError;
use scdp_engine::config::ModelConfig;
use scdp_engine::format::{
    self, ALIGN, CHECKSUM_RANGE, CONFIG_BYTES, ENTRY_BYTES, HEADER_BYTES, MAGIC, NAME_BYTES, Quant,
    VERSION,
};
use scdp_engine::weights::{ModelWeights, TensorSource};

/// One tensor the engine will ask for, in order.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TensorSpec {
    pub name: String,
    pub dims: Vec<usize>,
}

/// Records the names and shapes the engine's binder requests.
struct Recorder(Vec<TensorSpec>);

impl TensorSource<'static> for Recorder {
    fn f32_tensor(
        &mut self,
        name: fmt::Arguments<'_>,
        dims: &[usize],
    ) -> Result<&'static [f32], EngineError> {
        self.0.push(TensorSpec {
            name: name.to_string(),
            dims: dims.to_vec(),
        });
        Ok(&[])
    }
}

/// The engine's tensor list for `config`, in file order.
pub fn tensor_specs(config: &ModelConfig) -> Result<Vec<TensorSpec>> {
    let mut recorder = Recorder(Vec::new());
    ModelWeights::bind(config, &mut recorder)
        .map_err(|error| anyhow::anyhow!("config: {error}"))?;
    Ok(recorder.0)
}

fn align(offset: usize) -> usize {
    offset.div_ceil(ALIGN) * ALIGN
}

/// Serializes lowered tensors (engine name -> values) into a weights file.
pub fn write_weights_file(
    config: &ModelConfig,
    tensors: &BTreeMap<String, Vec<f32>>,
) -> Result<Vec<u8>> {
    let specs = tensor_specs(config)?;
    let mut unused: Vec<&String> = tensors
        .keys()
        .filter(|name| !specs.iter().any(|spec| &spec.name == *name))
        .collect();
    if !unused.is_empty() {
        unused.sort();
        bail!("internal: lowered tensors the engine does not read: {unused:?}");
    }
    let table_offset = HEADER_BYTES + CONFIG_BYTES;
    let mut offset = align(table_offset + specs.len() * ENTRY_BYTES);
    let mut table = Vec::with_capacity(specs.len() * ENTRY_BYTES);
    let mut placements = Vec::with_capacity(specs.len());
    for spec in &specs {
        let Some(values) = tensors.get(&spec.name) else {
            bail!("internal: no lowered tensor `{}`", spec.name);
        };
        let elements: usize = spec.dims.iter().product();
        ensure!(
            values.len() == elements,
            "internal: `{}` has {} values, the engine expects {:?}",
            spec.name,
            values.len(),
            spec.dims
        );
        ensure!(
            spec.name.len() <= NAME_BYTES,
            "internal: name `{}` too long",
            spec.name
        );
        let mut entry = [0u8; ENTRY_BYTES];
        entry[..spec.name.len()].copy_from_slice(spec.name.as_bytes());
        entry[56..60].copy_from_slice(&(format::DType::F32 as u32).to_le_bytes());
        entry[60..64].copy_from_slice(&(spec.dims.len() as u32).to_le_bytes());
        for (axis, &dim) in spec.dims.iter().enumerate() {
            entry[64 + 4 * axis..68 + 4 * axis].copy_from_slice(&u32::try_from(dim)?.to_le_bytes());
        }
        let byte_len = values.len() * 4;
        entry[80..88].copy_from_slice(&(offset as u64).to_le_bytes());
        entry[88..96].copy_from_slice(&(byte_len as u64).to_le_bytes());
        table.extend_from_slice(&entry);
        placements.push((offset, values));
        offset = align(offset + byte_len);
    }
    let file_len = offset;
    let mut bytes = vec![0u8; file_len];
    bytes[..8].copy_from_slice(&MAGIC);
    bytes[8..12].copy_from_slice(&VERSION.to_le_bytes());
    bytes[12..16].copy_from_slice(&(HEADER_BYTES as u32).to_le_bytes());
    bytes[16..24].copy_from_slice(&(file_len as u64).to_le_bytes());
    bytes[32..36].copy_from_slice(&(HEADER_BYTES as u32).to_le_bytes());
    bytes[36..40].copy_from_slice(&(CONFIG_BYTES as u32).to_le_bytes());
    bytes[40..44].copy_from_slice(&(table_offset as u32).to_le_bytes());
    bytes[44..48].copy_from_slice(&(specs.len() as u32).to_le_bytes());
    bytes[48..52].copy_from_slice(&(Quant::F32 as u32).to_le_bytes());
    bytes[HEADER_BYTES..HEADER_BYTES + CONFIG_BYTES]
        .copy_from_slice(&format::encode_config(config));
    bytes[table_offset..table_offset + table.len()].copy_from_slice(&table);
    for (at, values) in placements {
        for (chunk, value) in bytes[at..at + values.len() * 4]
            .chunks_exact_mut(4)
            .zip(values)
        {
            chunk.copy_from_slice(&value.to_le_bytes());
        }
    }
    let checksum = format::checksum(&bytes);
    bytes[CHECKSUM_RANGE].copy_from_slice(&checksum.to_le_bytes());
    Ok(bytes)
}

/// Copies `bytes` into a 64-byte aligned buffer, as the engine requires (a `Vec<u8>` only
/// guarantees byte alignment). Returns the buffer and the offset where the copy starts.
pub fn aligned_copy(bytes: &[u8]) -> AlignedBytes {
    let mut storage = vec![0u8; bytes.len() + ALIGN];
    let start = storage.as_ptr().align_offset(ALIGN);
    storage[start..start + bytes.len()].copy_from_slice(bytes);
    AlignedBytes {
        storage,
        start,
        len: bytes.len(),
    }
}

/// Owned bytes whose first byte is 64-byte aligned.
pub struct AlignedBytes {
    storage: Vec<u8>,
    start: usize,
    len: usize,
}

impl AlignedBytes {
    pub fn as_slice(&self) -> &[u8] {
        &self.storage[self.start..self.start + self.len]
    }

    pub fn as_mut_slice(&mut self) -> &mut [u8] {
        &mut self.storage[self.start..self.start + self.len]
    }

    /// A zeroed aligned buffer of `len` bytes (for arenas).
    pub fn zeroed(len: usize) -> Self {
        aligned_copy(&vec![0u8; len])
    }
}
