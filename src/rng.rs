//! The in-crate seeded Gaussian generator, and the [`NoiseSource`] trait samplers draw from.
//!
//! libflame does not try to reproduce PyTorch's `torch.randn` stream; it defines its own small,
//! fully specified generator so that a seed gives the same motion on every platform and in any
//! language. The algorithm, exactly (all integer arithmetic wraps modulo 2^64):
//!
//! 1. **Seeding (SplitMix64).** `s = seed`; four times: `s += 0x9E3779B97F4A7C15`; `z = s`;
//!    `z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9`; `z = (z ^ (z >> 27)) * 0x94D049BB133111EB`;
//!    `z ^= z >> 31`; the four `z` values, in order, are the xoshiro state words `s0, s1, s2, s3`.
//! 2. **Raw 64-bit draws (xoshiro256++).** `out = rotl(s0 + s3, 23) + s0`; then `t = s1 << 17`;
//!    `s2 ^= s0; s3 ^= s1; s1 ^= s2; s0 ^= s3; s2 ^= t; s3 = rotl(s3, 45)`; return `out`.
//! 3. **Uniform double in [0, 1).** `(out >> 11) as f64 * 2^-53` (the top 53 bits).
//! 4. **Box–Muller in f64.** Draw `a` then `b` (two uniforms, in that order); `u1 = 1 - a` (in
//!    (0, 1], so `ln` never sees 0), `u2 = b`; `r = sqrt(-2 * ln(u1))`; `θ = 2π * u2` (2π being the
//!    f64 constant 6.283185307179586); `z0 = r * cos(θ)`, `z1 = r * sin(θ)`.
//! 5. **Output.** `z0` then `z1`, each rounded to the nearest f32.
//!
//! The stream is a property of the seed alone: a [`NoiseSource::fill`] call that asks for an odd
//! count keeps the unused `z1` for the next call, so chunking never changes the values.
//! `tools/rng_reference.py` is an independent pure-Python implementation of the same algorithm;
//! `tests/fixtures/rng_reference.json` holds its output and a unit test compares bit for bit.
//!
//! [`NoiseSource`]: crate::rng::NoiseSource
//! [`NoiseSource::fill`]: crate::rng::NoiseSource::fill

/// Where samplers get their N(0, I) noise. `Send` so a session can move between threads.
pub trait NoiseSource: Send {
    /// Overwrites `out` with the next `out.len()` values of the stream.
    fn fill(&mut self, out: &mut [f32]);
}

/// Seeded standard-normal generator: xoshiro256++ seeded by SplitMix64, Box–Muller in f64
/// (see the module documentation for the exact algorithm).
#[derive(Debug, Clone)]
pub struct GaussianRng {
    s: [u64; 4],
    /// The `z1` of a Box–Muller pair whose `z0` was already handed out.
    spare: Option<f32>,
}

/// One SplitMix64 step; used only to expand the seed so that nearby seeds give unrelated states.
fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

impl GaussianRng {
    /// A generator whose whole stream is determined by `seed`.
    pub fn new(seed: u64) -> Self {
        let mut sm = seed;
        let s = [
            splitmix64(&mut sm),
            splitmix64(&mut sm),
            splitmix64(&mut sm),
            splitmix64(&mut sm),
        ];
        GaussianRng { s, spare: None }
    }

    /// The next raw xoshiro256++ output.
    pub fn next_u64(&mut self) -> u64 {
        let [s0, s1, s2, s3] = &mut self.s;
        let out = s0.wrapping_add(*s3).rotate_left(23).wrapping_add(*s0);
        let t = *s1 << 17;
        *s2 ^= *s0;
        *s3 ^= *s1;
        *s1 ^= *s2;
        *s0 ^= *s3;
        *s2 ^= t;
        *s3 = s3.rotate_left(45);
        out
    }

    /// A uniform double in [0, 1) from the top 53 bits of the next raw draw.
    pub fn next_uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// One Box–Muller pair `(z0, z1)` in f64, before rounding to f32.
    fn next_pair(&mut self) -> (f64, f64) {
        let u1 = 1.0 - self.next_uniform();
        let u2 = self.next_uniform();
        let r = (-2.0 * u1.ln()).sqrt();
        let theta = std::f64::consts::TAU * u2;
        (r * theta.cos(), r * theta.sin())
    }

    /// The next standard-normal value of the stream.
    pub fn next_normal(&mut self) -> f32 {
        if let Some(z) = self.spare.take() {
            return z;
        }
        let (z0, z1) = self.next_pair();
        self.spare = Some(z1 as f32);
        z0 as f32
    }
}

impl NoiseSource for GaussianRng {
    fn fill(&mut self, out: &mut [f32]) {
        let mut rest = out;
        // Hand out a spare left by a previous odd-sized call first, so chunking is invisible.
        if !rest.is_empty() {
            if let Some(z) = self.spare.take() {
                rest[0] = z;
                rest = &mut rest[1..];
            }
        }
        let mut pairs = rest.chunks_exact_mut(2);
        for pair in &mut pairs {
            let (z0, z1) = self.next_pair();
            pair[0] = z0 as f32;
            pair[1] = z1 as f32;
        }
        if let [last] = pairs.into_remainder() {
            *last = self.next_normal();
        }
    }
}

/// Replays pre-recorded noise (for example `torch.randn` values saved by a PyTorch reference run)
/// in order, so a libflame trajectory can be compared step by step with the reference.
///
/// Once the recording is used up, further values are zeros and [`ReplayNoise::overrun`] turns
/// true: a test can then fail with a clear message instead of silently drifting.
#[derive(Debug, Clone, Default)]
pub struct ReplayNoise {
    values: Vec<f32>,
    pos: usize,
    overrun: bool,
}

