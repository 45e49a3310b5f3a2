//! The CPU's extensions as the OS reports them, for hosted builds only (the engine's `std`
//! feature); firmware reads the ID registers instead.

#![cfg(feature = "std")]

/// The dot-product extension (`sdot`, FEAT_DotProd) is present.
pub fn has_dotprod() -> bool {
    std::arch::is_aarch64_feature_detected!("dotprod")
}

/// The int8 matrix multiply extension (`usdot`, `smmla`, FEAT_I8MM) is present, and the
/// dot product.
pub fn has_i8mm() -> bool {
    std::arch::is_aarch64_feature_detected!("i8mm") && has_dotprod()
}
