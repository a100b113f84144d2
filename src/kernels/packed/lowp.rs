//! Linear layers computed in reduced precision (opt-in load options): products of bf16 pairs
//! accumulated in f32 (`vdpbf16ps`, AVX512_BF16) and products of 8-bit integers accumulated in
//! 32-bit integers (`vpdpbusd` with AVX512_VNNI or AVX-VNNI, `vpmaddubsw` + `vpmaddwd` on plain
//! AVX2).
//!
//! - **bf16 compute** ([`WeightType::Bf16Compute`]): weights rounded to bf16 at load; each call
//!   rounds its activations to bf16 (nearest even). Panel `j`, pair row `q` holds for each of
//!   the [`NR`] columns one 32-bit word: `W[c, 2q]` in the low half, `W[c, 2q + 1]` in the high
//!   half (0 past `k`). An output starts at the bias and takes one `vdpbf16ps` step per pair in
//!   order: `acc += a₂q₊₁·w₂q₊₁`, then `acc += a₂q·w₂q`, each product exact in f32 and each sum
//!   rounded once, with bf16 subnormal inputs and f32 subnormal results read as zero — the
//!   instruction's documented behaviour, which the portable kernel reproduces, so both give the
//!   same bits (tested where the CPU runs both).
//! - **int8 compute** ([`WeightType::Int8`]): per output column a symmetric weight scale
//!   `s_w = max|W[c, :]| / 127` and weights `round(W / s_w)` in −127..=127 (a quarter of f32's
//!   memory); per call and row a symmetric activation scale `s_a = max|x[r, :]| / 127` and
//!   values `round(x / s_a)`, stored offset by 128 as unsigned bytes (`vpdpbusd` multiplies
//!   unsigned by signed). Quad row `q` of a panel holds `W[c, 4q..4q + 4]` per column. The
//!   integer sum is exact (32-bit sums over blocks of 32,768 inputs, added in 64 bits), so every
//!   kernel gives the same integers; the output is `(Σ − 128·Σ_k w) · (s_a·s_w) + bias` in one fused
//!   multiply-add. Without VNNI, AVX2's `vpmaddubsw` adds two unsigned × signed products into a
//!   saturating 16-bit lane: activations there use 63 levels (`s_a = max|x| / 63`, offset 64,
//!   bytes ≤ 127), so a pair is at most 2·127·127 < 2¹⁵ and never saturates ([`Int8Path`]); the
//!   sums are again exact, the same as the portable kernel's on those bytes, but the activations
//!   carry one bit less than on VNNI.
//!
//! Both are bit-identical for any thread count (each output is one fixed chain). Rows are cut
//! into tiles of [`MR512`], activations converted once per call into a per-thread buffer laid
//! out tile by tile (each step's 12 words adjacent), then split over the pool by weight panels
//! or by row tiles as the f32 kernel does.

use half::bf16;
use rayon::prelude::*;

use super::super::gemm::SharedMut;
use super::{
    equal_part, part_lines, prefetch_part, split_work, transpose_rows4, Activation, Isa, Line,
    PackedWeights, WeightType, MR512, NR, PAR_MIN_MACS,
};

/// Most row tiles per M block: the activations of 10 tiles stay in L2 while a panel streams
/// past them. A task's tiles are cut into equal blocks: 9 tiles as 8 + 1 would stream every
/// panel again for one tile.
const TILES_PER_BLOCK: usize = 10;

/// Quads summed in 32 bits before the sum moves to 64 (`4 · 8192 · 255 · 127 < 2³¹`), so the
/// integer sums are exact for any `k`.
const INT8_BLOCK: usize = 8192;

/// Whether this CPU has the instruction of a reduced-precision kernel (on top of AVX-512F).
pub(crate) fn has_bf16_dot() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        Isa::Avx512.supported() && is_x86_feature_detected!("avx512bf16")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

pub(crate) fn has_int8_dot() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        Isa::Avx512.supported() && is_x86_feature_detected!("avx512vnni")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// Whether this CPU has the VEX-encoded `vpdpbusd` on 256 bits (AVX-VNNI: Intel since Alder
/// Lake, AMD since Zen 5), with the AVX2 kernel's needs.
pub(crate) fn has_avx_vnni() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        Isa::Avx2.supported() && is_x86_feature_detected!("avxvnni")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// Whether this CPU runs the EVEX twin of the AVX-VNNI tile (the same instruction on 256 bits,
/// encoded for AVX512_VNNI + AVX512VL): how the tile's code is tested on a CPU without
/// AVX-VNNI. Never chosen by the dispatch.
fn has_avx_vnni_twin() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        Isa::Avx2.supported()
            && is_x86_feature_detected!("avx512vnni")
            && is_x86_feature_detected!("avx512vl")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// Which int8 tile a call runs and so how it quantises its activations.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Int8Path {
    /// `vpdpbusd` (AVX-512 kernel with AVX512_VNNI): 127 levels.
    Vnni,
    /// `Vnni` with pairs of full panels on a 12×32 tile (where the f32 kernel runs 12×32, see
    /// `packed::wide_tiles`: a 12×16 tile is limited by loads there): the same bits.
    VnniWide,
    /// `vpdpbusd` on 256 bits, VEX-encoded (AVX-VNNI, with either kernel when the CPU lacks
    /// AVX512_VNNI): 127 levels, the same integers and bits as `Vnni`.
    AvxVnni,
    /// `vpmaddubsw` + `vpmaddwd` (AVX2, or AVX-512 without VNNI): 63 levels, saturation-free.
    Avx2,
    /// The exact portable tile: 127 levels, as VNNI (the same bits).
    Portable,
}

impl Int8Path {
    pub(crate) fn for_kernel(isa: Isa) -> Int8Path {
        match isa {
            Isa::Avx512 if has_int8_dot() && super::wide_tiles() => Int8Path::VnniWide,
            Isa::Avx512 if has_int8_dot() => Int8Path::Vnni,
            Isa::Avx512 | Isa::Avx2 if has_avx_vnni() => Int8Path::AvxVnni,
            Isa::Avx512 | Isa::Avx2 if Isa::Avx2.supported() => Int8Path::Avx2,
            _ => Int8Path::Portable,
        }
    }

    /// The largest activation magnitude after quantisation; bytes are offset by `levels + 1`.
    fn levels(self) -> i32 {
        match self {
            Int8Path::Avx2 => 63,
            _ => 127,
        }
    }

    /// The instructions, for `flame info`.
    pub(crate) fn name(self) -> &'static str {
        match self {
            Int8Path::Vnni => "vpdpbusd, AVX512_VNNI",
            Int8Path::VnniWide => "vpdpbusd, AVX512_VNNI, 12x32 tiles",
            Int8Path::AvxVnni => "vpdpbusd on 256 bits, AVX-VNNI",
            Int8Path::Avx2 => "vpmaddubsw, AVX2; activations in 63 levels",
            Int8Path::Portable => "portable",
        }
    }
}

/// Words per panel column over `k` inputs: pairs (bf16) or quads (int8).
pub(super) fn steps(ty: WeightType, k: usize) -> usize {
    match ty {
        WeightType::Bf16Compute => k.div_ceil(2),
        WeightType::Int8 => k.div_ceil(4),
        _ => unreachable!("{ty:?} is not a reduced-precision compute type"),
    }
}

/// Rounds one activation row to bf16 bits in `bits` (`2·s` of them, zero past the row's end),
/// as `half`'s `bf16::from_f32` does (nearest even; NaN kept quiet); the AVX2 version computes
/// the same bits.
fn bf16_row(row: &[f32], bits: &mut [u16]) {
    #[cfg(target_arch = "x86_64")]
    if Isa::Avx2.supported() {
        // SAFETY: the CPU has avx2 (checked just above).
        return unsafe { avx2::bf16_row(row, bits) };
    }
    finish_bf16_row(row, 0, bits);
}

/// Bits `from..` of [`bf16_row`].
fn finish_bf16_row(row: &[f32], from: usize, bits: &mut [u16]) {
    for (j, b) in bits.iter_mut().enumerate().skip(from) {
        *b = row.get(j).map_or(0, |&v| bf16::from_f32(v).to_bits());
    }
}

/// `v / s` rounded to the nearest integer (ties to even) in −levels..=levels (`inv` = 1/s, 0
/// for an all-zero row).
fn quantize(v: f32, inv: f32, levels: i32) -> i8 {
    (v * inv)
        .round_ties_even()
        .clamp(-levels as f32, levels as f32) as i8
}

/// Quantises one activation row into `bytes` (`4·s` of them: value + `levels + 1`, the zero
/// point past the row's end) and returns its scale (NaN, and every byte the zero point, when a
/// value is not finite). The AVX2 version computes the same bits.
fn quantize_row(row: &[f32], levels: i32, bytes: &mut [u8]) -> f32 {
    #[cfg(target_arch = "x86_64")]
    if Isa::Avx512.supported() {
        // SAFETY: the CPU has avx512f (checked just above).
        return unsafe { avx512::quantize_row(row, levels, bytes) };
    }
    #[cfg(target_arch = "x86_64")]
    if Isa::Avx2.supported() {
        // SAFETY: the CPU has avx2 and fma (checked just above).
        return unsafe { avx2::quantize_row(row, levels, bytes) };
    }
    let scale = scale_of(row, levels);
    finish_row(row, 0, scale, levels, bytes);
    scale
}

/// Bytes `from..` of [`quantize_row`] for a row whose scale is known.
fn finish_row(row: &[f32], from: usize, scale: f32, levels: i32, bytes: &mut [u8]) {
    let zero = levels + 1;
    if scale.is_nan() {
        bytes.fill(zero as u8);
        return;
    }
    let inv = inverse(scale);
    for (j, b) in bytes.iter_mut().enumerate().skip(from) {
        *b = match row.get(j) {
            Some(&v) => (quantize(v, inv, levels) as i32 + zero) as u8,
            None => zero as u8,
        };
    }
}

