//! Embedding lookups and sinusoidal encodings.
//!
//! The sinusoid arguments are formed in f32 with exactly the operations (and roundings) of the
//! reference PyTorch code, because at diffusion timesteps near 1000 one ulp of an argument is
//! ~6e-5 of output. `exp`, `sin` and `cos` themselves are evaluated in f64 and rounded, which
//! gives the correctly rounded f32 result on every platform (PyTorch's own are within 1 ulp).

/// `ln(10000)`, the `max_period` of both encodings.
const LN_10000: f64 = 9.210_340_371_976_184;

/// Copies rows `ids[i]` of `table` (`[rows, dim]`) into `out[i]`. Callers guarantee ids < rows.
pub fn embedding(table: &[f32], dim: usize, ids: &[u32], out: &mut [f32]) {
    assert!(out.len() >= ids.len() * dim, "embedding: out too short");
    if dim == 0 {
        return;
    }
    for (o, &id) in out.chunks_exact_mut(dim).zip(ids) {
        let start = id as usize * dim;
        o.copy_from_slice(&table[start..start + dim]);
    }
}

/// FLAME/guided-diffusion timestep embedding of `s` into `out` (`dim` even): with `half = dim/2`,
/// `f_i = exp(-ln(10000) · i / half)` in f32, `out = [cos(s·f_0..), sin(s·f_0..)]` (cos first).
pub fn sinusoid_cos_first(s: f32, out: &mut [f32]) {
    assert_eq!(out.len() % 2, 0, "sinusoid_cos_first: odd dim");
    let half = out.len() / 2;
    let (cos, sin) = out.split_at_mut(half);
    // PyTorch: exp(-math.log(10000) * arange(half, dtype=float32) / half); the Python double
    // becomes an f32 scalar, then multiply and divide in f32, left to right.
    let neg_ln = -(LN_10000 as f32);
    for (i, (c, s_out)) in cos.iter_mut().zip(sin.iter_mut()).enumerate() {
        let f = exp_f32(neg_ln * i as f32 / half as f32);
        let arg = (s * f) as f64;
        *c = arg.cos() as f32;
        *s_out = arg.sin() as f32;
    }
}

/// MDM's positional table row for position `p`: `out[2i] = sin(p·d_i)`, `out[2i+1] = cos(p·d_i)`,
/// `d_i = exp(-(2i)·ln(10000)/dim)` (computed in f32 as PyTorch does).
///
/// MDM writes `arange(0, dim, 2).float() * (-np.log(10000.0) / dim)`: the quotient is a float64
/// scalar, rounded once to f32 before the multiply. (Dividing in f32 instead differs by an ulp
/// for some widths, e.g. 36, 72, 196.)
pub fn sinusoid_interleaved(p: f32, out: &mut [f32]) {
    assert_eq!(out.len() % 2, 0, "sinusoid_interleaved: odd dim");
    let step = (-LN_10000 / out.len() as f64) as f32;
    for (i, pair) in out.chunks_exact_mut(2).enumerate() {
        let d = exp_f32((2 * i) as f32 * step);
        let arg = (p * d) as f64;
        pair[0] = arg.sin() as f32;
        pair[1] = arg.cos() as f32;
    }
}

/// The guidance-scale embedding of latent consistency distillation (MotionLCM's
/// `get_guidance_scale_embedding`, as in diffusers' LCM pipelines; Dai-Wenxun/MotionLCM v2.0
/// `mld/utils/utils.py`): with `half = dim/2`, `w' = 1000·w` and
/// `f_i = exp(−(ln 10000 / (half − 1))·i)`, `out = [sin(w'·f_0..), cos(w'·f_0..)]` (sine first).
/// Every factor is formed in f32 as PyTorch does (`torch.log(torch.tensor(10000.0))` is an f32
/// scalar). `dim` is even and at least 4.
pub fn guidance_embedding(w: f32, out: &mut [f32]) {
    assert!(
        out.len().is_multiple_of(2) && out.len() >= 4,
        "guidance_embedding: dim must be even and at least 4"
    );
    let half = out.len() / 2;
    let step = (LN_10000 as f32) / (half - 1) as f32;
    let w = w * 1000.0;
    let (sin, cos) = out.split_at_mut(half);
    for (i, (s_out, c)) in sin.iter_mut().zip(cos.iter_mut()).enumerate() {
        let f = exp_f32(i as f32 * -step);
        let arg = (w * f) as f64;
        *s_out = arg.sin() as f32;
        *c = arg.cos() as f32;
    }
}

