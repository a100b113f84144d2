#!/usr/bin/env python3
"""Independent pure-Python implementation of libflame's GaussianRng (see src/rng.rs docs).

SplitMix64 expands the seed into xoshiro256++ state; uniforms are the top 53 bits times 2^-53;
Box-Muller in double precision with u1 = 1 - a, u2 = b, emitting r*cos(theta) then r*sin(theta),
each rounded to float32. Writes the first 16 values for seeds 0, 1 and 12345 to
tests/fixtures/rng_reference.json (as float32 bit patterns and as decimal values).

Usage: python3 tools/rng_reference.py [output.json]
"""
import json
import math
import os
import struct
import sys

MASK = (1 << 64) - 1


def rotl(x, k):
    return ((x << k) | (x >> (64 - k))) & MASK


class Rng:
    def __init__(self, seed):
        sm = seed & MASK
        state = []
        for _ in range(4):
            sm = (sm + 0x9E3779B97F4A7C15) & MASK
            z = sm
            z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK
            z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK
            state.append(z ^ (z >> 31))
        self.s = state

    def u64(self):
        s0, s1, s2, s3 = self.s
        out = (rotl((s0 + s3) & MASK, 23) + s0) & MASK
        t = (s1 << 17) & MASK
        s2 ^= s0
        s3 ^= s1
        s1 ^= s2
        s0 ^= s3
        s2 ^= t
        s3 = rotl(s3, 45)
        self.s = [s0, s1, s2, s3]
        return out

    def uniform(self):
        return (self.u64() >> 11) * 2.0 ** -53

    def normals(self, n):
        out = []
        while len(out) < n:
            u1 = 1.0 - self.uniform()
            u2 = self.uniform()
            r = math.sqrt(-2.0 * math.log(u1))
            theta = math.tau * u2
            out.append(r * math.cos(theta))
            out.append(r * math.sin(theta))
        return out[:n]


def f32_bits(x):
    return struct.unpack("<I", struct.pack("<f", x))[0]


def main():
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    path = sys.argv[1] if len(sys.argv) > 1 else os.path.join(
        root, "tests", "fixtures", "rng_reference.json")
    cases = []
    for seed in (0, 1, 12345):
        vals = Rng(seed).normals(16)
        bits = [f32_bits(v) for v in vals]
        f32vals = [struct.unpack("<f", struct.pack("<I", b))[0] for b in bits]
        cases.append({"seed": seed, "bits": bits, "values": f32vals})
    doc = {
        "generator": "splitmix64 -> xoshiro256++ -> 53-bit uniform -> Box-Muller f64 -> f32",
        "produced_by": "tools/rng_reference.py",
        "cases": cases,
    }
    with open(path, "w") as f:
        json.dump(doc, f, indent=1)
        f.write("\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