/// The symmetric scale of `v` (`max|v| / levels`), NaN when a value is not finite so that the
/// outputs are not finite either (the session's check reports it).
fn scale_of(v: &[f32], levels: i32) -> f32 {
    if v.iter().any(|x| !x.is_finite()) {
        return f32::NAN;
    }
    v.iter().fold(0.0f32, |m, x| m.max(x.abs())) / levels as f32
}

/// The scale of a row whose vector part left per-lane maxima of |x| in `lanes` (and no
/// non-finite value when `finite`), with the values past it in `tail`: as [`scale_of`].
#[cfg(target_arch = "x86_64")]
fn lanes_scale(lanes: &[f32], finite: bool, tail: &[f32], levels: i32) -> f32 {
    let m = lanes.iter().fold(0.0f32, |a, &b| a.max(b));
    if !finite || tail.iter().any(|v| !v.is_finite()) {
        return f32::NAN;
    }
    tail.iter().fold(m, |a, v| a.max(v.abs())) / levels as f32
}

fn inverse(scale: f32) -> f32 {
    if scale > 0.0 {
        1.0 / scale
    } else {
        0.0
    }
}

/// Converts one row in place into its `words.len()` little-endian words: bf16 pairs, or bytes
/// quantised to `levels` and offset by `levels + 1` (the row's scale is returned; 0 for bf16).
fn convert_row(ty: WeightType, row: &[f32], levels: i32, words: &mut [u32]) -> f32 {
    let (p, s) = (words.as_mut_ptr(), words.len());
    // SAFETY: the s words are 4·s initialised bytes, aligned for u8 and u16; each view lives
    // only for its call.
    match ty {
        WeightType::Bf16Compute => {
            bf16_row(row, unsafe {
                std::slice::from_raw_parts_mut(p as *mut u16, 2 * s)
            });
            0.0
        }
        _ => quantize_row(row, levels, unsafe {
            std::slice::from_raw_parts_mut(p as *mut u8, 4 * s)
        }),
    }
}

/// Packs `w` (`[n, k]`) for a reduced-precision type into `p` (whose `k`, `n`, `ty` are set).
pub(super) fn pack(p: &mut PackedWeights, w: &[f32]) {
    let (n, k, ty) = (p.n, p.k, p.ty);
    let panels = n.div_ceil(NR);
    let s = steps(ty, k);
    p.lines = vec![Line([0; 64]); panels * s];
    // SAFETY: one 64-byte line per (panel, step) holds its NR 32-bit words; every bit pattern
    // is a valid u32.
    let words: &mut [u32] = unsafe {
        std::slice::from_raw_parts_mut(p.lines.as_mut_ptr() as *mut u32, panels * s * NR)
    };
    // Each column (a row of `w`) is converted as an activation row is, 8 values at a time
    // where the CPU has AVX2, then its words go to their panel; columns past `n` stay zero.
    if ty == WeightType::Int8 {
        p.scales = vec![0.0; n];
        p.colsum = vec![0; n];
    }
    let mut row = vec![0u32; s];
    for col in 0..n {
        // The activations' quantiser at 127 levels gives `v + 128` for the weights'
        // `v = round(W / s_w)` (the same scale and rounding; 128, i.e. 0, past `k` and for a
        // column that is not finite, whose scale is NaN): XOR 0x80 makes the signed bytes.
        let scale = convert_row(ty, &w[col * k..(col + 1) * k], 127, &mut row);
        let (j, c) = (col / NR, col % NR);
        let mut offset = 0;
        for (q, word) in row.iter().enumerate() {
            let mut word = u32::from_le(*word);
            if ty == WeightType::Int8 {
                offset += word.to_le_bytes().iter().map(|&b| b as i32).sum::<i32>();
                word ^= 0x8080_8080;
            }
            words[(j * s + q) * NR + c] = word;
        }
        if ty == WeightType::Int8 {
            p.scales[col] = scale;
            p.colsum[col] = offset - 128 * 4 * s as i32;
        }
    }
}

/// Packs int8 weights `q` (`[n, k]`) with their column scales into `p` (whose `k`, `n` are set,
/// type int8): the words and column sums [`pack`] makes from the same integers.
pub(super) fn pack_int8(p: &mut PackedWeights, q: &[i8], scales: &[f32]) {
    let (n, k) = (p.n, p.k);
    let panels = n.div_ceil(NR);
    let s = steps(WeightType::Int8, k);
    p.lines = vec![Line([0; 64]); panels * s];
    // SAFETY: as in `pack`.
    let words: &mut [u32] = unsafe {
        std::slice::from_raw_parts_mut(p.lines.as_mut_ptr() as *mut u32, panels * s * NR)
    };
    p.scales = scales.to_vec();
    p.colsum = vec![0; n];
    for col in 0..n {
        let row = &q[col * k..(col + 1) * k];
        let (j, c) = (col / NR, col % NR);
        for (step, quad) in row.chunks(4).enumerate() {
            let mut bytes = [0u8; 4];
            for (b, &v) in bytes.iter_mut().zip(quad) {
                *b = v as u8;
            }
            words[(j * s + step) * NR + c] = u32::from_le_bytes(bytes);
        }
        p.colsum[col] = row.iter().map(|&v| v as i32).sum();
    }
}

/// The weights back as `[n, k]` f32: bf16 values widened, int8 values times their scale.
pub(super) fn unpack(p: &PackedWeights) -> Vec<f32> {
    let (n, k) = (p.n, p.k);
    let s = steps(p.ty, k);
    let words = p.words();
    let mut w = vec![0.0f32; n * k];
    for col in 0..n {
        let (j, c) = (col / NR, col % NR);
        for i in 0..k {
            let word = words[(j * s + i / per_word(p.ty)) * NR + c];
            w[col * k + i] = match p.ty {
                WeightType::Bf16Compute => {
                    bf16::from_bits((word >> (16 * (i % 2))) as u16).to_f32()
                }
                _ => (word.to_le_bytes()[i % 4] as i8) as f32 * p.scales[col],
            };
        }
    }
    w
}

fn per_word(ty: WeightType) -> usize {
    match ty {
        WeightType::Bf16Compute => 2,
        _ => 4,
    }
}

