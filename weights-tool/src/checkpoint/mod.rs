//! Loading a state dict from any container of docs/SPEC.md section 6: a Diffusion Policy training
//! checkpoint or a plain state dict written by `torch.save`, or a `.safetensors` file. The
//! container is recognised by its first bytes, not by the file name.

pub mod dtype;
pub mod pickle;
mod torch_zip;

use std::fs::File;
use std::io::Read;
use std::path::Path;

use anyhow::{Context as _, bail};
use indicatif::ProgressBar;

use crate::safetensors_io::read_safetensors;
use crate::state_dict::StateDict;

/// What the first bytes of a file say it is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Container {
    Zip,
    Safetensors,
    /// A bare pickle: `torch.save` before PyTorch 1.6 (or `_use_new_zipfile_serialization=False`).
    LegacyTorch,
}

fn sniff(head: &[u8]) -> Option<Container> {
    match head {
        // Local file header, or the end record of an empty archive.
        [b'P', b'K', 3, 4, ..] | [b'P', b'K', 5, 6, ..] => Some(Container::Zip),
        // A little-endian header length, then the JSON header.
        [_, _, _, _, _, _, _, _, b'{', ..] => Some(Container::Safetensors),
        [0x80, ..] => Some(Container::LegacyTorch),
        _ => None,
    }
}

/// Reads the state dict in `path`. Float tensors (f32, f16, bf16, f64) become f32; other
/// entries (integer tensors such as `num_batches_tracked`, non-tensors) are listed in
/// [`StateDict::skipped`]. Errors name the file and, where there is one, the key.
pub fn load_checkpoint(path: &Path) -> anyhow::Result<StateDict> {
    load_checkpoint_with_progress(path, &ProgressBar::hidden())
}

/// [`load_checkpoint`], advancing `progress` once per state-dict entry.
pub fn load_checkpoint_with_progress(
    path: &Path,
    progress: &ProgressBar,
) -> anyhow::Result<StateDict> {
    load(path, progress).with_context(|| path.display().to_string())
}

fn load(path: &Path, progress: &ProgressBar) -> anyhow::Result<StateDict> {
    let mut head = Vec::with_capacity(9);
    File::open(path)
        .context("cannot open")?
        .take(9)
        .read_to_end(&mut head)
        .context("cannot read")?;
    match sniff(&head) {
        Some(Container::Zip) => torch_zip::read_torch_archive(path, progress),
        Some(Container::Safetensors) => {
            let bytes = std::fs::read(path).context("cannot read")?;
            read_safetensors(&bytes, progress)
        }
        Some(Container::LegacyTorch) => bail!(
            "a bare pickle (torch.save's format before PyTorch 1.6), which this tool does not \
             read; load it in Python and torch.save it again"
        ),
        None if head.is_empty() => bail!("empty file"),
        None => bail!(
            "neither a torch.save zip archive nor a safetensors file (starts with {:02x?})",
            head
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sniffs_containers() {
        assert_eq!(sniff(b"PK\x03\x04rest"), Some(Container::Zip));
        assert_eq!(
            sniff(b"\x10\x00\x00\x00\x00\x00\x00\x00{\"a\""),
            Some(Container::Safetensors)
        );
        assert_eq!(sniff(b"\x80\x02\x8a\x0a"), Some(Container::LegacyTorch));
        assert_eq!(sniff(b"hello world"), None);
        assert_eq!(sniff(b""), None);
    }
}
