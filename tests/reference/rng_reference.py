"""Independent reference values for the engine's noise generator (engine/src/rng.rs).

Written from the documented contract only, not from the Rust code: splitmix64 seeding of
xoshiro256** (Blackman and Vigna's reference algorithms, with Python integers masked to 64
bits), then Box-Muller in float64 on pairs of draws:
    u1 = ((x >> 11) + 1) * 2^-53,  u2 = (y >> 11) * 2^-53,
    r = sqrt(-2 ln u1),  values r cos(2 pi u2), r sin(2 pi u2), rounded to float32.

Run once with `python tests/reference/rng_reference.py`; tests/tests/determinism.rs pins
the printed values.
"""

import numpy as np

MASK = (1 << 64) - 1


def splitmix64(state):
    state = (state + 0x9E3779B97F4A7C15) & MASK
    z = state
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK
    return state, z ^ (z >> 31)


def rotl(x, k):
    return ((x << k) | (x >> (64 - k))) & MASK


class Xoshiro256StarStar:
    def __init__(self, seed):
        self.s = []
        state = seed & MASK
        for _ in range(4):
            state, value = splitmix64(state)
            self.s.append(value)

    def next_u64(self):
        s = self.s
        result = (rotl((s[1] * 5) & MASK, 7) * 9) & MASK
        t = (s[1] << 17) & MASK
        s[2] ^= s[0]
        s[3] ^= s[1]
        s[1] ^= s[2]
        s[0] ^= s[3]
        s[2] ^= t
        s[3] = rotl(s[3], 45)
        return result


def normals(seed, count):
    rng = Xoshiro256StarStar(seed)
    out = []
    while len(out) < count:
        x, y = rng.next_u64(), rng.next_u64()
        u1 = np.float64((x >> 11) + 1) * np.float64(2.0 ** -53)
        u2 = np.float64(y >> 11) * np.float64(2.0 ** -53)
        r = np.sqrt(np.float64(-2.0) * np.log(u1))
        angle = np.float64(2.0 * np.pi) * u2
        out.append(np.float32(r * np.cos(angle)))
        out.append(np.float32(r * np.sin(angle)))
    return out[:count]


def main():
    for seed in (0, 7, 0xFFFF_FFFF_FFFF_FFFF):
        rng = Xoshiro256StarStar(seed)
        print(f"seed {seed:#x} u64:", ", ".join(f"{rng.next_u64():#018x}" for _ in range(6)))
    for seed in (0, 7):
        values = normals(seed, 9)
        print(f"seed {seed} normals (f32 bits):",
              ", ".join(f"{int(np.float32(v).view(np.uint32)):#010x}" for v in values))
        print(f"seed {seed} normals:", ", ".join(repr(float(v)) for v in values))


if __name__ == "__main__":
    main()