thread_local! {
    /// Each calling thread's converted activations (words) and row scales, reused across calls.
    static ACTS: std::cell::RefCell<(Vec<u32>, Vec<f32>)> = Default::default();
    /// Each converting thread's four rows of converted activations, reused across calls.
    static ROW: std::cell::RefCell<Vec<u32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// `y = act(x · Wᵀ + bias)` for a reduced-precision `w` on kernel `isa` (the portable
/// reproduction when the CPU lacks the instruction).
pub(super) fn linear(
    isa: Isa,
    x: &[f32],
    w: &PackedWeights,
    bias: Option<&[f32]>,
    act: Activation,
    y: &mut [f32],
    m: usize,
) {
    ACTS.with(|cell| match cell.try_borrow_mut() {
        Ok(mut bufs) => {
            let (words, scales) = &mut *bufs;
            linear_with(isa, x, w, bias, act, y, m, words, scales)
        }
        Err(_) => linear_with(isa, x, w, bias, act, y, m, &mut Vec::new(), &mut Vec::new()),
    })
}

#[allow(clippy::too_many_arguments)]
fn linear_with(
    isa: Isa,
    x: &[f32],
    w: &PackedWeights,
    bias: Option<&[f32]>,
    act: Activation,
    y: &mut [f32],
    m: usize,
    words: &mut Vec<u32>,
    scales: &mut Vec<f32>,
) {
    let (k, n, ty) = (w.k, w.n, w.ty);
    let s = steps(ty, k);
    let tiles = m.div_ceil(MR512);
    let int8 = forced_int8_path().unwrap_or_else(|| Int8Path::for_kernel(isa));
    convert(ty, int8.levels(), x, m, k, s, words, scales);
    let job = Job {
        native: isa == Isa::Avx512 && has_bf16_dot(),
        int8,
        w,
        s,
        acts: words,
        row_scales: scales,
        bias,
        act,
        y: SharedMut(y.as_mut_ptr()),
        m,
    };
    split_work(tiles, n.div_ceil(NR), m * k * n, |t0, t1, j0, j1| {
        job.run(t0, t1, j0, j1)
    });
}

#[cfg(test)]
thread_local! {
    /// The int8 tile a test asks for on this thread, whatever the kernel would pick.
    static FORCED_INT8: std::cell::Cell<Option<Int8Path>> = const { std::cell::Cell::new(None) };
}

#[cfg(test)]
fn forced_int8_path() -> Option<Int8Path> {
    FORCED_INT8.with(|f| f.get())
}

#[cfg(test)]
impl Int8Path {
    const ALL: [Int8Path; 5] = [
        Int8Path::Vnni,
        Int8Path::VnniWide,
        Int8Path::AvxVnni,
        Int8Path::Avx2,
        Int8Path::Portable,
    ];

    /// Whether this CPU runs the path's tile (`AvxVnni` through its EVEX twin without AVX-VNNI).
    fn runs_here(self) -> bool {
        match self {
            Int8Path::Vnni | Int8Path::VnniWide => has_int8_dot(),
            Int8Path::AvxVnni => has_avx_vnni() || has_avx_vnni_twin(),
            Int8Path::Avx2 => Isa::Avx2.supported(),
            Int8Path::Portable => true,
        }
    }

    /// `f` with every int8 call made on this thread running this path's tile.
    fn forced<R>(self, f: impl FnOnce() -> R) -> R {
        assert!(self.runs_here(), "{self:?} does not run here");
        let before = FORCED_INT8.with(|c| c.replace(Some(self)));
        let r = f();
        FORCED_INT8.with(|c| c.set(before));
        r
    }
}

#[cfg(not(test))]
fn forced_int8_path() -> Option<Int8Path> {
    None
}

/// Converts `x [m, k]` into words laid out tile by tile: word `(t·s + q)·12 + i` is step `q`
/// of row `12t + i` (a bf16 pair, or four bytes quantised to `levels` and offset by
/// `levels + 1`); rows past `m` are zero. Int8 also fills the row scales. Tiles are converted
/// in parallel (each is independent).
#[allow(clippy::too_many_arguments)]
fn convert(
    ty: WeightType,
    levels: i32,
    x: &[f32],
    m: usize,
    k: usize,
    s: usize,
    words: &mut Vec<u32>,
    scales: &mut Vec<f32>,
) {
    let tiles = m.div_ceil(MR512);
    // Every word and scale of a real row is written below; only the last tile's missing rows
    // need zeros, so the buffers are not cleared (a pass over the whole block per call).
    words.resize(tiles * s * MR512, 0);
    scales.resize(tiles * MR512, 0.0);
    if !m.is_multiple_of(MR512) {
        let last = (tiles - 1) * s * MR512;
        for step in words[last..tiles * s * MR512].chunks_exact_mut(MR512) {
            step[m % MR512..].fill(0);
        }
        scales[m..tiles * MR512].fill(0.0);
    }
    let tile = |t: usize, out: &mut [u32], tile_scales: &mut [f32]| {
        ROW.with_borrow_mut(|row_words| {
            // Four rows converted in place: 4·s bytes (int8) or 2·s bf16 values each, read back
            // as the rows' s little-endian words, then written to the tile by 4 × 4 word
            // transposes (a scatter of single words was as slow as the quantisation itself).
            row_words.clear();
            row_words.resize(4 * s, 0);
            let rows = MR512.min(m - t * MR512);
            for i0 in (0..rows).step_by(4) {
                let group = 4.min(rows - i0);
                for (i, words) in row_words.chunks_exact_mut(s).take(group).enumerate() {
                    let r = t * MR512 + i0 + i;
                    // Past k the weight is 0: the byte adds nothing; the zero point (a zero
                    // value) keeps the column-sum correction exact.
                    tile_scales[i0 + i] = convert_row(ty, &x[r * k..(r + 1) * k], levels, words);
                }
                if group == 4 && cfg!(target_endian = "little") {
                    let (a, rest) = row_words.split_at(s);
                    let (b, rest) = rest.split_at(s);
                    let (c, d) = rest.split_at(s);
                    transpose_rows4([a, b, c, d], &mut out[i0..]);
                    continue;
                }
                for (i, words) in row_words.chunks_exact(s).take(group).enumerate() {
                    for (q, &w) in words.iter().enumerate() {
                        out[q * MR512 + i0 + i] = u32::from_le(w);
                    }
                }
            }
        })
    };
    if s == 0 {
        return;
    }
    if crate::kernels::threads() > 1 && m * k >= PAR_MIN_MACS / 64 {
        words
            .par_chunks_mut(s * MR512)
            .zip(scales.par_chunks_mut(MR512))
            .enumerate()
            .for_each(|(t, (out, sc))| tile(t, out, sc));
    } else {
        words
            .chunks_mut(s * MR512)
            .zip(scales.chunks_mut(MR512))
            .enumerate()
            .for_each(|(t, (out, sc))| tile(t, out, sc));
    }
}

/// One call's operands, shared by its tasks.
struct Job<'a> {
    /// The CPU runs `vdpbf16ps` (otherwise the portable reproduction runs).
    native: bool,
    /// The int8 tile (and the activations' quantisation).
    int8: Int8Path,
    w: &'a PackedWeights,
    /// Steps (pairs or quads) per column.
    s: usize,
    acts: &'a [u32],
    row_scales: &'a [f32],
    bias: Option<&'a [f32]>,
    act: Activation,
    y: SharedMut,
    m: usize,
}

impl Job<'_> {
    /// Row tiles `t0..t1` × panels `j0..j1`.
    fn run(&self, t0: usize, t1: usize, j0: usize, j1: usize) {
        let (n, s) = (self.w.n, self.s);
        let words = self.w.words();
        let block = equal_part(t1 - t0, TILES_PER_BLOCK);
        for tb in (t0..t1).step_by(block) {
            let tiles = block.min(t1 - tb);
            let mut j = j0;
            while j < j1 {
                if self.w.ty == WeightType::Int8
                    && self.int8 == Int8Path::VnniWide
                    && self.s <= INT8_BLOCK
                    && j + 1 < j1
                    && (j + 2) * NR <= n
                {
                    self.run_pair(tb, tiles, j, j1);
                    j += 2;
                    continue;
                }
                let c0 = j * NR;
                let cols = NR.min(n - c0);
                let mut bias = [0.0f32; NR];
                if let Some(b) = self.bias {
                    bias[..cols].copy_from_slice(&b[c0..c0 + cols]);
                }
                let panel = &words[j * s * NR..(j + 1) * s * NR];
                for t in tb..tb + tiles {
                    // The next panel's lines, a share per tile (see `Job::panel` for f32).
                    if j + 1 < j1 {
                        let next = words[(j + 1) * s * NR..].as_ptr() as *const u8;
                        prefetch_part(next, s * NR * 4, tiles, t - tb);
                    }
                    let a = &self.acts[t * s * MR512..(t + 1) * s * MR512];
                    let mut tile = [0.0f32; MR512 * NR];
                    match self.w.ty {
                        WeightType::Bf16Compute => self.bf16_tile(a, panel, &bias, &mut tile),
                        _ => self.int8_tile(t, c0, cols, a, panel, &bias, &mut tile),
                    }
                    let rows = MR512.min(self.m - t * MR512);
                    for i in 0..rows {
                        let r = t * MR512 + i;
                        // SAFETY: row r < m, columns c0..c0 + cols ≤ n lie inside the checked
                        // m×n output; this task alone writes this (tile, panel) block.
                        let out = unsafe {
                            std::slice::from_raw_parts_mut(self.y.get().add(r * n + c0), cols)
                        };
                        if let Ok(full) = <&mut [f32; NR]>::try_from(&mut *out) {
                            // A whole row of the tile: one fixed-size copy (a 64-byte move),
                            // not a call to `memmove` per row.
                            full.copy_from_slice(&tile[i * NR..i * NR + NR]);
                        } else {
                            out.copy_from_slice(&tile[i * NR..i * NR + cols]);
                        }
                        self.act.apply(out);
                    }
                }
                j += 1;
            }
        }
    }

    /// Row tiles `tb..tb + tiles` of the full panels `j` and `j + 1` on the 12×32 VNNI tile
    /// (`VnniWide`, one block of sums); `j1` ends the task's panels.
    fn run_pair(&self, tb: usize, tiles: usize, j: usize, j1: usize) {
        let (n, s) = (self.w.n, self.s);
        let words = self.w.words();
        let c0 = j * NR;
        let zero = self.int8.levels() + 1;
        let (mut offset, mut wscale, mut bias) =
            ([0i32; 2 * NR], [0.0f32; 2 * NR], [0.0f32; 2 * NR]);
        for (o, &c) in offset.iter_mut().zip(&self.w.colsum[c0..c0 + 2 * NR]) {
            *o = zero * c;
        }
        wscale.copy_from_slice(&self.w.scales[c0..c0 + 2 * NR]);
        if let Some(b) = self.bias {
            bias.copy_from_slice(&b[c0..c0 + 2 * NR]);
        }
        let (b0, b1) = words[j * s * NR..(j + 2) * s * NR].split_at(s * NR);
        for t in tb..tb + tiles {
            // The next two panels' lines, a share per tile, hinted by the tile one per step
            // (a burst before the tile stalls on the fill buffers; see `Job::panel` for f32).
            let mut hints = [(std::ptr::null::<u8>(), 0usize); 2];
            for (h, q) in hints.iter_mut().zip(j + 2..(j + 4).min(j1)) {
                let (l0, l1) = part_lines(s * NR * 4, tiles, t - tb);
                *h = (
                    (words[q * s * NR..].as_ptr() as *const u8).wrapping_add(l0 * 64),
                    l1 - l0,
                );
            }
            let a = &self.acts[t * s * MR512..(t + 1) * s * MR512];
            let rows = MR512.min(self.m - t * MR512);
            let mut tile = [0.0f32; MR512 * 2 * NR];
            #[cfg(target_arch = "x86_64")]
            // SAFETY: `VnniWide` is chosen only when the CPU has avx512f and avx512vnni; `a`
            // holds s·12 words, `b0` and `b1` s·NR each; s ≤ INT8_BLOCK (checked by the caller).
            unsafe {
                avx512::tile_int8_scaled_wide(
                    s,
                    a.as_ptr(),
                    (b0.as_ptr(), b1.as_ptr()),
                    (&offset, &wscale, &bias),
                    &self.row_scales[t * MR512..t * MR512 + rows],
                    &mut tile,
                    hints,
                )
            };
            #[cfg(not(target_arch = "x86_64"))]
            unreachable!("VnniWide runs on x86-64 only");
            for i in 0..rows {
                let r = t * MR512 + i;
                // SAFETY: row r < m, columns c0..c0 + 32 ≤ n lie inside the checked m×n
                // output; this task alone writes this (tile, panels) block.
                let out = unsafe { &mut *(self.y.get().add(r * n + c0) as *mut [f32; 2 * NR]) };
                out.copy_from_slice(&tile[i * 2 * NR..(i + 1) * 2 * NR]);
                self.act.apply(out);
            }
        }
    }

    fn bf16_tile(&self, a: &[u32], b: &[u32], bias: &[f32; NR], tile: &mut [f32; MR512 * NR]) {
        #[cfg(target_arch = "x86_64")]
        if self.native {
            // SAFETY: `native` is set only when the CPU has avx512f and avx512bf16; the slices
            // hold s·12 and s·NR words and the tile 12·NR values.
            unsafe { avx512::tile_bf16(self.s, a.as_ptr(), b.as_ptr(), bias, tile) };
            return;
        }
        portable_bf16_tile(self.s, a, b, bias, tile);
    }

    #[allow(clippy::too_many_arguments)]
    fn int8_tile(
        &self,
        t: usize,
        c0: usize,
        cols: usize,
        a: &[u32],
        b: &[u32],
        bias: &[f32; NR],
        tile: &mut [f32; MR512 * NR],
    ) {
        let rows = MR512.min(self.m - t * MR512);
        #[cfg(target_arch = "x86_64")]
        if self.int8 != Int8Path::Portable && self.s <= INT8_BLOCK {
            // One block: the sums stay in 32 bits and the epilogue runs on the vectors.
            let (mut colsum, mut wscale, mut rscale) = ([0i32; NR], [0.0f32; NR], [0.0f32; MR512]);
            // The zero point's share of each sum, `(levels + 1)·Σ_k w` (exact in 32 bits).
            let zero = self.int8.levels() + 1;
            for (o, &c) in colsum[..cols].iter_mut().zip(&self.w.colsum[c0..c0 + cols]) {
                *o = zero * c;
            }
            wscale[..cols].copy_from_slice(&self.w.scales[c0..c0 + cols]);
            rscale[..rows].copy_from_slice(&self.row_scales[t * MR512..t * MR512 + rows]);
            let scales = (&colsum, &wscale, bias);
            let (a, b) = (a.as_ptr(), b.as_ptr());
            // SAFETY: `Vnni` is chosen only when the CPU has avx512f and avx512vnni, `AvxVnni`
            // only when it has avx2, fma and a 256-bit `vpdpbusd`, `Avx2` only when it has avx2
            // and fma; the slices hold s·12 and s·NR words.
            unsafe {
                match self.int8 {
                    Int8Path::Vnni | Int8Path::VnniWide => {
                        avx512::tile_int8_scaled(self.s, a, b, scales, &rscale[..rows], tile)
                    }
                    Int8Path::AvxVnni => avx2::tile_int8_scaled(
                        avx2::vnni_tile(),
                        self.s,
                        a,
                        b,
                        scales,
                        &rscale[..rows],
                        tile,
                    ),
                    _ => avx2::tile_int8_scaled(
                        avx2::tile_int8,
                        self.s,
                        a,
                        b,
                        scales,
                        &rscale[..rows],
                        tile,
                    ),
                }
            };
            return;
        }
        let mut total = [0i64; MR512 * NR];
        for q0 in (0..self.s).step_by(INT8_BLOCK) {
            let q1 = (q0 + INT8_BLOCK).min(self.s);
            let (a, b) = (&a[q0 * MR512..q1 * MR512], &b[q0 * NR..q1 * NR]);
            let mut sums = [0i32; MR512 * NR];
            #[cfg(target_arch = "x86_64")]
            let done = match self.int8 {
                // SAFETY: `Vnni` is chosen only when the CPU has avx512f and avx512vnni,
                // `AvxVnni` only when it has a 256-bit `vpdpbusd`, `Avx2` only when it has avx2;
                // the slices hold (q1 − q0)·12 and (q1 − q0)·NR words.
                Int8Path::Vnni | Int8Path::VnniWide => {
                    unsafe {
                        avx512::tile_int8::<MR512>(q1 - q0, a.as_ptr(), b.as_ptr(), &mut sums)
                    };
                    true
                }
                Int8Path::AvxVnni => {
                    unsafe { avx2::vnni_tile()(MR512, q1 - q0, a.as_ptr(), b.as_ptr(), &mut sums) };
                    true
                }
                Int8Path::Avx2 => {
                    unsafe { avx2::tile_int8(MR512, q1 - q0, a.as_ptr(), b.as_ptr(), &mut sums) };
                    true
                }
                Int8Path::Portable => false,
            };
            #[cfg(not(target_arch = "x86_64"))]
            let done = false;
            if !done {
                portable_int8_tile(q1 - q0, a, b, &mut sums);
            }
            for (t, s) in total.iter_mut().zip(&sums) {
                *t += *s as i64;
            }
        }
        let zero = self.int8.levels() as i64 + 1;
        for i in 0..rows {
            let sa = self.row_scales[t * MR512 + i];
            for c in 0..cols {
                let col = c0 + c;
                let exact = total[i * NR + c] - zero * self.w.colsum[col] as i64;
                tile[i * NR + c] = (exact as f32).mul_add(sa * self.w.scales[col], bias[c]);
            }
        }
    }
}

