//! Writes the engine's weights file (docs/FORMAT.md). The tensor order is not decided here:
//! it is recorded from the engine's own binder ([`ModelWeights::bind`]), so the writer and
//! the reader cannot disagree.

use core::fmt;
use std::collections::BTreeMap;

use anyhow::{Result, bail, ensure};
use scdp_engine::Error as EngineError;
use scdp_engine::config::ModelConfig;
use scdp_engine::format::{
    self, ALIGN, CHECKSUM_RANGE, CONFIG_BYTES, DType, ENTRY_BYTES, HEADER_BYTES, MAGIC, NAME_BYTES,
    Quant, VERSION,
};
use scdp_engine::weights::{ActivationCodes, ModelWeights, NarrowCodes, TensorSource, Weight};

/// One tensor the engine will ask for, in order.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TensorSpec {
    pub name: String,
    pub dims: Vec<usize>,
    /// For weight matrices and kernels, which may be stored as int8: the name of the scale
    /// tensor that then follows, and how many scales (output channels) it has.
    pub int8_scales: Option<(String, usize)>,
    /// Whether the layer can quantize its input to narrow (8-bit) codes.
    pub narrow: NarrowCodes,
}

/// A tensor as it will be stored.
#[derive(Clone, Debug, PartialEq)]
pub enum Stored {
    F32(Vec<f32>),
    /// Symmetric int8 with one scale per output channel, and the codes the layer
    /// quantizes its input to; for the trunk's residual-block convolutions also the plane
    /// that refines them, written only when `refined` (`DType::I8Refined`).
    Int8 {
        values: Vec<i8>,
        scales: Vec<f32>,
        activations: ActivationCodes,
        residual: Option<ResidualPlane>,
        refined: bool,
    },
}

/// The rounding error of an int8 weight tensor quantized again: int8 values in the same
/// layout, one scale per output channel.
#[derive(Clone, Debug, PartialEq)]
pub struct ResidualPlane {
    pub values: Vec<i8>,
    pub scales: Vec<f32>,
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
            int8_scales: None,
            narrow: NarrowCodes::NotAllowed,
        });
        Ok(&[])
    }

    fn weight(
        &mut self,
        name: fmt::Arguments<'_>,
        scale_name: fmt::Arguments<'_>,
        dims: &[usize],
        channels: usize,
        narrow: NarrowCodes,
    ) -> Result<Weight<'static>, EngineError> {
        self.0.push(TensorSpec {
            name: name.to_string(),
            dims: dims.to_vec(),
            int8_scales: Some((scale_name.to_string(), channels)),
            narrow,
        });
        Ok(Weight::F32(&[]))
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

/// One table entry and its data, before offsets are assigned.
struct Entry {
    name: String,
    dims: Vec<usize>,
    dtype: DType,
    bytes: Vec<u8>,
}