/// Correctly rounded (barring double rounding) and platform-independent f32 exp.
fn exp_f32(x: f32) -> f32 {
    (x as f64).exp() as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn guidance_embedding_is_sine_first_over_half_minus_one() {
        // dim 4: half 2, frequencies exp(0) = 1 and exp(−ln 10000) = 1e-4; w = 0.5 → w' = 500.
        let mut e = [0f32; 4];
        guidance_embedding(0.5, &mut e);
        let want = [500f64.sin(), 0.05f64.sin(), 500f64.cos(), 0.05f64.cos()];
        assert_close(&e, &want, 1e-6);
    }

    fn assert_close(got: &[f32], want: &[f64], tol: f64) {
        assert_eq!(got.len(), want.len());
        for (i, (&g, &w)) in got.iter().zip(want).enumerate() {
            assert!((g as f64 - w).abs() <= tol, "[{i}]: {g} vs {w}");
        }
    }

    #[test]
    fn ln_10000_matches_f32_ln() {
        assert_eq!(LN_10000, 10000f64.ln());
        assert_eq!(LN_10000 as f32, 10000f32.ln());
    }

    #[test]
    fn embedding_copies_rows() {
        let table: Vec<f32> = (0..12).map(|v| v as f32).collect(); // 4 rows of 3
        let mut out = vec![-1.0; 4 * 3];
        embedding(&table, 3, &[2, 0, 3, 2], &mut out);
        assert_eq!(
            out,
            [6.0, 7.0, 8.0, 0.0, 1.0, 2.0, 9.0, 10.0, 11.0, 6.0, 7.0, 8.0]
        );
        embedding(&table, 3, &[], &mut out);
    }

    #[test]
    fn cos_first_at_zero_is_ones_then_zeros() {
        let mut out = vec![f32::NAN; 10];
        sinusoid_cos_first(0.0, &mut out);
        assert_eq!(out, [1.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
    }

    #[test]
    fn cos_first_dim4_at_one() {
        // half = 2: f = [1, exp(-ln(10000)/2) = 0.01].
        let mut out = [0.0f32; 4];
        sinusoid_cos_first(1.0, &mut out);
        assert_close(
            &out,
            &[1f64.cos(), 0.01f64.cos(), 1f64.sin(), 0.01f64.sin()],
            1e-7,
        );
    }

    #[test]
    fn cos_first_matches_pytorch() {
        // torch 2.x CPU, guided-diffusion `timestep_embedding(tensor([937.]), 12)`.
        let want = [
            0.6928306221961975,
            0.6905012130737305,
            0.882047712802887,
            -0.9985000491142273,
            -0.4330817759037018,
            0.9069051146507263,
            0.721100389957428,
            0.7233312726020813,
            -0.4711601138114929,
            0.05475068464875221,
            0.9013546109199524,
            0.4213349223136902,
        ];
        let mut out = [0.0f32; 12];
        sinusoid_cos_first(937.0, &mut out);
        assert_close(&out, &want, 2e-7);
    }

    #[test]
    fn interleaved_at_zero_and_one() {
        let mut out = [f32::NAN; 8];
        sinusoid_interleaved(0.0, &mut out);
        assert_eq!(out, [0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0]);
        // dim 4: d = [1, exp(-2·ln(10000)/4) = 0.01].
        let mut out = [0.0f32; 4];
        sinusoid_interleaved(1.0, &mut out);
        assert_close(
            &out,
            &[1f64.sin(), 1f64.cos(), 0.01f64.sin(), 0.01f64.cos()],
            1e-7,
        );
    }

    #[test]
    fn interleaved_matches_pytorch() {
        // torch 2.x CPU, MDM `PositionalEncoding(36).pe[123]`; 36 is a width where the f32
        // quotient and the f64-then-rounded quotient differ.
        let want = [
            -0.4599034786224365,
            -0.887968897819519,
            -0.99587482213974,
            -0.09073774516582489,
            0.21980412304401398,
            0.9755440354347229,
            0.9792665839195251,
            0.2025759369134903,
            -0.17715930938720703,
            -0.9841821789741516,
            -0.09850620478391647,
            -0.9951364398002625,
            -0.5430198907852173,
            0.839719831943512,
            -0.27727463841438293,
            -0.9607906937599182,
            0.8865476250648499,
            -0.4626373052597046,
            0.942488968372345,
            0.3342372477054596,
            0.6723402142524719,
            0.7402422428131104,
            0.4277836084365845,
            0.9038811922073364,
            0.2619050443172455,
            0.9650936722755432,
            0.15819330513477325,
            0.9874081611633301,
            0.0950905829668045,
            0.9954686164855957,
            0.057060543447732925,
            0.9983707070350647,
            0.03421881049871445,
            0.9994143843650818,
            0.020516209304332733,
            0.9997895359992981,
        ];
        let mut out = [0.0f32; 36];
        sinusoid_interleaved(123.0, &mut out);
        assert_close(&out, &want, 2e-7);
    }
}
