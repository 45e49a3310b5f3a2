//! The integer dot products the int8 kernels are generic over ([`Int8Lanes`]), and the
//! exact widening of their i32 sums to f64 and the one rounding to f32. Each architecture
//! implements them for its vectors (`x86_64::int8_lanes`, `aarch64::int8_lanes`).

/// An integer dot product over input-channel quads, `WIDTH` output channels a vector, and
/// the f32 arithmetic around it.
///
/// # Safety
/// Every method requires the CPU to support the vector's instructions (AVX2 for
/// [`PairSumsYmm`], AVX-512 F/BW/VNNI for [`VnniZmm`]); pointers must cover what each
/// method reads or writes.
pub(crate) unsafe trait Int8Lanes {
    /// `WIDTH` i32 lanes: sums, and the bytes of `WIDTH` weight quads or a broadcast quad.
    type Integers: Copy;
    /// `WIDTH` f32 lanes.
    type Floats: Copy;
    /// `WIDTH` integers held exactly in two vectors of f64 lanes: sums over a whole kernel
    /// that i32 lanes cannot hold.
    type Exact: Copy;
    const WIDTH: usize;
    unsafe fn zero_integers() -> Self::Integers;
    unsafe fn zero_floats() -> Self::Floats;
    unsafe fn zero_exact() -> Self::Exact;
    /// The quads of `WIDTH` output channels (`4 WIDTH` bytes).
    unsafe fn load_weights(from: *const i8) -> Self::Integers;
    /// Four activations, repeated in every lane.
    unsafe fn broadcast_quad(from: *const i8) -> Self::Integers;
    /// `sum + activations . weights` per lane: four u8 x i8 products, exact for
    /// activations in 0..=127.
    unsafe fn dot_quads(
        sum: Self::Integers,
        activations: Self::Integers,
        weights: Self::Integers,
    ) -> Self::Integers;
    /// `2 WIDTH` consecutive weights widened to i16, two a lane. For a convolution these are
    /// the quads of `WIDTH / 2` output channels: lanes `2k` and `2k + 1` hold weights (0, 1)
    /// and (2, 3) of the `k`-th channel; for a FiLM row, `2 WIDTH` of its columns.
    unsafe fn widen_quads(from: *const i8) -> Self::Integers;
    /// Four i16 codes (one quad) as lane pairs: (c0, c1), (c2, c3), repeated.
    unsafe fn broadcast_codes(from: *const i16) -> Self::Integers;
    /// `sum + codes . weights` per lane: two i16 x i16 products, exact for codes and
    /// weights in the scheme's range (|product| <= 16383 x 128).
    unsafe fn dot_code_pairs(
        sum: Self::Integers,
        codes: Self::Integers,
        weights: Self::Integers,
    ) -> Self::Integers;
    /// `2 WIDTH` consecutive i16 codes, two a lane.
    unsafe fn load_codes(from: *const i16) -> Self::Integers;
    /// `a + b` per i32 lane (wrapping).
    unsafe fn add_integers(a: Self::Integers, b: Self::Integers) -> Self::Integers;
    /// The sum of every i32 lane, exact.
    unsafe fn lane_sum(sums: Self::Integers) -> i64;
    /// The sums of adjacent lane pairs: those of `first` (channels 0 .. WIDTH/2), then those
    /// of `second`, in channel order.
    unsafe fn add_lane_pairs(first: Self::Integers, second: Self::Integers) -> Self::Integers;
    /// `total + sum` per lane, exact (integers in f64 lanes, below 2^53).
    unsafe fn add_exact(total: Self::Exact, sum: Self::Integers) -> Self::Exact;
    /// `128 high + low` per lane, exact.
    unsafe fn exact_digits(high: Self::Integers, low: Self::Integers) -> Self::Exact;
    /// The exact integers rounded to f32 (to nearest), times `scale`: two roundings.
    unsafe fn round_scaled(total: Self::Exact, scale: f32) -> Self::Floats;
    unsafe fn load(from: *const f32) -> Self::Floats;
    unsafe fn store(to: *mut f32, value: Self::Floats);
    unsafe fn mul(a: Self::Floats, b: Self::Floats) -> Self::Floats;
    unsafe fn add(a: Self::Floats, b: Self::Floats) -> Self::Floats;
}

/// Lanes that run the tiles of the U-Net's signed narrow codes
/// ([`SignedByteRows`](crate::kernels::SignedByteRows)): [`dot_quads`](Int8Lanes::dot_quads)
/// multiplies the weights, offset by [`WEIGHT_OFFSET`](Self::WEIGHT_OFFSET) where its first
/// side is unsigned, by the signed codes, exactly; the offset's share is taken back out.
///
/// # Safety
/// As for [`Int8Lanes`].
pub(crate) unsafe trait SignedByteLanes: Int8Lanes {
    /// What [`offset_bytes`](Self::offset_bytes) adds to every weight: 128 where the first
    /// side of the dot product is unsigned (VNNI, `usdot`), 0 where both are signed (`sdot`).
    const WEIGHT_OFFSET: i32;
    /// Every weight byte plus [`WEIGHT_OFFSET`](Self::WEIGHT_OFFSET), as the first side of
    /// [`dot_quads`](Int8Lanes::dot_quads) reads it (`byte ^ 0x80` read as unsigned, for 128).
    unsafe fn offset_bytes(bytes: Self::Integers) -> Self::Integers;
    /// `value` in every i32 lane.
    unsafe fn splat_integers(value: i32) -> Self::Integers;
    /// i32 sums rounded to f32 (to nearest), times `scale`: the bits of
    /// [`round_scaled`](Int8Lanes::round_scaled) of the same sums (an i32 is exact in f64),
    /// in one conversion where that takes five.
    unsafe fn integers_scaled(sums: Self::Integers, scale: f32) -> Self::Floats;
}

/// Lanes whose [`dot_quads`](Int8Lanes::dot_quads) is exact for activations in 0..=255
/// (whole bytes), not only 0..=127: the tiles of whole bytes
/// ([`ByteRows`](crate::kernels::ByteRows)) are written for these lanes only.
///
/// # Safety
/// As for [`Int8Lanes`], and the products of whole bytes are exact.
pub(crate) unsafe trait WholeByteLanes: SignedByteLanes {}

/// Lanes that run the tiles of whole bytes on a signed-by-signed dot product (`sdot`): each
/// byte centred (`byte - 128`), the weights' share `128 sum w` added back per channel
/// ([`CenteredBytes`](super::CenteredBytes)). Only aarch64 has such lanes.
///
/// # Safety
/// As for [`Int8Lanes`].
#[cfg(target_arch = "aarch64")]
pub(crate) unsafe trait CenteredByteLanes: SignedByteLanes {
    /// Four bytes, each centred (`byte ^ 0x80`: `byte - 128` read as i8), repeated in every
    /// lane.
    unsafe fn broadcast_centred_quad(from: *const i8) -> Self::Integers;
    /// `WIDTH` i32 values from `from`.
    unsafe fn load_integers(from: *const i32) -> Self::Integers;
}