/// Serializes stored tensors (engine name -> data) into a weights file.
pub fn write_weights_file(
    config: &ModelConfig,
    tensors: &BTreeMap<String, Stored>,
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
    let mut entries = Vec::with_capacity(specs.len());
    let mut any_int8 = false;
    for spec in &specs {
        let Some(stored) = tensors.get(&spec.name) else {
            bail!("internal: no lowered tensor `{}`", spec.name);
        };
        let elements: usize = spec.dims.iter().product();
        match stored {
            Stored::F32(values) => {
                ensure!(
                    values.len() == elements,
                    "internal: `{}` has {} values, the engine expects {:?}",
                    spec.name,
                    values.len(),
                    spec.dims
                );
                entries.push(Entry {
                    name: spec.name.clone(),
                    dims: spec.dims.clone(),
                    dtype: DType::F32,
                    bytes: values.iter().flat_map(|v| v.to_le_bytes()).collect(),
                });
            }
            Stored::Int8 {
                values,
                scales,
                activations,
                residual,
                refined,
            } => {
                let Some((scale_name, channels)) = &spec.int8_scales else {
                    bail!("internal: `{}` cannot be stored as int8", spec.name);
                };
                let residual = match (refined, residual) {
                    (false, _) => None,
                    (true, Some(residual)) => Some(residual),
                    (true, None) => bail!("internal: `{}` has no residual plane", spec.name),
                };
                let dtype = match (activations, residual.is_some()) {
                    (ActivationCodes::Wide, false) => DType::I8,
                    (ActivationCodes::Narrow, false) => DType::I8Narrow,
                    (ActivationCodes::Wide, true) => DType::I8Refined,
                    (ActivationCodes::Narrow, true) => DType::I8NarrowRefined,
                };
                ensure!(
                    dtype == DType::I8 || spec.narrow == NarrowCodes::Allowed,
                    "internal: `{}` cannot take narrow activations or a residual plane",
                    spec.name
                );
                // Convolution kernels are stored in input-channel quads (docs/FORMAT.md).
                let stored_elements =
                    scdp_engine::kernels::int8_stored_elements(&spec.dims).unwrap_or(elements);
                let planes = [
                    Some((values, scales)),
                    residual.map(|r| (&r.values, &r.scales)),
                ];
                let planes: Vec<_> = planes.into_iter().flatten().collect();
                ensure!(
                    planes.iter().all(|(values, scales)| {
                        values.len() == stored_elements && scales.len() == *channels
                    }),
                    "internal: int8 `{}` does not match {:?}",
                    spec.name,
                    spec.dims
                );
                any_int8 = true;
                let scale_dims = match planes.len() {
                    1 => vec![*channels],
                    count => vec![count, *channels],
                };
                entries.push(Entry {
                    name: spec.name.clone(),
                    dims: spec.dims.clone(),
                    dtype,
                    bytes: planes
                        .iter()
                        .flat_map(|(values, _)| values.iter().map(|&v| v as u8))
                        .collect(),
                });
                entries.push(Entry {
                    name: scale_name.clone(),
                    dims: scale_dims,
                    dtype: DType::F32,
                    bytes: planes
                        .iter()
                        .flat_map(|(_, scales)| scales.iter().flat_map(|v| v.to_le_bytes()))
                        .collect(),
                });
            }
        }
    }

    let quant = if any_int8 { Quant::Int8 } else { Quant::F32 };
    serialize(config, quant, &entries)
}

