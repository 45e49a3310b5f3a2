//! Element types a checkpoint may store, and their conversion to f32.

use std::fmt;

use half::{bf16, f16};

/// A stored element type. Only the float types are read; the rest are named in reports.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum DType {
    F32,
    F16,
    BF16,
    /// Rounded to the nearest f32.
    F64,
    /// Anything else (integers, bool, complex, fp8, ...), by the container's name for it.
    Other(String),
}

/// Byte order of stored elements. Safetensors is always little-endian; a torch archive says
/// which in its `byteorder` entry.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ByteOrder {
    Little,
    Big,
}

impl DType {
    /// Bytes per element of the float types.
    pub fn float_size(&self) -> Option<usize> {
        match self {
            DType::F32 => Some(4),
            DType::F16 | DType::BF16 => Some(2),
            DType::F64 => Some(8),
            DType::Other(_) => None,
        }
    }

    /// Decodes one element of a float type from exactly `float_size()` bytes.
    pub fn decode(&self, bytes: &[u8], order: ByteOrder) -> f32 {
        fn array<const N: usize>(bytes: &[u8], order: ByteOrder) -> [u8; N] {
            let mut array: [u8; N] = bytes.try_into().expect("caller passes float_size bytes");
            if order == ByteOrder::Big {
                array.reverse();
            }
            array
        }
        match self {
            DType::F32 => f32::from_le_bytes(array(bytes, order)),
            DType::F16 => f16::from_le_bytes(array(bytes, order)).to_f32(),
            DType::BF16 => bf16::from_le_bytes(array(bytes, order)).to_f32(),
            DType::F64 => f64::from_le_bytes(array(bytes, order)) as f32,
            DType::Other(name) => panic!("decode called for non-float dtype {name}"),
        }
    }
}

impl fmt::Display for DType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            DType::F32 => "float32",
            DType::F16 => "float16",
            DType::BF16 => "bfloat16",
            DType::F64 => "float64",
            DType::Other(name) => name,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decodes_each_float_type() {
        let order = ByteOrder::Little;
        assert_eq!(DType::F32.decode(&1.5f32.to_le_bytes(), order), 1.5);
        assert_eq!(DType::F16.decode(&[0x00, 0x3e], order), 1.5);
        assert_eq!(DType::BF16.decode(&[0xc0, 0x3f], order), 1.5);
        assert_eq!(DType::F64.decode(&1.5f64.to_le_bytes(), order), 1.5);
        assert_eq!(
            DType::F32.decode(&1.5f32.to_be_bytes(), ByteOrder::Big),
            1.5
        );
    }
}
