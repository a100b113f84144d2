//! Embedding lookups and sinusoidal encodings.

/// Copies rows `ids[i]` of `table` (`[rows, dim]`) into `out[i]`. Callers guarantee ids < rows.
pub fn embedding(table: &[f32], dim: usize, ids: &[u32], out: &mut [f32]) {
    let _ = (table, dim, ids, out);
    unimplemented!()
}

/// FLAME/guided-diffusion timestep embedding of `s` into `out` (`dim` even): with `half = dim/2`,
/// `f_i = exp(-ln(10000) · i / half)` in f32, `out = [cos(s·f_0..), sin(s·f_0..)]` (cos first).
pub fn sinusoid_cos_first(s: f32, out: &mut [f32]) {
    let _ = (s, out);
    unimplemented!()
}

/// MDM's positional table row for position `p`: `out[2i] = sin(p·d_i)`, `out[2i+1] = cos(p·d_i)`,
/// `d_i = exp(-(2i)·ln(10000)/dim)` (computed in f32 as PyTorch does).
pub fn sinusoid_interleaved(p: f32, out: &mut [f32]) {
    let _ = (p, out);
    unimplemented!()
}
