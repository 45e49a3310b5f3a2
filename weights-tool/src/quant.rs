//! How the weights file stores the model's weights.

use std::fmt;
use std::str::FromStr;

/// Storage precision of the weights file's tensors.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Quant {
    /// Every tensor as f32: bit-identical to the checkpoint.
    #[default]
    F32,
    /// Weight matrices and convolution kernels as int8 with scales; the rest stays f32.
    Int8,
}

impl Quant {
    pub const ALL: [Quant; 2] = [Quant::F32, Quant::Int8];

    pub fn name(self) -> &'static str {
        match self {
            Quant::F32 => "f32",
            Quant::Int8 => "int8",
        }
    }
}

impl fmt::Display for Quant {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Quant {
    type Err = String;

    fn from_str(name: &str) -> Result<Self, Self::Err> {
        Quant::ALL
            .into_iter()
            .find(|quant| quant.name() == name)
            .ok_or_else(|| format!("unknown quantization {name:?}, expected f32 or int8"))
    }
}