/// A bf16 word's two values widened, subnormals read as zero (as `vdpbf16ps` does).
fn pair_values(word: u32) -> (f32, f32) {
    let widen = |bits: u32| {
        let v = f32::from_bits(bits << 16);
        if v.is_subnormal() {
            0.0f32.copysign(v)
        } else {
            v
        }
    };
    (widen(word & 0xffff), widen(word >> 16))
}

/// An f32 subnormal result flushed to zero (as `vdpbf16ps` does).
fn flush(v: f32) -> f32 {
    if v.is_subnormal() {
        0.0f32.copysign(v)
    } else {
        v
    }
}

/// The portable reproduction of the AVX512_BF16 tile (see the module doc for the chain).
pub(super) fn portable_bf16_tile(
    s: usize,
    a: &[u32],
    b: &[u32],
    bias: &[f32; NR],
    tile: &mut [f32; MR512 * NR],
) {
    for i in 0..MR512 {
        tile[i * NR..(i + 1) * NR].copy_from_slice(bias);
    }
    for q in 0..s {
        let bq = &b[q * NR..(q + 1) * NR];
        for i in 0..MR512 {
            let (a0, a1) = pair_values(a[q * MR512 + i]);
            for (c, &word) in bq.iter().enumerate() {
                let (b0, b1) = pair_values(word);
                let v = &mut tile[i * NR + c];
                *v = flush(*v + a1 * b1);
                *v = flush(*v + a0 * b0);
            }
        }
    }
}