impl ReplayNoise {
    /// A source that hands out `values` in order.
    pub fn new(values: Vec<f32>) -> Self {
        ReplayNoise {
            values,
            pos: 0,
            overrun: false,
        }
    }

    /// True when every recorded value has been handed out.
    pub fn exhausted(&self) -> bool {
        self.pos >= self.values.len()
    }

    /// How many recorded values are still to come.
    pub fn remaining(&self) -> usize {
        self.values.len() - self.pos
    }

    /// True if some `fill` asked for more than was left (those positions got zeros).
    pub fn overrun(&self) -> bool {
        self.overrun
    }
}

impl NoiseSource for ReplayNoise {
    fn fill(&mut self, out: &mut [f32]) {
        let take = out.len().min(self.remaining());
        out[..take].copy_from_slice(&self.values[self.pos..self.pos + take]);
        out[take..].fill(0.0);
        self.pos += take;
        if take < out.len() {
            self.overrun = true;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stream(seed: u64, n: usize) -> Vec<f32> {
        let mut rng = GaussianRng::new(seed);
        let mut v = vec![0.0; n];
        rng.fill(&mut v);
        v
    }

    #[test]
    fn splitmix_seeding_matches_published_vector() {
        // SplitMix64 from state 1234567 (Vigna's reference test vector).
        let mut s = 1234567u64;
        let got: Vec<u64> = (0..3).map(|_| splitmix64(&mut s)).collect();
        assert_eq!(
            got,
            [
                6457827717110365317,
                3203168211198807973,
                9817491932198370423
            ]
        );
    }

    #[test]
    fn xoshiro_step_matches_hand_computation() {
        // State [1, 2, 3, 4]: out = rotl(1 + 4, 23) + 1 = 5 << 23 | ... = 41943041.
        let mut rng = GaussianRng {
            s: [1, 2, 3, 4],
            spare: None,
        };
        assert_eq!(rng.next_u64(), 41_943_041);
        // Next state worked by hand: t = 2<<17; s2 = 3^1 = 2; s3 = 4^2 = 6; s1 = 2^2 = 0;
        // s0 = 1^6 = 7; s2 = 2 ^ 262144 = 262146; s3 = rotl(6, 45).
        assert_eq!(rng.s, [7, 0, 262_146, 6u64.rotate_left(45)]);
    }

    #[test]
    fn matches_python_reference_bit_for_bit() {
        #[derive(serde::Deserialize)]
        struct Case {
            seed: u64,
            bits: Vec<u32>,
        }
        #[derive(serde::Deserialize)]
        struct Fixture {
            cases: Vec<Case>,
        }
        let fx: Fixture =
            serde_json::from_str(include_str!("../tests/fixtures/rng_reference.json")).unwrap();
        assert_eq!(fx.cases.len(), 3);
        for case in fx.cases {
            let got: Vec<u32> = stream(case.seed, case.bits.len())
                .iter()
                .map(|v| v.to_bits())
                .collect();
            assert_eq!(got, case.bits, "seed {}", case.seed);
        }
    }

    #[test]
    fn chunking_does_not_change_the_stream() {
        let whole = stream(42, 101);
        for chunks in [
            &[1usize, 1, 1, 98][..],
            &[3, 5, 7, 86],
            &[0, 50, 0, 51],
            &[101],
        ] {
            let mut rng = GaussianRng::new(42);
            let mut got = Vec::new();
            for &c in chunks {
                let mut v = vec![0.0; c];
                rng.fill(&mut v);
                got.extend(v);
            }
            assert_eq!(got, whole, "chunks {chunks:?}");
        }
        let mut rng = GaussianRng::new(42);
        let singles: Vec<f32> = (0..101).map(|_| rng.next_normal()).collect();
        assert_eq!(singles, whole);
    }

    #[test]
    fn seeds_give_different_streams() {
        assert_ne!(stream(0, 8), stream(1, 8));
        assert_eq!(stream(7, 8), stream(7, 8));
    }

    #[test]
    fn moments_are_standard_normal() {
        let v = stream(2024, 100_000);
        let n = v.len() as f64;
        let mean = v.iter().map(|&x| x as f64).sum::<f64>() / n;
        let var = v.iter().map(|&x| (x as f64 - mean).powi(2)).sum::<f64>() / n;
        // Standard error of the mean is ~0.003, of the variance ~0.0045.
        assert!(mean.abs() < 0.02, "mean {mean}");
        assert!((var - 1.0).abs() < 0.03, "var {var}");
        assert!(v.iter().all(|x| x.is_finite()));
        let frac_within_1 = v.iter().filter(|x| x.abs() < 1.0).count() as f64 / n;
        assert!((frac_within_1 - 0.6827).abs() < 0.01, "{frac_within_1}");
    }

    #[test]
    fn replay_hands_out_values_in_order_then_zeros() {
        let mut r = ReplayNoise::new(vec![1.0, 2.0, 3.0]);
        assert!(!r.exhausted());
        let mut a = [0.0; 2];
        r.fill(&mut a);
        assert_eq!(a, [1.0, 2.0]);
        assert_eq!(r.remaining(), 1);
        assert!(!r.overrun());
        let mut b = [9.0; 3];
        r.fill(&mut b);
        assert_eq!(b, [3.0, 0.0, 0.0]);
        assert!(r.exhausted());
        assert!(r.overrun());
    }

    #[test]
    fn replay_exact_use_is_not_an_overrun() {
        let mut r = ReplayNoise::new(vec![0.5; 4]);
        let mut a = [0.0; 4];
        r.fill(&mut a);
        assert!(r.exhausted());
        assert!(!r.overrun());
    }
}
