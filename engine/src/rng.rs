//! The engine's Gaussian noise source, identical on every platform: xoshiro256** seeded
//! through splitmix64, and Box-Muller in f64 with libm (a pure-software libm, so the bits do
//! not depend on the host's maths library).
//!
//! Normal number `2i` and `2i + 1` come from the pair `(u1, u2)` of 64-bit draws `2i, 2i+1`:
//! `u1 = ((x >> 11) + 1) 2^-53` in (0, 1], `u2 = (y >> 11) 2^-53` in [0, 1),
//! `r = sqrt(-2 ln u1)`, values `r cos(2 pi u2)` and `r sin(2 pi u2)`, rounded to f32.

/// xoshiro256** state.
#[derive(Clone, Debug)]
pub struct NoiseRng {
    state: [u64; 4],
}

fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

impl NoiseRng {
    pub fn new(seed: u64) -> Self {
        let mut mixer = seed;
        NoiseRng {
            state: [
                splitmix64(&mut mixer),
                splitmix64(&mut mixer),
                splitmix64(&mut mixer),
                splitmix64(&mut mixer),
            ],
        }
    }

    pub fn next_u64(&mut self) -> u64 {
        let [s0, s1, s2, s3] = &mut self.state;
        let result = s1.wrapping_mul(5).rotate_left(7).wrapping_mul(9);
        let t = *s1 << 17;
        *s2 ^= *s0;
        *s3 ^= *s1;
        *s1 ^= *s2;
        *s0 ^= *s3;
        *s2 ^= t;
        *s3 = s3.rotate_left(45);
        result
    }

    /// Fills `output` with standard normal values.
    pub fn fill_normal(&mut self, output: &mut [f32]) {
        const UNIT: f64 = 1.0 / (1u64 << 53) as f64;
        for pair in output.chunks_mut(2) {
            let u1 = ((self.next_u64() >> 11) + 1) as f64 * UNIT;
            let u2 = (self.next_u64() >> 11) as f64 * UNIT;
            let radius = libm::sqrt(-2.0 * libm::log(u1));
            let angle = 2.0 * core::f64::consts::PI * u2;
            pair[0] = (radius * libm::cos(angle)) as f32;
            if let Some(second) = pair.get_mut(1) {
                *second = (radius * libm::sin(angle)) as f32;
            }
        }
    }
}