/// The portable int8 tile: exact 32-bit sums of unsigned × signed bytes.
pub(super) fn portable_int8_tile(s: usize, a: &[u32], b: &[u32], sums: &mut [i32; MR512 * NR]) {
    for q in 0..s {
        for i in 0..MR512 {
            let ab = a[q * MR512 + i].to_le_bytes();
            for c in 0..NR {
                let wb = b[q * NR + c].to_le_bytes();
                let dot: i32 = (0..4).map(|k| ab[k] as i32 * (wb[k] as i8) as i32).sum();
                sums[i * NR + c] = sums[i * NR + c].wrapping_add(dot);
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod avx512 {
    //! The 12×16 reduced-precision tiles: 12 accumulators of 16 lanes, one panel line per
    //! step, each row's word broadcast. The bf16 steps are written in assembly so that each
    //! row's word is broadcast by the product instruction itself (`{1to16}`): compiled from
    //! intrinsics, every broadcast was a separate instruction, and on Zen 4 those compete with
    //! the products (an L1-resident loop: 172 against 230 GFLOP/s on one core).

    use super::{MR512, NR};
    use std::arch::x86_64::*;

    /// `s` steps of `$op` (`vdpbf16ps`, whose pair products do not depend on the operands'
    /// order) into twelve accumulators `$acc`: per step one panel line from `$b` and each of
    /// the 12 words at `$a` broadcast.
    macro_rules! steps {
        ($op:literal, $s:expr, $a:expr, $b:expr, $acc:ident) => {
            if $s > 0 {
                let [mut c0, mut c1, mut c2, mut c3, mut c4, mut c5] =
                    [$acc[0], $acc[1], $acc[2], $acc[3], $acc[4], $acc[5]];
                let [mut c6, mut c7, mut c8, mut c9, mut c10, mut c11] =
                    [$acc[6], $acc[7], $acc[8], $acc[9], $acc[10], $acc[11]];
                std::arch::asm!(
                    "2:",
                    "vmovdqu32 zmm12, [{b}]",
                    concat!($op, " zmm0, zmm12, dword ptr [{a}]{{1to16}}"),
                    concat!($op, " zmm1, zmm12, dword ptr [{a} + 4]{{1to16}}"),
                    concat!($op, " zmm2, zmm12, dword ptr [{a} + 8]{{1to16}}"),
                    concat!($op, " zmm3, zmm12, dword ptr [{a} + 12]{{1to16}}"),
                    concat!($op, " zmm4, zmm12, dword ptr [{a} + 16]{{1to16}}"),
                    concat!($op, " zmm5, zmm12, dword ptr [{a} + 20]{{1to16}}"),
                    concat!($op, " zmm6, zmm12, dword ptr [{a} + 24]{{1to16}}"),
                    concat!($op, " zmm7, zmm12, dword ptr [{a} + 28]{{1to16}}"),
                    concat!($op, " zmm8, zmm12, dword ptr [{a} + 32]{{1to16}}"),
                    concat!($op, " zmm9, zmm12, dword ptr [{a} + 36]{{1to16}}"),
                    concat!($op, " zmm10, zmm12, dword ptr [{a} + 40]{{1to16}}"),
                    concat!($op, " zmm11, zmm12, dword ptr [{a} + 44]{{1to16}}"),
                    "add {a}, 48",
                    "add {b}, 64",
                    "dec {s}",
                    "jnz 2b",
                    a = inout(reg) $a => _,
                    b = inout(reg) $b => _,
                    s = inout(reg) $s => _,
                    inout("zmm0") c0, inout("zmm1") c1, inout("zmm2") c2, inout("zmm3") c3,
                    inout("zmm4") c4, inout("zmm5") c5, inout("zmm6") c6, inout("zmm7") c7,
                    inout("zmm8") c8, inout("zmm9") c9, inout("zmm10") c10,
                    inout("zmm11") c11, out("zmm12") _,
                    options(nostack, readonly),
                );
                $acc = [c0, c1, c2, c3, c4, c5, c6, c7, c8, c9, c10, c11];
            }
        };
    }

    /// # Safety
    /// The CPU supports avx512f and avx512bf16; `a` readable for `s·12` words, `b` for `s·NR`.
    #[target_feature(enable = "avx512f,avx512bf16")]
    pub(super) unsafe fn tile_bf16(
        s: usize,
        a: *const u32,
        b: *const u32,
        bias: &[f32; NR],
        tile: &mut [f32; MR512 * NR],
    ) {
        // SAFETY (whole body): the steps read a[..s·12] and b[..s·NR] (12 and NR words per
        // step), stores stay inside tile.
        unsafe {
            let mut acc = [_mm512_loadu_ps(bias.as_ptr()); MR512];
            steps!("vdpbf16ps", s, a, b, acc);
            for (i, v) in acc.iter().enumerate() {
                _mm512_storeu_ps(tile.as_mut_ptr().add(i * NR), *v);
            }
        }
    }

    /// [`tile_int8`] and the epilogue in one: output `(Σ − offset)·(s_a·s_w) + bias` per
    /// row and column (`offset` = the zero point times the column's weight sum), the same
    /// operations (one rounding each, the last a fused multiply-add) as the scalar epilogue,
    /// so the same bits.
    ///
    /// # Safety
    /// The CPU supports avx512f and avx512vnni; `a` readable for `s·12` words, `b` for `s·NR`;
    /// `s` at most `INT8_BLOCK` (the sums fit 32 bits). `rscale` holds the scales of the
    /// tile's real rows (1 to 12), and only those rows of `tile` are written.
    #[target_feature(enable = "avx512f,avx512vnni")]
    pub(super) unsafe fn tile_int8_scaled(
        s: usize,
        a: *const u32,
        b: *const u32,
        (offset, wscale, bias): (&[i32; NR], &[f32; NR], &[f32; NR]),
        rscale: &[f32],
        tile: &mut [f32; MR512 * NR],
    ) {
        let rows = rscale.len();
        let mut sums = [0i32; MR512 * NR];
        // SAFETY (whole body): loads and stores stay inside the arrays and the granted ranges.
        unsafe {
            super::super::with_rows!(rows; 1 2 3 4 5 6 7 8 9 10 11 12;
                tile_int8(s, a, b, &mut sums));
            scale_columns(
                sums.as_ptr(),
                (offset.as_ptr(), wscale.as_ptr(), bias.as_ptr()),
                rscale,
                tile.as_mut_ptr(),
                NR,
            );
        }
    }

    /// The epilogue on 16 columns of `rscale.len()` rows at `stride`: `(Σ − offset)·(s_a·s_w)
    /// + bias` from `sums` into `out`, one rounding per operation and a fused multiply-add last.
    ///
    /// # Safety
    /// The CPU supports avx512f; `offset`, `wscale` and `bias` readable for 16 values, `sums`
    /// and `out` for `rscale.len()` rows of 16 at `stride`.
    #[inline]
    #[target_feature(enable = "avx512f")]
    unsafe fn scale_columns(
        sums: *const i32,
        (offset, wscale, bias): (*const i32, *const f32, *const f32),
        rscale: &[f32],
        out: *mut f32,
        stride: usize,
    ) {
        // SAFETY (whole body): as the contract grants.
        unsafe {
            let offset = _mm512_loadu_si512(offset as *const _);
            let ws = _mm512_loadu_ps(wscale);
            let bv = _mm512_loadu_ps(bias);
            for (i, &sa) in rscale.iter().enumerate() {
                let acc = _mm512_loadu_si512(sums.add(i * stride) as *const _);
                let exact = _mm512_cvtepi32_ps(_mm512_sub_epi32(acc, offset));
                let scale = _mm512_mul_ps(_mm512_set1_ps(sa), ws);
                _mm512_storeu_ps(out.add(i * stride), _mm512_fmadd_ps(exact, scale, bv));
            }
        }
    }

    /// `super::quantize_row` on 16 values at a time: the same scale (the largest magnitude,
    /// NaN when a value is not finite) and the same round-half-to-even, clamp and offset, so
    /// the same bytes; the 32-bit results (1..=255) are narrowed to bytes by `vpmovdb`.
    ///
    /// # Safety
    /// The CPU supports avx512f; `bytes` holds at least `row.len()` bytes.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn quantize_row(row: &[f32], levels: i32, bytes: &mut [u8]) -> f32 {
        let k = row.len();
        let main = k - k % 16;
        assert!(bytes.len() >= k);
        // SAFETY (whole body): loads stay inside row[..main], stores inside bytes[..main].
        unsafe {
            let inf = _mm512_set1_ps(f32::INFINITY);
            let (mut top, mut bad) = (_mm512_setzero_ps(), 0u16);
            for j in (0..main).step_by(16) {
                let v = _mm512_abs_ps(_mm512_loadu_ps(row.as_ptr().add(j)));
                top = _mm512_max_ps(top, v);
                // Not below infinity: infinite or NaN.
                bad |= _mm512_cmp_ps_mask::<_CMP_NLT_UQ>(v, inf);
            }
            let mut lanes = [0.0f32; 16];
            _mm512_storeu_ps(lanes.as_mut_ptr(), top);
            let scale = super::lanes_scale(&lanes, bad == 0, &row[main..], levels);
            let finite = !scale.is_nan();
            if finite {
                let inv = _mm512_set1_ps(super::inverse(scale));
                let (lo, hi) = (
                    _mm512_set1_ps(-levels as f32),
                    _mm512_set1_ps(levels as f32),
                );
                let zero = _mm512_set1_epi32(levels + 1);
                for j in (0..main).step_by(16) {
                    let v = _mm512_mul_ps(_mm512_loadu_ps(row.as_ptr().add(j)), inv);
                    let r = _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(
                        v,
                    );
                    let q = _mm512_add_epi32(
                        _mm512_cvtps_epi32(_mm512_min_ps(_mm512_max_ps(r, lo), hi)),
                        zero,
                    );
                    _mm_storeu_si128(
                        bytes.as_mut_ptr().add(j) as *mut __m128i,
                        _mm512_cvtepi32_epi8(q),
                    );
                }
            }
            super::finish_row(row, if finite { main } else { 0 }, scale, levels, bytes);
            scale
        }
    }

    /// [`tile_int8_scaled`] on two panels at once (the 12×32 tile): the same sums and
    /// epilogue per column. `hints` are up to two runs of 64-byte lines (start, count) hinted
    /// into L2 one line of each per step.
    ///
    /// # Safety
    /// As [`tile_int8_scaled`], with `b.0` and `b.1` each readable for `s·NR` words.
    #[target_feature(enable = "avx512f,avx512vnni")]
    pub(super) unsafe fn tile_int8_scaled_wide(
        s: usize,
        a: *const u32,
        b: (*const u32, *const u32),
        (offset, wscale, bias): (&[i32; 2 * NR], &[f32; 2 * NR], &[f32; 2 * NR]),
        rscale: &[f32],
        tile: &mut [f32; MR512 * 2 * NR],
        hints: [(*const u8, usize); 2],
    ) {
        let rows = rscale.len();
        let mut sums = [0i32; MR512 * 2 * NR];
        // SAFETY (whole body): loads and stores stay inside the arrays and the granted ranges.
        unsafe {
            super::super::with_rows!(rows; 1 2 3 4 5 6 7 8 9 10 11 12;
                tile_int8_wide(s, a, b, &mut sums, hints));
            for half in 0..2 {
                let c = half * NR;
                scale_columns(
                    sums.as_ptr().add(c),
                    (
                        offset.as_ptr().add(c),
                        wscale.as_ptr().add(c),
                        bias.as_ptr().add(c),
                    ),
                    rscale,
                    tile.as_mut_ptr().add(c),
                    2 * NR,
                );
            }
        }
    }

    /// The 12×32 sums of the tile's first `R` rows (row stride 2·NR in `sums`).
    ///
    /// # Safety
    /// As [`tile_int8`], with `b.0` and `b.1` each readable for `s·NR` words.
    #[target_feature(enable = "avx512f,avx512vnni")]
    unsafe fn tile_int8_wide<const R: usize>(
        s: usize,
        a: *const u32,
        (b0, b1): (*const u32, *const u32),
        sums: &mut [i32; MR512 * 2 * NR],
        hints: [(*const u8, usize); 2],
    ) {
        // SAFETY (whole body): as in `tile_int8`; the hints never fault.
        unsafe {
            let mut lo = [_mm512_setzero_si512(); R];
            let mut hi = [_mm512_setzero_si512(); R];
            for q in 0..s {
                for &(base, lines) in &hints {
                    if q < lines {
                        _mm_prefetch::<_MM_HINT_T1>(base.wrapping_add(q * 64) as *const i8);
                    }
                }
                let w0 = _mm512_loadu_si512(b0.add(q * NR) as *const _);
                let w1 = _mm512_loadu_si512(b1.add(q * NR) as *const _);
                let aq = a.add(q * MR512);
                for i in 0..R {
                    let x = _mm512_set1_epi32(*aq.add(i) as i32);
                    lo[i] = _mm512_dpbusd_epi32(lo[i], x, w0);
                    hi[i] = _mm512_dpbusd_epi32(hi[i], x, w1);
                }
            }
            for i in 0..R {
                _mm512_storeu_si512(sums.as_mut_ptr().add(i * 2 * NR) as *mut _, lo[i]);
                _mm512_storeu_si512(sums.as_mut_ptr().add(i * 2 * NR + NR) as *mut _, hi[i]);
            }
        }
    }

    /// The sums of the tile's first `R` rows (an edge tile runs only its real rows; the
    /// other rows of `sums` are left as they are).
    ///
    /// # Safety
    /// The CPU supports avx512f and avx512vnni; `a` readable for `s·12` words, `b` for `s·NR`;
    /// `R` ≤ 12.
    #[target_feature(enable = "avx512f,avx512vnni")]
    pub(super) unsafe fn tile_int8<const R: usize>(
        s: usize,
        a: *const u32,
        b: *const u32,
        sums: &mut [i32; MR512 * NR],
    ) {
        // SAFETY (whole body): as in `tile_bf16`.
        unsafe {
            // Intrinsics here: `vpdpbusd` reads its memory operand as the signed bytes, and the
            // broadcast words are the unsigned activations.
            let mut acc = [_mm512_setzero_si512(); R];
            for q in 0..s {
                let bq = _mm512_loadu_si512(b.add(q * NR) as *const _);
                let aq = a.add(q * MR512);
                for (i, v) in acc.iter_mut().enumerate() {
                    *v = _mm512_dpbusd_epi32(*v, _mm512_set1_epi32(*aq.add(i) as i32), bq);
                }
            }
            for (i, v) in acc.iter().enumerate() {
                _mm512_storeu_si512(sums.as_mut_ptr().add(i * NR) as *mut _, *v);
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    //! 256-bit code: the int8 tiles (`vpmaddubsw` on AVX2, `vpdpbusd` on AVX-VNNI), their
    //! epilogue, and the activations' bf16 rounding and int8 quantisation.

    use super::{MR512, NR};
    use std::arch::x86_64::*;

    /// `super::bf16_row` on 8 values at a time, in integer arithmetic: shifting
    /// `x + 0x7fff + bit16` right by 16 is round to nearest even on the bits (a carry moves
    /// into the exponent as it should), NaN keeps its top bits with the quiet bit set.
    ///
    /// # Safety
    /// The CPU supports avx2; `bits` holds at least `row.len()` values.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn bf16_row(row: &[f32], bits: &mut [u16]) {
        let k = row.len();
        let main = k - k % 8;
        assert!(bits.len() >= k);
        // SAFETY (whole body): loads stay inside row[..main], stores inside bits[..main].
        unsafe {
            let abs = _mm256_set1_epi32(0x7fff_ffff);
            let inf = _mm256_set1_epi32(0x7f80_0000);
            let (half, one, quiet) = (
                _mm256_set1_epi32(0x7fff),
                _mm256_set1_epi32(1),
                _mm256_set1_epi32(0x40),
            );
            for j in (0..main).step_by(8) {
                let x = _mm256_loadu_si256(row.as_ptr().add(j) as *const __m256i);
                let nan = _mm256_cmpgt_epi32(_mm256_and_si256(x, abs), inf);
                let top = _mm256_srli_epi32::<16>(x);
                let odd = _mm256_and_si256(top, one);
                let rounded =
                    _mm256_srli_epi32::<16>(_mm256_add_epi32(_mm256_add_epi32(x, half), odd));
                let v = _mm256_blendv_epi8(rounded, _mm256_or_si256(top, quiet), nan);
                // Eight values ≤ 0xffff to 16 bits: each 128-bit half packs its four, then
                // the two quads side by side.
                let p = _mm256_permute4x64_epi64::<0b1000>(_mm256_packus_epi32(v, v));
                _mm_storeu_si128(
                    bits.as_mut_ptr().add(j) as *mut __m128i,
                    _mm256_castsi256_si128(p),
                );
            }
        }
        super::finish_bf16_row(row, main, bits);
    }

    /// `super::quantize_row` on 8 values at a time: the same multiply, rounding (ties to even)
    /// and clamp, so the same bytes.
    ///
    /// # Safety
    /// The CPU supports avx2 and fma; `bytes` holds at least `row.len()` bytes.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn quantize_row(row: &[f32], levels: i32, bytes: &mut [u8]) -> f32 {
        let k = row.len();
        let main = k - k % 8;
        assert!(bytes.len() >= k);
        // SAFETY (whole body): loads stay inside row[..main], stores inside bytes[..main].
        unsafe {
            let abs = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fff_ffff));
            let inf = _mm256_set1_ps(f32::INFINITY);
            let (mut top, mut bad) = (_mm256_setzero_ps(), _mm256_setzero_ps());
            for j in (0..main).step_by(8) {
                let v = _mm256_and_ps(_mm256_loadu_ps(row.as_ptr().add(j)), abs);
                top = _mm256_max_ps(top, v);
                // Not below infinity: infinite or NaN.
                bad = _mm256_or_ps(bad, _mm256_cmp_ps::<_CMP_NLT_UQ>(v, inf));
            }
            let mut lanes = [0.0f32; 8];
            _mm256_storeu_ps(lanes.as_mut_ptr(), top);
            let scale =
                super::lanes_scale(&lanes, _mm256_movemask_ps(bad) == 0, &row[main..], levels);
            let finite = !scale.is_nan();
            if finite {
                let inv = _mm256_set1_ps(super::inverse(scale));
                let (lo, hi) = (
                    _mm256_set1_ps(-levels as f32),
                    _mm256_set1_ps(levels as f32),
                );
                let zero = _mm256_set1_epi32(levels + 1);
                let first_dwords = _mm256_setr_epi32(0, 4, 0, 0, 0, 0, 0, 0);
                for j in (0..main).step_by(8) {
                    let v = _mm256_mul_ps(_mm256_loadu_ps(row.as_ptr().add(j)), inv);
                    let r = _mm256_round_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(v);
                    let q = _mm256_add_epi32(
                        _mm256_cvtps_epi32(_mm256_min_ps(_mm256_max_ps(r, lo), hi)),
                        zero,
                    );
                    // i32 → u8 (values 1..=255, so no saturation), then the two 4-byte groups
                    // of the 128-bit halves side by side.
                    let w = _mm256_packus_epi16(_mm256_packs_epi32(q, q), _mm256_setzero_si256());
                    let w = _mm256_permutevar8x32_epi32(w, first_dwords);
                    _mm_storel_epi64(
                        bytes.as_mut_ptr().add(j) as *mut __m128i,
                        _mm256_castsi256_si128(w),
                    );
                }
            }
            super::finish_row(row, if finite { main } else { 0 }, scale, levels, bytes);
            scale
        }
    }

    /// An int8 tile: the exact sums of `s` quads for the first `rows` of its 12 rows (a
    /// sub-block of rows at a time, so up to a sub-block more) × [`NR`] columns.
    pub(super) type Int8Tile =
        unsafe fn(usize, usize, *const u32, *const u32, &mut [i32; MR512 * NR]);

    /// `sums` (one of this module's int8 tiles) and the epilogue in one, as
    /// `avx512::tile_int8_scaled` (the same operations, so the same bits as the scalar
    /// epilogue).
    ///
    /// # Safety
    /// The CPU supports avx2, fma and what `sums` needs; as [`tile_int8`]; `s` at most
    /// `INT8_BLOCK`; `rscale` as in `avx512::tile_int8_scaled`.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn tile_int8_scaled(
        sums_of: Int8Tile,
        s: usize,
        a: *const u32,
        b: *const u32,
        (offset, wscale, bias): (&[i32; NR], &[f32; NR], &[f32; NR]),
        rscale: &[f32],
        tile: &mut [f32; MR512 * NR],
    ) {
        let rows = rscale.len();
        let mut sums = [0i32; MR512 * NR];
        // SAFETY (whole body): loads and stores stay inside the arrays and the granted ranges.
        unsafe {
            sums_of(rows, s, a, b, &mut sums);
            for h in 0..2 {
                let offset = _mm256_loadu_si256(offset.as_ptr().add(8 * h) as *const _);
                let ws = _mm256_loadu_ps(wscale.as_ptr().add(8 * h));
                let bv = _mm256_loadu_ps(bias.as_ptr().add(8 * h));
                for (i, &sa) in rscale.iter().enumerate() {
                    let at = i * NR + 8 * h;
                    let acc = _mm256_loadu_si256(sums.as_ptr().add(at) as *const _);
                    let exact = _mm256_cvtepi32_ps(_mm256_sub_epi32(acc, offset));
                    let scale = _mm256_mul_ps(_mm256_set1_ps(sa), ws);
                    _mm256_storeu_ps(tile.as_mut_ptr().add(at), _mm256_fmadd_ps(exact, scale, bv));
                }
            }
        }
    }

    /// A 256-bit int8 tile: `$rows` rows at a time, two accumulators (16 columns) per row,
    /// `$dot(acc, activations, weights)` adding each column's four byte products.
    macro_rules! int8_tile_256 {
        ($name:ident, $features:literal, $rows:literal, $dot:ident) => {
            /// # Safety
            #[doc = concat!("The CPU supports ", $features, "; `a` readable for `s·12` words,")]
            /// `b` for `s·NR` (for `vpmaddubsw`, activation bytes at most 127).
            #[target_feature(enable = $features)]
            pub(super) unsafe fn $name(
                rows: usize,
                s: usize,
                a: *const u32,
                b: *const u32,
                sums: &mut [i32; MR512 * NR],
            ) {
                // SAFETY (whole body): loads stay inside a[..s·12] and b[..s·NR], stores
                // inside sums.
                unsafe {
                    // Sub-blocks holding real rows only (`rows` ≤ 12, so every sub-block
                    // read lies inside the tile's 12 words per quad).
                    for r0 in (0..rows.min(MR512)).step_by($rows) {
                        let mut acc = [[_mm256_setzero_si256(); 2]; $rows];
                        for q in 0..s {
                            let bq = b.add(q * NR) as *const __m256i;
                            let (b0, b1) = (_mm256_loadu_si256(bq), _mm256_loadu_si256(bq.add(1)));
                            let aq = a.add(q * MR512 + r0);
                            for (i, v) in acc.iter_mut().enumerate() {
                                let ai = _mm256_set1_epi32(*aq.add(i) as i32);
                                v[0] = $dot(v[0], ai, b0);
                                v[1] = $dot(v[1], ai, b1);
                            }
                        }
                        for (i, v) in acc.iter().enumerate() {
                            let out = sums.as_mut_ptr().add((r0 + i) * NR) as *mut __m256i;
                            _mm256_storeu_si256(out, v[0]);
                            _mm256_storeu_si256(out.add(1), v[1]);
                        }
                    }
                }
            }
        };
    }

    /// `vpmaddubsw` adds each column's two unsigned × signed byte products into a 16-bit lane
    /// (activations in 63 levels: at most 2·127·127, no saturation), `vpmaddwd` with ones adds
    /// the two halves of the quad into 32 bits.
    #[inline(always)]
    unsafe fn maddubs_dot(acc: __m256i, a: __m256i, b: __m256i) -> __m256i {
        // SAFETY: called only inside `tile_int8`, whose CPU has avx2.
        unsafe {
            let pairs = _mm256_maddubs_epi16(a, b);
            _mm256_add_epi32(acc, _mm256_madd_epi16(pairs, _mm256_set1_epi16(1)))
        }
    }

    // Four rows: 8 accumulators, two panel vectors, the ones and the temporaries fit the 16
    // registers.
    int8_tile_256!(tile_int8, "avx2", 4, maddubs_dot);
    // `vpdpbusd` adds each column's four unsigned × signed byte products into its 32-bit lane,
    // so activations keep 127 levels and the sums are `avx512::tile_int8`'s. Six rows: 12
    // accumulators, two panel vectors and the broadcast word fill 15 of the 16 registers.
    int8_tile_256!(
        tile_int8_avx_vnni,
        "avx2,avxvnni",
        6,
        _mm256_dpbusd_avx_epi32
    );
    // The same tile encoded for AVX512_VNNI + AVX512VL, so that its code runs (in tests) on
    // CPUs without AVX-VNNI.
    int8_tile_256!(
        tile_int8_avx_vnni_twin,
        "avx2,avx512vnni,avx512vl",
        6,
        _mm256_dpbusd_epi32
    );

    /// The 256-bit `vpdpbusd` tile this CPU runs: the VEX encoding where it has AVX-VNNI, else
    /// the EVEX twin (reached only by tests that ask for the `AvxVnni` path).
    pub(super) fn vnni_tile() -> Int8Tile {
        if super::has_avx_vnni() {
            tile_int8_avx_vnni
        } else {
            assert!(
                super::has_avx_vnni_twin(),
                "no 256-bit vpdpbusd on this CPU"
            );
            tile_int8_avx_vnni_twin
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::linear_packed_on;
    use super::*;
    use crate::kernels::testutil::{in_pool, same_bits, Rng};
    use std::collections::BTreeSet;

    /// Shapes with odd `k` (a half-filled pair or quad), edge tiles in both directions, one
    /// tile and several M blocks, and a `k` long enough for a few blocks of f32 rounding.
    const SHAPES: &[(usize, usize, usize)] = &[
        (1, 1, 1),
        (1, 3, 5),
        (3, 1, 17),
        (5, 7, 1),
        (2, 0, 3),
        (12, 16, 16),
        (13, 257, 16),
        (7, 301, 33),
        (100, 520, 47),
        (197, 66, 70),
        (40, 2050, 20),
        (30, 100, 96),
    ];

    fn data(m: usize, k: usize, n: usize, seed: u64) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let mut rng = Rng::new(seed);
        // Activations with a spread of magnitudes (as after a layer norm and a GELU).
        let x = (0..m * k)
            .map(|i| rng.uniform() * if i % 7 == 0 { 4.0 } else { 1.0 })
            .collect();
        (x, rng.vec(n * k), rng.vec(n))
    }

    #[allow(clippy::too_many_arguments)]
    fn run(
        isa: Isa,
        ty: WeightType,
        x: &[f32],
        w: &[f32],
        b: &[f32],
        m: usize,
        k: usize,
        n: usize,
        act: Activation,
    ) -> Vec<f32> {
        let packed = PackedWeights::pack(w, n, k, ty);
        let mut y = vec![f32::NAN; m * n + 3];
        linear_packed_on(isa, x, &packed, Some(b), act, &mut y, m);
        assert!(
            y[m * n..].iter().all(|v| v.is_nan()),
            "wrote past the output"
        );
        y.truncate(m * n);
        y
    }

    /// The AVX512_BF16 tile and the portable reproduction give the same bits (and so every
    /// machine gives the same results); any thread count too.
    #[test]
    fn bf16_compute_is_the_same_bits_on_every_kernel_and_thread_count() {
        if !has_bf16_dot() {
            eprintln!("AVX512_BF16 not supported by this CPU: only the portable bf16 kernel ran");
        }
        for (s, &(m, k, n)) in SHAPES.iter().enumerate() {
            let (x, w, b) = data(m, k, n, s as u64);
            let want = run(
                Isa::Portable,
                WeightType::Bf16Compute,
                &x,
                &w,
                &b,
                m,
                k,
                n,
                Activation::None,
            );
            for isa in Isa::ALL.into_iter().filter(|i| i.supported()) {
                for threads in [1, 2, 3] {
                    let got = in_pool(threads, || {
                        run(
                            isa,
                            WeightType::Bf16Compute,
                            &x,
                            &w,
                            &b,
                            m,
                            k,
                            n,
                            Activation::None,
                        )
                    });
                    assert!(
                        same_bits(&got, &want),
                        "{m}x{k}x{n} {isa:?} {threads} threads"
                    );
                }
            }
        }
    }

    /// Against an f64 sum of the bf16-rounded products: the only difference is the f32
    /// accumulation (a relative error of a few ulps of `Σ|x||w|` per step).
    #[test]
    fn bf16_compute_sums_the_rounded_products() {
        let r = |v: f32| bf16::from_f32(v).to_f32() as f64;
        for (s, &(m, k, n)) in SHAPES.iter().enumerate() {
            let (x, w, b) = data(m, k, n, 100 + s as u64);
            let got = run(
                Isa::ALL[0],
                WeightType::Bf16Compute,
                &x,
                &w,
                &b,
                m,
                k,
                n,
                Activation::None,
            );
            let got_portable = run(
                Isa::Portable,
                WeightType::Bf16Compute,
                &x,
                &w,
                &b,
                m,
                k,
                n,
                Activation::None,
            );
            for i in 0..m {
                for j in 0..n {
                    let (mut sum, mut mag) = (b[j] as f64, (b[j] as f64).abs());
                    for p in 0..k {
                        let t = r(x[i * k + p]) * r(w[j * k + p]);
                        sum += t;
                        mag += t.abs();
                    }
                    let tol = (k as f64 + 1.0) * f32::EPSILON as f64 * mag + 1e-30;
                    for g in [&got, &got_portable] {
                        let e = (g[i * n + j] as f64 - sum).abs();
                        assert!(
                            e <= tol,
                            "{m}x{k}x{n} [{i},{j}]: {} vs {sum} (tol {tol})",
                            g[i * n + j]
                        );
                    }
                }
            }
            // And it is not the f32 result: bf16 rounding is there (the test can fail).
            if k >= 16 {
                let f32y = run(
                    Isa::Portable,
                    WeightType::F32,
                    &x,
                    &w,
                    &b,
                    m,
                    k,
                    n,
                    Activation::None,
                );
                assert!(!same_bits(&f32y, &got));
            }
        }
    }

    /// Int8 on every tile the CPU runs (VNNI, the 256-bit `vpdpbusd` in either encoding, AVX2,
    /// portable; the others printed as skipped) and any thread count: the result is the exact
    /// integer dot product of the values quantised by hand (weights in 127 levels, activations
    /// in the tile's: 127, or 63 on AVX2), scaled, bit for bit; the 127-level tiles and
    /// portable are the same bits; every result is within the quantisation error of f32.
    #[test]
    fn int8_is_exact_on_the_quantised_values_on_every_kernel() {
        let (mut ran, mut skipped) = (BTreeSet::new(), BTreeSet::new());
        for (s, &(m, k, n)) in SHAPES.iter().enumerate() {
            let (x, w, b) = data(m, k, n, 200 + s as u64);
            // Int8 on the tile the kernel (or `Int8Path::forced`) picks.
            let int8 = || {
                run(
                    Isa::Portable,
                    WeightType::Int8,
                    &x,
                    &w,
                    &b,
                    m,
                    k,
                    n,
                    Activation::None,
                )
            };
            let portable = int8();
            let f32y = run(
                Isa::Portable,
                WeightType::F32,
                &x,
                &w,
                &b,
                m,
                k,
                n,
                Activation::None,
            );
            // Independent: quantise by hand (symmetric, max/levels, round half to even).
            let q = |v: &[f32], levels: f32| {
                let s = v.iter().fold(0.0f32, |a, x| a.max(x.abs())) / levels;
                let inv = if s > 0.0 { 1.0 / s } else { 0.0 };
                (
                    s,
                    v.iter()
                        .map(|&x| (x * inv).round_ties_even().clamp(-levels, levels) as i64)
                        .collect::<Vec<_>>(),
                )
            };
            for path in Int8Path::ALL {
                if !path.runs_here() {
                    skipped.insert(format!("{path:?}"));
                    continue;
                }
                ran.insert(match path {
                    Int8Path::AvxVnni if !has_avx_vnni() => "AvxVnni (EVEX twin)".to_string(),
                    _ => format!("{path:?}"),
                });
                let levels = path.levels() as f32;
                let on_path = || path.forced(int8);
                let got = on_path();
                for threads in [2, 3] {
                    let again = in_pool(threads, on_path);
                    assert!(
                        same_bits(&again, &got),
                        "{m}x{k}x{n} {path:?} {threads} threads"
                    );
                }
                if path != Int8Path::Avx2 {
                    assert!(same_bits(&got, &portable), "{m}x{k}x{n} {path:?}");
                }
                for i in 0..m {
                    let (sa, qa) = q(&x[i * k..(i + 1) * k], levels);
                    for j in 0..n {
                        let (sw, qw) = q(&w[j * k..(j + 1) * k], 127.0);
                        let dot: i64 = qa.iter().zip(&qw).map(|(a, b)| a * b).sum();
                        let expect = (dot as f32).mul_add(sa * sw, b[j]);
                        assert_eq!(
                            got[i * n + j].to_bits(),
                            expect.to_bits(),
                            "{m}x{k}x{n} {path:?} [{i},{j}]"
                        );
                        // Each value is off by at most half a step of its scale.
                        let bound: f64 = (0..k)
                            .map(|p| {
                                (x[i * k + p].abs() as f64 * sw as f64
                                    + w[j * k + p].abs() as f64 * sa as f64)
                                    / 2.0
                                    + sa as f64 * sw as f64 / 4.0
                            })
                            .sum::<f64>()
                            + 1e-5;
                        let e = (got[i * n + j] as f64 - f32y[i * n + j] as f64).abs();
                        assert!(e <= bound, "{m}x{k}x{n} {path:?} [{i},{j}]: {e} > {bound}");
                    }
                }
            }
        }
        eprintln!("int8 tiles run: {ran:?}; not supported by this CPU, skipped: {skipped:?}");
        // Every kernel this CPU runs picks a tile that runs here.
        for isa in Isa::ALL.into_iter().filter(|i| i.supported()) {
            assert!(Int8Path::for_kernel(isa).runs_here(), "{isa:?}");
        }
    }

    /// The AVX2 activation quantiser gives the portable one's bytes and scale: every length
    /// from 0 to 40 (vector body and tail), ties (values exactly half way after scaling), both
    /// level counts, zero rows, and rows with a NaN or an infinity in the body or the tail.
    #[test]
    fn quantize_row_is_the_same_on_avx2_avx512_and_portable() {
        if !Isa::Avx2.supported() {
            eprintln!("AVX2 not supported by this CPU: only the portable quantiser ran");
            return;
        }
        let mut rng = Rng::new(5);
        for k in 0..=40usize {
            for levels in [127, 63] {
                for case in 0..5 {
                    let mut row: Vec<f32> = (0..k).map(|_| rng.uniform() * 3.0).collect();
                    match case {
                        // max 2·levels: the values 2j + 1 halve to exact ties j + 0.5.
                        1 if k > 0 => {
                            for (j, v) in row.iter_mut().enumerate() {
                                *v = ((2 * j + 1) % (2 * levels as usize)) as f32;
                            }
                            row[0] = 2.0 * levels as f32;
                        }
                        2 => row.iter_mut().for_each(|v| *v = 0.0),
                        3 if k > 0 => row[k / 2] = f32::NAN,
                        4 if k > 0 => row[k - 1] = f32::NEG_INFINITY,
                        _ => {}
                    }
                    let n = 4 * k.div_ceil(4);
                    let (mut want, mut got) = (vec![0u8; n], vec![0u8; n]);
                    let scale = scale_of(&row, levels);
                    finish_row(&row, 0, scale, levels, &mut want);
                    // SAFETY: AVX2 and FMA checked above; `got` holds n >= k bytes.
                    let got_scale = unsafe { avx2::quantize_row(&row, levels, &mut got) };
                    assert_eq!(got_scale.to_bits(), scale.to_bits(), "k {k} case {case}");
                    assert_eq!(got, want, "k {k} levels {levels} case {case}");
                    if Isa::Avx512.supported() {
                        let mut got = vec![0u8; n];
                        // SAFETY: AVX-512F checked just above; `got` holds n >= k bytes.
                        let got_scale = unsafe { avx512::quantize_row(&row, levels, &mut got) };
                        assert_eq!(got_scale.to_bits(), scale.to_bits(), "avx512 k {k} {case}");
                        assert_eq!(got, want, "avx512 k {k} levels {levels} case {case}");
                    }
                    if case == 1 && k > 2 {
                        // 1.5 → 2 and 2.5 → 2: ties went to even.
                        assert_eq!(want[1] as i32 - levels - 1, 2, "k {k}");
                        assert_eq!(want[2] as i32 - levels - 1, 2, "k {k}");
                    }
                }
            }
        }
    }

    /// The AVX2 bf16 rounding gives `half`'s bits: every length 0 to 40, ties (both
    /// directions), carries into the exponent and to infinity, subnormals, infinities, and
    /// NaNs of both signs with and without the quiet bit, plus random bit patterns.
    #[test]
    fn bf16_row_is_the_same_on_avx2_and_half() {
        if !Isa::Avx2.supported() {
            eprintln!("AVX2 not supported by this CPU: only the portable bf16 rounding ran");
            return;
        }
        let special: [u32; 14] = [
            0x3f80_8000, // tie, even below: stays
            0x3f81_8000, // tie, odd below: rounds up
            0x3f80_8001,
            0x3f80_7fff,
            0x7f7f_ffff, // rounds up to infinity
            0xff7f_8000,
            0x0000_0001, // subnormal
            0x807f_ffff,
            0x7f80_0000,
            0xff80_0000,
            0x7f80_0001, // signalling NaN: quieted
            0xffc0_0000,
            0x7fff_ffff,
            0x0000_0000,
        ];
        let mut rng = Rng::new(17);
        for k in 0..=40usize {
            for round in 0..20 {
                let row: Vec<f32> = (0..k)
                    .map(|j| {
                        let r = (rng.uniform() * 4.0e9) as u32 ^ (j as u32).wrapping_mul(0x9e37);
                        f32::from_bits(if round % 2 == 0 {
                            special[(j + round) % 14]
                        } else {
                            r
                        })
                    })
                    .collect();
                let n = 2 * k.div_ceil(2);
                let (mut want, mut got) = (vec![0u16; n], vec![7u16; n]);
                finish_bf16_row(&row, 0, &mut want);
                // SAFETY: AVX2 checked above; `got` holds n >= k values.
                unsafe { avx2::bf16_row(&row, &mut got) };
                assert_eq!(got, want, "k {k} round {round}");
            }
        }
        // The two ties went to even, the carry reached infinity.
        let b = |x: u32| bf16::from_f32(f32::from_bits(x)).to_bits();
        assert_eq!(
            (b(0x3f80_8000), b(0x3f81_8000), b(0x7f7f_ffff)),
            (0x3f80, 0x3f82, 0x7f80)
        );
    }

    /// Non-finite activations give non-finite outputs (the session's check then reports them)
    /// rather than quantised garbage.
    #[test]
    fn int8_keeps_non_finite_inputs_visible() {
        let (m, k, n) = (3, 20, 5);
        let (mut x, w, b) = data(m, k, n, 9);
        x[k + 4] = f32::NAN;
        x[2 * k] = f32::INFINITY;
        let y = run(
            Isa::ALL[0],
            WeightType::Int8,
            &x,
            &w,
            &b,
            m,
            k,
            n,
            Activation::None,
        );
        assert!(y[..n].iter().all(|v| v.is_finite()));
        assert!(y[n..].iter().all(|v| v.is_nan()));
    }

    /// Activations are applied after the epilogue; unpack gives the values the kernels use.
    #[test]
    fn activations_and_unpack() {
        let (m, k, n) = (13, 37, 21);
        let (x, w, b) = data(m, k, n, 11);
        for ty in [WeightType::Bf16Compute, WeightType::Int8] {
            let plain = run(Isa::Portable, ty, &x, &w, &b, m, k, n, Activation::None);
            let relu = run(Isa::Portable, ty, &x, &w, &b, m, k, n, Activation::Relu);
            let want: Vec<f32> = plain.iter().map(|&v| v.max(0.0)).collect();
            assert!(same_bits(&relu, &want), "{ty:?}");
            let p = PackedWeights::pack(&w, n, k, ty);
            let u = p.unpack();
            for (i, (&a, &b)) in u.iter().zip(&w).enumerate() {
                let tol = match ty {
                    WeightType::Bf16Compute => b.abs() / 128.0,
                    _ => p.scales[i / k] / 2.0 + 1e-7,
                };
                assert!((a - b).abs() <= tol, "{ty:?} {i}: {a} vs {b}");
            }
            assert!(p.bytes() < n.div_ceil(NR) * NR * k * ty.size() + 64 * n + 8 * n + 64 * 16);
        }
    }
}
