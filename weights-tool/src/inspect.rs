//! `weights-tool inspect`: what a weights file holds and what running it will need.

use std::fmt::Write as _;

use anyhow::Result;
use scdp_engine::format::{DType, Quant};
use scdp_engine::{ArenaPlan, Model};

use crate::config_to_toml;

fn mebibytes(bytes: usize) -> String {
    format!("{:.2} MiB", bytes as f64 / (1024.0 * 1024.0))
}

/// How an int8 file stores its weights: how many layers read 15-bit and 8-bit activation
/// codes (dtypes `i8`/`i16` and `i8a8`/`i16a8`), and how many carry a second weight plane
/// (`i16`, `i16a8`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WeightCounts {
    pub wide: usize,
    pub narrow: usize,
    pub refined: usize,
    /// 8-bit layers whose kernels the file holds in the pair layout too.
    pub paired: usize,
}

/// The [`WeightCounts`] of a weights file.
pub fn weight_counts(bytes: &[u8]) -> Result<WeightCounts> {
    let aligned = crate::writer::aligned_copy(bytes);
    let model =
        Model::from_bytes(aligned.as_slice()).map_err(|error| anyhow::anyhow!("{error}"))?;
    let file = model.file();
    let mut counts = WeightCounts::default();
    for index in 0..file.tensor_count() {
        let entry = file
            .entry(index)
            .map_err(|error| anyhow::anyhow!("{error}"))?;
        match entry.dtype {
            DType::I8 | DType::I8Refined => counts.wide += 1,
            DType::I8Narrow | DType::I8NarrowRefined => counts.narrow += 1,
            DType::I8Pairs | DType::I8RefinedPairs => counts.paired += 1,
            DType::F32 => {}
        }
        counts.refined += usize::from(entry.dtype.is_refined() && !entry.dtype.is_pairs());
    }
    Ok(counts)
}

/// A one-screen report: config, storage, arena plan, then the tensor table.
pub fn report(bytes: &[u8]) -> Result<String> {
    let aligned = crate::writer::aligned_copy(bytes);
    let model =
        Model::from_bytes(aligned.as_slice()).map_err(|error| anyhow::anyhow!("{error}"))?;
    let file = model.file();
    let config = model.config();
    let plan = ArenaPlan::new(config);
    let mut out = String::new();
    writeln!(
        out,
        "format version {}, checksum ok, {} tensors, {} ({} bytes)",
        scdp_engine::format::VERSION,
        file.tensor_count(),
        mebibytes(file.len()),
        file.len()
    )?;
    writeln!(
        out,
        "weights: {}",
        match file.quant() {
            Quant::F32 => "f32",
            Quant::Int8 => "int8",
        }
    )?;
    writeln!(
        out,
        "arena: {} ({} bytes); without buffer reuse {} ({:.1}x)",
        mebibytes(plan.arena_bytes),
        plan.arena_bytes,
        mebibytes(plan.without_reuse_bytes),
        plan.without_reuse_bytes as f64 / plan.arena_bytes as f64
    )?;
    writeln!(
        out,
        "  feature maps {} (all frames), trunk/denoiser scratch {}",
        mebibytes(plan.features * 4),
        mebibytes(plan.scratch * 4)
    )?;
    writeln!(
        out,
        "kernels on this CPU (`run --kernels NAME`): {} (auto: {})",
        crate::run::available_kernels().join(", "),
        crate::run::select_kernels("auto")?.name()
    )?;
    writeln!(out, "\n[config]\n{}", config_to_toml(config))?;
    let entries = (0..file.tensor_count())
        .map(|index| file.entry(index))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|error| anyhow::anyhow!("{error}"))?;
    if file.quant() == Quant::Int8 {
        let count = |dtype: DType| entries.iter().filter(|entry| entry.dtype == dtype).count();
        writeln!(
            out,
            "int8 activations: {} layers on 15-bit codes (i8), {} on 8-bit codes (i8a8, docs/QUANTIZATION.md)",
            count(DType::I8) + count(DType::I8Refined),
            count(DType::I8Narrow) + count(DType::I8NarrowRefined)
        )?;
        for entry in entries
            .iter()
            .filter(|entry| matches!(entry.dtype, DType::I8Narrow | DType::I8NarrowRefined))
        {
            writeln!(out, "  8-bit  {}", entry.name)?;
        }
        let refined: Vec<_> = entries
            .iter()
            .filter(|entry| entry.dtype.is_refined() && !entry.dtype.is_pairs())
            .collect();
        writeln!(
            out,
            "int8 weights: {} layers refined by a second plane (i16, i16a8: about 15-bit weights)",
            refined.len()
        )?;
        for entry in refined {
            writeln!(out, "  refined  {}", entry.name)?;
        }
        writeln!(
            out,
            "pair layout (`add-pairs`, `convert --weight-pairs`; read by `i8mm`): {} of the 8-bit layers",
            entries
                .iter()
                .filter(|entry| entry.dtype.is_pairs())
                .count()
        )?;
        writeln!(out)?;
    }
    writeln!(
        out,
        "{:<48} {:>5} {:<22} {:>12} {:>12}",
        "tensor", "dtype", "shape", "offset", "bytes"
    )?;
    let (mut parameters, mut pair_values) = (0usize, 0usize);
    for entry in &entries {
        match entry.dtype.is_pairs() {
            true => pair_values += entry.element_count(),
            false => parameters += entry.element_count(),
        }
        let dtype = match entry.dtype {
            DType::F32 => "f32",
            DType::I8 => "i8",
            DType::I8Narrow => "i8a8",
            DType::I8Refined => "i16",
            DType::I8NarrowRefined => "i16a8",
            DType::I8Pairs => "i8p",
            DType::I8RefinedPairs => "i16p",
        };
        writeln!(
            out,
            "{:<48} {:>5} {:<22} {:>12} {:>12}",
            entry.name,
            dtype,
            format!("{:?}", entry.dims()),
            entry.offset,
            entry.byte_len
        )?;
    }
    writeln!(out, "{parameters} stored values")?;
    if pair_values > 0 {
        writeln!(out, "{pair_values} more in the pair layout")?;
    }
    Ok(out)
}
