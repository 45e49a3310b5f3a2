//! The vector of f32 lanes the f32 kernels are written over: one generic body (`f32_tile`,
//! `sequence`) instantiated inside each backend's thin `#[target_feature]` wrapper, where
//! `#[inline(always)]` lets each architecture's intrinsics compile with that backend's
//! instructions.

/// A vector of f32 lanes and the operations the f32 kernels need.
///
/// # Safety
/// Every method requires the CPU to support the vector's instructions (the implementing
/// type names them); pointers must cover `WIDTH` floats.
pub(crate) unsafe trait Lanes {
    type Vector: Copy;
    const WIDTH: usize;
    unsafe fn zero() -> Self::Vector;
    unsafe fn load(from: *const f32) -> Self::Vector;
    unsafe fn store(to: *mut f32, value: Self::Vector);
    unsafe fn splat(value: f32) -> Self::Vector;
    /// `a * b + c`, one rounding.
    unsafe fn fma(a: Self::Vector, b: Self::Vector, c: Self::Vector) -> Self::Vector;
    unsafe fn add(a: Self::Vector, b: Self::Vector) -> Self::Vector;
    /// The sum of the lanes, in some fixed order.
    unsafe fn horizontal_sum(value: Self::Vector) -> f32;
}
