//! The aarch64 features as the OS reports them: hosted builds' answer (the `std` feature).

// Declared under the same gate in `mod.rs`; said here too, so the file stands on its own.
#![cfg(feature = "std")]

#[cfg(feature = "std")]
use std::arch::is_aarch64_feature_detected;

/// The dot-product extension (`sdot`, FEAT_DotProd) is present, as the OS reports it.
pub fn has_dotprod() -> bool {
    is_aarch64_feature_detected!("dotprod")
}

/// The int8 matrix multiply extension (`usdot`, `smmla`, FEAT_I8MM) is present, and the
/// dot product, as the OS reports them.
pub fn has_i8mm() -> bool {
    is_aarch64_feature_detected!("i8mm") && has_dotprod()
}