/// The file of `entries`, in their order: header, config record, table, aligned data,
/// checksum.
fn serialize(config: &ModelConfig, quant: Quant, entries: &[Entry]) -> Result<Vec<u8>> {
    let table_offset = HEADER_BYTES + CONFIG_BYTES;
    let mut offset = align(table_offset + entries.len() * ENTRY_BYTES);
    let mut table = Vec::with_capacity(entries.len() * ENTRY_BYTES);
    let mut placements = Vec::with_capacity(entries.len());
    for entry in entries {
        ensure!(
            entry.name.len() <= NAME_BYTES,
            "tensor name `{}` too long for the file's table",
            entry.name
        );
        let mut row = [0u8; ENTRY_BYTES];
        row[..entry.name.len()].copy_from_slice(entry.name.as_bytes());
        row[56..60].copy_from_slice(&(entry.dtype as u32).to_le_bytes());
        row[60..64].copy_from_slice(&(entry.dims.len() as u32).to_le_bytes());
        for (axis, &dim) in entry.dims.iter().enumerate() {
            row[64 + 4 * axis..68 + 4 * axis].copy_from_slice(&u32::try_from(dim)?.to_le_bytes());
        }
        row[80..88].copy_from_slice(&(offset as u64).to_le_bytes());
        row[88..96].copy_from_slice(&(entry.bytes.len() as u64).to_le_bytes());
        table.extend_from_slice(&row);
        placements.push((offset, &entry.bytes));
        offset = align(offset + entry.bytes.len());
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
    bytes[44..48].copy_from_slice(&(entries.len() as u32).to_le_bytes());
    bytes[48..52].copy_from_slice(&(quant as u32).to_le_bytes());
    bytes[HEADER_BYTES..HEADER_BYTES + CONFIG_BYTES]
        .copy_from_slice(&format::encode_config(config));
    bytes[table_offset..table_offset + table.len()].copy_from_slice(&table);
    for (at, data) in placements {
        bytes[at..at + data.len()].copy_from_slice(data);
    }
    let checksum = format::checksum(&bytes);
    bytes[CHECKSUM_RANGE].copy_from_slice(&checksum.to_le_bytes());
    Ok(bytes)
}

/// `bytes` (a weights file) with each 8-bit convolution kernel (`DType::I8Narrow`, refined
/// or not) followed by `NAME.pairs`: its values again in eight-input groups
/// (`DType::I8Pairs`, docs/FORMAT.md), the operands of I8MM's matrix multiplies as stored.
/// The quads stay for every other backend; every output keeps its bits. A file that has
/// them already is returned as it is.
pub fn add_weight_pairs(bytes: &[u8]) -> Result<Vec<u8>> {
    use scdp_engine::kernels::PAIR;
    use scdp_engine::kernels::{int8_convolution, int8_pair_index, int8_pairs, int8_quad_index};
    let aligned = aligned_copy(bytes);
    let file = format::WeightsFile::parse(aligned.as_slice())
        .map_err(|error| anyhow::anyhow!("{error}"))?;
    let mut entries = Vec::with_capacity(file.tensor_count());
    let mut index = 0;
    while index < file.tensor_count() {
        let entry = file
            .entry(index)
            .map_err(|error| anyhow::anyhow!("{error}"))?;
        if entry.dtype.is_pairs() {
            return Ok(bytes.to_vec());
        }
        let copy = |entry: &format::TensorEntry<'_>| Entry {
            name: entry.name.to_string(),
            dims: entry.dims().to_vec(),
            dtype: entry.dtype,
            bytes: file.data(entry).to_vec(),
        };
        entries.push(copy(&entry));
        index += 1;
        let narrow = matches!(entry.dtype, DType::I8Narrow | DType::I8NarrowRefined);
        let convolution = int8_convolution(entry.dims());
        let (true, Some((taps, inputs, outputs))) = (narrow, convolution) else {
            continue;
        };
        // The scales come between the weight and its pairs.
        let scales = file
            .entry(index)
            .map_err(|error| anyhow::anyhow!("{error}"))?;
        entries.push(copy(&scales));
        index += 1;
        let quads = file.data(&entry);
        let plane_len = quads.len() / entry.dtype.size();
        let pair_len = taps * int8_pairs(inputs) * PAIR * outputs;
        let mut pairs = vec![0u8; pair_len * entry.dtype.size()];
        for (quads, pairs) in quads
            .chunks_exact(plane_len)
            .zip(pairs.chunks_exact_mut(pair_len))
        {
            for tap in 0..taps {
                for input in 0..inputs {
                    for output in 0..outputs {
                        let at = (tap, input, output);
                        pairs[int8_pair_index(taps, inputs, outputs, at)] =
                            quads[int8_quad_index(taps, inputs, outputs, at)];
                    }
                }
            }
        }
        entries.push(Entry {
            name: format!("{}.pairs", entry.name),
            dims: entry.dims().to_vec(),
            dtype: match entry.dtype.is_refined() {
                true => DType::I8RefinedPairs,
                false => DType::I8Pairs,
            },
            bytes: pairs,
        });
    }
    serialize(file.config(), file.quant(), &entries)
}

/// Copies `bytes` into a 64-byte aligned buffer, as the engine requires (a `Vec<u8>` only
/// guarantees byte alignment).
pub fn aligned_copy(bytes: &[u8]) -> AlignedBytes {
    let mut copy = AlignedBytes::zeroed(bytes.len());
    copy.as_mut_slice().copy_from_slice(bytes);
    copy
}

/// Owned, zero-initialized bytes, page aligned (so 64-byte aligned, as the engine requires),
/// on Linux in transparent huge pages where the kernel has them. The U-Net's weights are
/// read in full at every denoising step: over 4 KiB pages their 15 MB are 3,600 TLB misses
/// a step, and the hardware prefetchers stop at every page boundary; 2 MiB pages made the
/// denoising loop 12-15% faster (in-process A/B).
pub struct AlignedBytes {
    map: memmap2::MmapMut,
    len: usize,
}

impl AlignedBytes {
    pub fn as_slice(&self) -> &[u8] {
        &self.map[..self.len]
    }

    pub fn as_mut_slice(&mut self) -> &mut [u8] {
        &mut self.map[..self.len]
    }

    /// A zeroed aligned buffer of `len` bytes (weights files, arenas).
    pub fn zeroed(len: usize) -> Self {
        // An anonymous map is zeroed by the OS; a map of no bytes does not exist.
        let map = memmap2::MmapOptions::new()
            .len(len.max(1))
            .map_anon()
            .expect("anonymous memory map");
        // Advice only, before the first touch: where the kernel has no huge pages to give
        // (or THP is off), the buffer is plain pages and works the same.
        #[cfg(target_os = "linux")]
        let _ = map.advise(memmap2::Advice::HugePage);
        AlignedBytes { map, len }
    }
}
