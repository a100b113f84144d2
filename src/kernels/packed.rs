//! Linear layers on weights packed once at load into the micro-kernel's panel layout, in f32,
//! f16 or bf16, with the bias and an activation applied as each output tile is finished.
//!
//! Layout: the weight `W [n, k]` (PyTorch `Linear.weight`) is cut into panels of [`NR`] output
//! columns; panel `j` stores `k` rows of `NR` values, row `p` holding `W[j·NR + c, p]` for
//! `c < NR` (zeros past `n`). The micro-kernel walks one panel row per multiply step, so the
//! weights are never repacked per call. Activations are read in place (rows of `x`).
//!
//! Every output element is one chain: start at the bias (or 0), then one fused multiply-add
//! per `p = 0..k` in order (the portable kernel: multiply, then add), then the activation. Tile
//! position, the K blocking and the thread split never change that chain, so results are
//! bit-identical for any thread count; half-precision weights are widened exactly, so an f16
//! run equals an f32 run on weights pre-rounded to f16.
//!
//! This module does not hold activations-by-activations products (attention scores): those
//! stay on [`super::gemm`].

use std::sync::OnceLock;

use half::{bf16, f16};
use rayon::prelude::*;

use super::activation::{gelu_erf, relu};
use super::gemm::SharedMut;

mod lowp;

/// Rows of a micro-tile of the AVX2 and portable kernels.
const MR: usize = 6;
/// Rows of a micro-tile of the AVX-512 kernel: 12 accumulators of 16 lanes.
const MR512: usize = 12;
/// Columns of a micro-tile and of a weight panel: two 8-lane vectors.
const NR: usize = 16;
/// Multiply steps per K block: the panel slice (`KC × NR` weights) stays in L1.
const KC: usize = 256;
/// Most rows per M block (a multiple of [`MR`] and [`MR512`]): the `MC × KC` block of
/// activations stays in L2 while every panel of the task streams past it. A task's rows are
/// cut into equal blocks (see [`m_block`]).
const MC: usize = 120;
/// Below this many multiply-adds a fork/join costs more than a second core saves.
const PAR_MIN_MACS: usize = 1 << 20;

/// How weights are held in memory and read by the kernels.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum WeightType {
    /// Single precision, as trained.
    #[default]
    F32,
    /// IEEE half precision (rounded to nearest even when narrowed from f32).
    F16,
    /// bfloat16 (rounded to nearest even when narrowed from f32).
    Bf16,
    /// bf16 weights and bf16 products: activations rounded to bf16 per call, pairs multiplied
    /// and accumulated in f32 (`vdpbf16ps`; see `packed::lowp`). Needs AVX512_BF16.
    Bf16Compute,
    /// 8-bit weights (per-column scales) and 8-bit activations (per-row scales per call),
    /// multiplied and accumulated in 32-bit integers (`vpdpbusd` with AVX512_VNNI, or
    /// `vpmaddubsw` on AVX2 with activations in 63 levels; see `packed::lowp`). Needs AVX2.
    Int8,
}

impl WeightType {
    /// Every type, in the order `flame info` and the benchmarks list them.
    pub const ALL: [WeightType; 5] = [
        WeightType::F32,
        WeightType::F16,
        WeightType::Bf16,
        WeightType::Bf16Compute,
        WeightType::Int8,
    ];

    /// The name [`FromStr`](std::str::FromStr) reads back: `f32`, `f16`, `bf16`,
    /// `bf16-compute` or `int8`.
    pub fn name(self) -> &'static str {
        match self {
            WeightType::F32 => "f32",
            WeightType::F16 => "f16",
            WeightType::Bf16 => "bf16",
            WeightType::Bf16Compute => "bf16-compute",
            WeightType::Int8 => "int8",
        }
    }

    /// Bytes per stored weight (scales aside).
    pub fn size(self) -> usize {
        match self {
            WeightType::F32 => 4,
            WeightType::F16 | WeightType::Bf16 | WeightType::Bf16Compute => 2,
            WeightType::Int8 => 1,
        }
    }

    /// Whether the products themselves run in reduced precision (not only the storage).
    pub fn reduced_compute(self) -> bool {
        matches!(self, WeightType::Bf16Compute | WeightType::Int8)
    }

    /// Whether this CPU runs the type's own instructions: always for the storage types; for
    /// `bf16-compute` AVX512_BF16; for `int8` AVX512_VNNI or AVX2 (models refuse these types
    /// elsewhere rather than run the slow portable reproduction).
    pub fn native_on_this_cpu(self) -> bool {
        match self {
            WeightType::Bf16Compute => lowp::has_bf16_dot() && detected_isa() == Isa::Avx512,
            WeightType::Int8 => {
                lowp::Int8Path::for_kernel(detected_isa()) != lowp::Int8Path::Portable
            }
            _ => true,
        }
    }

    /// The instructions the type's products run on with the kernel in use (`flame info`), or
    /// what it would need.
    pub fn compute_path(self) -> &'static str {
        match self {
            WeightType::Bf16Compute if self.native_on_this_cpu() => "vdpbf16ps, AVX512_BF16",
            WeightType::Bf16Compute => "needs AVX512_BF16 and the avx512 kernel",
            WeightType::Int8 if self.native_on_this_cpu() => {
                lowp::Int8Path::for_kernel(detected_isa()).name()
            }
            WeightType::Int8 => "needs AVX2 or AVX512_VNNI and their kernels",
            _ => "f32 FMA",
        }
    }
}

impl std::str::FromStr for WeightType {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "f32" | "float32" => Ok(WeightType::F32),
            "f16" | "float16" | "half" => Ok(WeightType::F16),
            "bf16" | "bfloat16" => Ok(WeightType::Bf16),
            "bf16-compute" | "bf16_compute" => Ok(WeightType::Bf16Compute),
            "int8" => Ok(WeightType::Int8),
            _ => Err(format!(
                "weight type `{s}`: expected f32, f16, bf16, bf16-compute or int8"
            )),
        }
    }
}

/// What is applied to each output after the bias.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Activation {
    /// The outputs as computed (`x·Wᵀ + b`).
    #[default]
    None,
    /// `max(y, 0)`, the same function as [`super::relu`].
    Relu,
    /// Exact (erf) GELU, the same function as [`super::gelu_erf`].
    Gelu,
}

impl Activation {
    /// Applies the activation to finished outputs in place.
    fn apply(self, v: &mut [f32]) {
        match self {
            Activation::None => {}
            Activation::Relu => relu(v),
            Activation::Gelu => gelu_erf(v),
        }
    }
}

/// Which micro-kernel runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Isa {
    /// x86-64 with AVX-512F (and AVX2, FMA, F16C): a 12×16 tile, one 16-lane vector per row.
    Avx512,
    /// x86-64 with AVX2, FMA and F16C: a 6×16 tile, two 8-lane vectors per row.
    Avx2,
    /// Plain Rust the compiler may vectorise; any target.
    Portable,
}

impl Isa {
    /// Every kernel, best first.
    pub(crate) const ALL: [Isa; 3] = [Isa::Avx512, Isa::Avx2, Isa::Portable];

    pub(crate) fn name(self) -> &'static str {
        match self {
            Isa::Avx512 => "avx512",
            Isa::Avx2 => "avx2",
            Isa::Portable => "portable",
        }
    }

    /// Whether this CPU runs the kernel.
    pub(crate) fn supported(self) -> bool {
        #[cfg(target_arch = "x86_64")]
        let avx2 = is_x86_feature_detected!("avx2")
            && is_x86_feature_detected!("fma")
            && is_x86_feature_detected!("f16c");
        #[cfg(not(target_arch = "x86_64"))]
        let avx2 = false;
        match self {
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => avx2 && is_x86_feature_detected!("avx512f"),
            #[cfg(not(target_arch = "x86_64"))]
            Isa::Avx512 => false,
            Isa::Avx2 => avx2,
            Isa::Portable => true,
        }
    }

    /// Whether the AVX2 + FMA code of the other kernels (attention, activations) may run.
    pub(crate) fn has_avx2(self) -> bool {
        matches!(self, Isa::Avx512 | Isa::Avx2)
    }

    /// Rows of this kernel's micro-tile.
    fn mr(self) -> usize {
        match self {
            Isa::Avx512 => MR512,
            _ => MR,
        }
    }
}

/// The kernel in use: the best this CPU runs, or the one `FLAME_KERNEL` names (`avx512`,
/// `avx2`, `portable`; `avx512-12x16` and `avx512-12x32` also pick the f32 tile, see
/// [`wide_tiles`]) when the CPU runs it — for comparing paths on one machine. Detected once.
pub(crate) fn detected_isa() -> Isa {
    static ISA: OnceLock<Isa> = OnceLock::new();
    *ISA.get_or_init(|| {
        let best = Isa::ALL
            .into_iter()
            .find(|i| i.supported())
            .unwrap_or(Isa::Portable);
        match std::env::var("FLAME_KERNEL") {
            Ok(name) => Isa::ALL
                .into_iter()
                .find(|i| {
                    let name = name.trim().to_ascii_lowercase();
                    i.name() == name.split('-').next().unwrap_or_default() && i.supported()
                })
                .unwrap_or(best),
            Err(_) => best,
        }
    })
}

/// The name of the linear-layer kernel in use (`avx512`, `avx2` or `portable`), for `flame
/// info` and the benchmarks.
pub fn kernel_name() -> &'static str {
    detected_isa().name()
}

/// Whether the AVX-512 kernel runs f32 weights on 12×32 tiles (two panels per tile) rather than
/// 12×16. On a core with two full-width 512-bit FMA units (Intel's server cores) the 12×16 tile
/// is limited by loads: 13 per 12 multiply-adds (one weight vector, 12 broadcasts) while two
/// loads and two multiply-adds issue per cycle. The 12×32 tile loads 14 per 24. On a core that
/// splits 512-bit operations (AMD Zen 4: one 512-bit multiply-add per cycle) 12×16 already runs
/// at the multiply-add limit and its panel slice is half the L1 footprint, so it stays. Chosen
/// by timing both vector widths' multiply-adds once (about 0.5 ms): the 12×32 tile when a
/// 512-bit one issues as fast as a 256-bit one. `FLAME_KERNEL=avx512-12x16` or `avx512-12x32`
/// picks one. Both run every output as the same chain, so they give the same bits.
pub(crate) fn wide_tiles() -> bool {
    static WIDE: OnceLock<bool> = OnceLock::new();
    *WIDE.get_or_init(|| {
        if detected_isa() != Isa::Avx512 {
            return false;
        }
        match std::env::var("FLAME_KERNEL").map(|v| v.trim().to_ascii_lowercase()) {
            Ok(v) if v == "avx512-12x16" => false,
            Ok(v) if v == "avx512-12x32" => true,
            _ => full_width_fma512(),
        }
    })
}

/// Whether 512-bit multiply-adds issue as fast as 256-bit ones (two full-width units): the
/// best of 5 alternating timings of 12 independent chains each.
fn full_width_fma512() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        use std::time::Instant;
        const ITERS: usize = 8192;
        let time = |f: unsafe fn(usize) -> f32| {
            let t = Instant::now();
            // SAFETY: called only on the avx512 kernel (avx512f, avx2 and fma detected).
            std::hint::black_box(unsafe { f(ITERS) });
            t.elapsed().as_secs_f64()
        };
        // Warm up: some cores raise the 512-bit units' power only after their first use.
        time(avx512::chains512);
        let (mut t256, mut t512) = (f64::MAX, f64::MAX);
        for _ in 0..5 {
            t256 = t256.min(time(avx512::chains256));
            t512 = t512.min(time(avx512::chains512));
        }
        // Equal instruction counts: about 1 with two full-width units, about 2 when 512-bit
        // operations are split or share one unit.
        t512 < 1.5 * t256
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// The f32 micro-tile of the kernel in use, for `flame info` and the benchmarks.
pub fn f32_tile() -> &'static str {
    match detected_isa() {
        Isa::Avx512 if wide_tiles() => "12x32",
        Isa::Avx512 => "12x16",
        Isa::Avx2 | Isa::Portable => "6x16",
    }
}

/// One 64-byte line: the allocation unit of the panels, so every panel row starts aligned.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct Line([u8; 64]);

/// A panel slice widened to f32, aligned like the packed panels: each panel row is one
/// 64-byte line, so the kernel's two 32-byte loads per row never straddle lines.
#[repr(C, align(64))]
struct Widened([f32; KC * NR]);

/// Where a micro-tile's activation rows are read.
#[derive(Clone, Copy)]
enum TileRows {
    /// One pointer per row (the AVX2 and portable kernels, [`MR`] rows).
    Pointers([*const f32; MR]),
    /// A tile of a [`RowBlock`] (the AVX-512 kernel).
    Packed(*const f32),
}

thread_local! {
    /// Each thread's row block for the AVX-512 kernel, allocated on its first call.
    static ROW_BLOCK: std::cell::RefCell<RowBlock> = std::cell::RefCell::new(RowBlock::new());
}

/// An `MC × kc` block of activation rows packed for the AVX-512 kernel: tile `t` (rows
/// `12t..12t + 12` of the block) holds, for each step `p`, its 12 values `x[row, kb + p]`
/// adjacent (zeros past the block's last row).
struct RowBlock {
    lines: Vec<Line>,
    kc: usize,
}

impl RowBlock {
    fn new() -> RowBlock {
        RowBlock {
            lines: Vec::new(),
            kc: 0,
        }
    }

    /// Packs rows `r0..r1` (at most [`MC`]), columns `kb..kb + kc` (at most [`KC`]) of `x`
    /// (row stride `k`).
    fn fill(&mut self, x: &[f32], k: usize, r0: usize, r1: usize, kb: usize, kc: usize) {
        assert!(r1 - r0 <= MC && kc <= KC && kb + kc <= k && r1 * k <= x.len());
        if self.lines.is_empty() {
            self.lines = vec![Line([0; 64]); MC * KC * 4 / 64];
        }
        self.kc = kc;
        // SAFETY: `lines` holds MC·KC f32s, 64-byte aligned; every bit pattern is an f32.
        let dst =
            unsafe { std::slice::from_raw_parts_mut(self.lines.as_mut_ptr() as *mut f32, MC * KC) };
        for (t, tile) in dst[..(r1 - r0).div_ceil(MR512) * MR512 * kc]
            .chunks_exact_mut(MR512 * kc)
            .enumerate()
        {
            // Four rows at a time: a 4 × 4 transpose per four steps where all four are real.
            for i0 in (0..MR512).step_by(4) {
                let r = r0 + t * MR512 + i0;
                if r + 4 <= r1 {
                    let rows: [&[f32]; 4] =
                        std::array::from_fn(|i| &x[(r + i) * k + kb..(r + i) * k + kb + kc]);
                    transpose_rows4(rows, &mut tile[i0..]);
                    continue;
                }
                for i in i0..i0 + 4 {
                    let r = r0 + t * MR512 + i;
                    let row = (r < r1).then(|| &x[r * k + kb..r * k + kb + kc]);
                    for p in 0..kc {
                        tile[p * MR512 + i] = row.map_or(0.0, |row| row[p]);
                    }
                }
            }
        }
    }

    /// The tile holding block row `offset` (a multiple of [`MR512`]).
    fn tile(&self, offset: usize) -> *const f32 {
        debug_assert!(offset.is_multiple_of(MR512) && offset < MC);
        // SAFETY: inside the MC·KC block (offset < MC, kc ≤ KC).
        unsafe { (self.lines.as_ptr() as *const f32).add(offset * self.kc) }
    }
}

/// Writes four equal-length rows interleaved into `tile` at a stride of [`MR512`]:
/// `tile[p·MR512 + i] = rows[i][p]`, four steps per 4 × 4 transpose (SSE, which every x86-64
/// CPU has; a scalar loop elsewhere). `tile` starts at the first of the four columns.
/// Any 4-byte `T` is moved as raw bits (int8 and bf16 activation words go through it too).
pub(super) fn transpose_rows4<T: Copy>(rows: [&[T]; 4], tile: &mut [T]) {
    const { assert!(std::mem::size_of::<T>() == 4) };
    let kc = rows[0].len();
    assert!(rows.iter().all(|r| r.len() == kc));
    assert!(kc == 0 || tile.len() >= (kc - 1) * MR512 + 4);
    let mut p = 0;
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::*;
        while p + 4 <= kc {
            // SAFETY: p + 4 ≤ kc, the rows' length; the four stores end at
            // (p + 3)·MR512 + 4 ≤ (kc - 1)·MR512 + 4 ≤ tile.len(). Unaligned forms throughout.
            unsafe {
                let [a, b, c, d] = rows.map(|r| _mm_loadu_ps(r.as_ptr().add(p) as *const f32));
                let (ab_lo, cd_lo) = (_mm_unpacklo_ps(a, b), _mm_unpacklo_ps(c, d));
                let (ab_hi, cd_hi) = (_mm_unpackhi_ps(a, b), _mm_unpackhi_ps(c, d));
                let out = tile.as_mut_ptr().add(p * MR512) as *mut f32;
                _mm_storeu_ps(out, _mm_movelh_ps(ab_lo, cd_lo));
                _mm_storeu_ps(out.add(MR512), _mm_movehl_ps(cd_lo, ab_lo));
                _mm_storeu_ps(out.add(2 * MR512), _mm_movelh_ps(ab_hi, cd_hi));
                _mm_storeu_ps(out.add(3 * MR512), _mm_movehl_ps(cd_hi, ab_hi));
            }
            p += 4;
        }
    }
    for p in p..kc {
        for (i, row) in rows.iter().enumerate() {
            tile[p * MR512 + i] = row[p];
        }
    }
}

/// Writes `w` (`[n, k]`) into `dst`'s [`NR`]-column panels (panel `j`, row `p`, column `c` at
/// `(j·k + p)·NR + c`), converted by `conv`; the columns past `n` keep their zeros. A panel is
/// a transpose: it is walked in blocks of [`PACK_ROWS`] rows so both the source rows and the
/// destination lines stay in L1.
fn pack_panels<T: Copy>(w: &[f32], n: usize, k: usize, dst: &mut [T], conv: impl Fn(f32) -> T) {
    if k == 0 {
        return;
    }
    for (j, panel) in dst.chunks_exact_mut(k * NR).enumerate() {
        let cols = NR.min(n - j * NR);
        let src = &w[j * NR * k..(j * NR + cols) * k];
        for p0 in (0..k).step_by(PACK_ROWS) {
            let p1 = (p0 + PACK_ROWS).min(k);
            for (c, row) in src.chunks_exact(k).enumerate() {
                for (p, &v) in row[p0..p1].iter().enumerate() {
                    panel[(p0 + p) * NR + c] = conv(v);
                }
            }
        }
    }
}

/// Rows of a panel packed per block by [`pack_panels`] (64 lines of 64 bytes, 4 KiB of f32).
const PACK_ROWS: usize = 64;

/// A `Linear` weight `[n, k]` packed into `NR`-column panels.
pub struct PackedWeights {
    k: usize,
    n: usize,
    ty: WeightType,
    lines: Vec<Line>,
    /// Int8: each column's weight scale and the sum of its quantised weights.
    scales: Vec<f32>,
    colsum: Vec<i32>,
}

impl PackedWeights {
    /// Packs `w` (`[n, k]`, row-major, PyTorch `Linear.weight`), narrowing to `ty`.
    pub fn pack(w: &[f32], n: usize, k: usize, ty: WeightType) -> PackedWeights {
        assert_eq!(w.len(), n * k, "pack: weight is not {n}x{k}");
        if ty.reduced_compute() {
            let mut packed = PackedWeights {
                k,
                n,
                ty,
                ..PackedWeights::empty()
            };
            lowp::pack(&mut packed, w);
            return packed;
        }
        let panels = n.div_ceil(NR);
        let bytes = panels * k * NR * ty.size();
        let mut packed = PackedWeights {
            k,
            n,
            ty,
            lines: vec![Line([0; 64]); bytes.div_ceil(64)],
            scales: Vec::new(),
            colsum: Vec::new(),
        };
        match ty {
            WeightType::F32 => pack_panels(w, n, k, packed.f32_mut(), |v| v),
            WeightType::F16 => {
                pack_panels(w, n, k, packed.u16_mut(), |v| f16::from_f32(v).to_bits())
            }
            WeightType::Bf16 => {
                pack_panels(w, n, k, packed.u16_mut(), |v| bf16::from_f32(v).to_bits())
            }
            WeightType::Bf16Compute | WeightType::Int8 => unreachable!("packed above"),
        }
        packed
    }

    /// Packs weights already quantised to int8 (`q [n, k]` in −127..=127, one scale per output
    /// column: `W ≈ q · scale`), as a quantised model file stores them: the same layout and
    /// products as [`PackedWeights::pack`] with [`WeightType::Int8`], whose rounding is replaced
    /// by the file's. The caller has checked the scales (finite, positive).
    pub fn from_int8(q: &[i8], scales: &[f32], n: usize, k: usize) -> PackedWeights {
        assert_eq!(q.len(), n * k, "from_int8: weight is not {n}x{k}");
        assert_eq!(
            scales.len(),
            n,
            "from_int8: {} scales for {n} columns",
            scales.len()
        );
        let mut packed = PackedWeights {
            k,
            n,
            ty: WeightType::Int8,
            ..PackedWeights::empty()
        };
        lowp::pack_int8(&mut packed, q, scales);
        packed
    }

    /// An empty f32 pack, for [`PackedWeights::repack_kn`].
    pub fn empty() -> PackedWeights {
        PackedWeights {
            k: 0,
            n: 0,
            ty: WeightType::F32,
            lines: Vec::new(),
            scales: Vec::new(),
            colsum: Vec::new(),
        }
    }

    /// Repacks `b` (`[k, n]` row-major: the right-hand matrix of `x · b`) as f32 in place,
    /// reusing the allocation: for products of two activations, which change every call, so
    /// a step that repeats the same shapes allocates nothing.
    pub fn repack_kn(&mut self, b: &[f32], k: usize, n: usize) {
        assert_eq!(b.len(), k * n, "repack_kn: b is not {k}x{n}");
        let panels = n.div_ceil(NR);
        let bytes = panels * k * NR * 4;
        let lines = bytes.div_ceil(64);
        if self.lines.len() < lines {
            self.lines.resize(lines, Line([0; 64]));
        }
        (self.k, self.n, self.ty) = (k, n, WeightType::F32);
        let dst = self.f32_mut();
        for j in 0..panels {
            for p in 0..k {
                let row = &b[p * n..(p + 1) * n];
                let out = &mut dst[(j * k + p) * NR..][..NR];
                for (c, o) in out.iter_mut().enumerate() {
                    *o = row.get(j * NR + c).copied().unwrap_or(0.0);
                }
            }
        }
    }

    /// Input features (`k`).
    pub fn inputs(&self) -> usize {
        self.k
    }

    /// Output features (`n`).
    pub fn outputs(&self) -> usize {
        self.n
    }

    /// How the weights are stored and multiplied.
    pub fn weight_type(&self) -> WeightType {
        self.ty
    }

    /// Heap bytes held (padding and int8 scales included).
    pub fn bytes(&self) -> usize {
        self.lines.len() * 64 + self.scales.len() * 4 + self.colsum.len() * 4
    }

    /// The packed words of a reduced-precision type (one per column and pair or quad).
    fn words(&self) -> &[u32] {
        let len = self.n.div_ceil(NR) * lowp::steps(self.ty, self.k) * NR;
        assert!(len * 4 <= self.lines.len() * 64);
        // SAFETY: `lines` owns at least `len * 4` bytes, 64-byte aligned; every bit pattern is
        // a valid u32.
        unsafe { std::slice::from_raw_parts(self.lines.as_ptr() as *const u32, len) }
    }

    /// The weight back as `[n, k]` row-major f32: the values as stored (narrowed for f16 and
    /// bf16, widened exactly), the panel padding dropped. Used to build derived layers (the
    /// transpose a backward pass multiplies by) only when they are needed.
    pub fn unpack(&self) -> Vec<f32> {
        if self.ty.reduced_compute() {
            return lowp::unpack(self);
        }
        let (n, k) = (self.n, self.k);
        let mut w = vec![0.0f32; n * k];
        let at = |col: usize, p: usize| ((col / NR) * k + p) * NR + col % NR;
        match self.ty {
            WeightType::F32 => {
                let src = self.f32s();
                for (col, row) in w.chunks_exact_mut(k.max(1)).take(n).enumerate() {
                    for (p, v) in row.iter_mut().enumerate() {
                        *v = src[at(col, p)];
                    }
                }
            }
            ty => {
                let src = self.u16s();
                for (col, row) in w.chunks_exact_mut(k.max(1)).take(n).enumerate() {
                    for (p, v) in row.iter_mut().enumerate() {
                        let bits = src[at(col, p)];
                        *v = match ty {
                            WeightType::F16 => f16::from_bits(bits).to_f32(),
                            _ => bf16::from_bits(bits).to_f32(),
                        };
                    }
                }
            }
        }
        w
    }

    fn values(&self) -> usize {
        self.n.div_ceil(NR) * self.k * NR
    }

    fn f32_mut(&mut self) -> &mut [f32] {
        let len = self.values();
        assert!(len * 4 <= self.lines.len() * 64);
        // SAFETY: `lines` owns at least `len * 4` bytes, 64-byte aligned, and every bit pattern
        // is a valid f32; the borrow of `self` keeps them alive and unaliased.
        unsafe { std::slice::from_raw_parts_mut(self.lines.as_mut_ptr() as *mut f32, len) }
    }

    fn f32s(&self) -> &[f32] {
        let len = self.values();
        assert!(len * 4 <= self.lines.len() * 64);
        // SAFETY: as in `f32_mut`, shared.
        unsafe { std::slice::from_raw_parts(self.lines.as_ptr() as *const f32, len) }
    }

    fn u16s(&self) -> &[u16] {
        let len = self.values();
        assert!(len * 2 <= self.lines.len() * 64);
        // SAFETY: as in `f32_mut`, for u16, shared.
        unsafe { std::slice::from_raw_parts(self.lines.as_ptr() as *const u16, len) }
    }

    fn u16_mut(&mut self) -> &mut [u16] {
        let len = self.values();
        assert!(len * 2 <= self.lines.len() * 64);
        // SAFETY: as in `f32_mut`, for u16.
        unsafe { std::slice::from_raw_parts_mut(self.lines.as_mut_ptr() as *mut u16, len) }
    }

    /// First byte of panel `j`, row `p`.
    fn panel_ptr(&self, j: usize, p: usize) -> *const u8 {
        let offset = ((j * self.k + p) * NR) * self.ty.size();
        debug_assert!(offset <= self.lines.len() * 64);
        // SAFETY: the offset is inside (or one past) the allocation for j < panels, p ≤ k.
        unsafe { (self.lines.as_ptr() as *const u8).add(offset) }
    }
}

impl Default for PackedWeights {
    fn default() -> PackedWeights {
        PackedWeights::empty()
    }
}

impl std::fmt::Debug for PackedWeights {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "PackedWeights[{}, {}] {}",
            self.n,
            self.k,
            self.ty.name()
        )
    }
}

/// `y[m, n] = act(x[m, k] · Wᵀ + bias)` on pre-packed weights, split over the current rayon pool.
/// `y` is overwritten (nothing past `m·n` is touched).
pub fn linear_packed(
    x: &[f32],
    w: &PackedWeights,
    bias: Option<&[f32]>,
    act: Activation,
    y: &mut [f32],
    m: usize,
) {
    linear_packed_on(detected_isa(), x, w, bias, act, y, m);
}

/// [`linear_packed`] on a chosen kernel (tests force the portable one through this).
pub(crate) fn linear_packed_on(
    isa: Isa,
    x: &[f32],
    w: &PackedWeights,
    bias: Option<&[f32]>,
    act: Activation,
    y: &mut [f32],
    m: usize,
) {
    let wide = isa == Isa::Avx512 && wide_tiles();
    linear_packed_tiles(isa, wide, x, w, bias, act, y, m);
}

/// [`linear_packed_on`] with the AVX-512 kernel's f32 tile chosen (`wide`: 12×32; tests run
/// both).
#[allow(clippy::too_many_arguments)]
fn linear_packed_tiles(
    isa: Isa,
    wide: bool,
    x: &[f32],
    w: &PackedWeights,
    bias: Option<&[f32]>,
    act: Activation,
    y: &mut [f32],
    m: usize,
) {
    let (k, n) = (w.k, w.n);
    // These checks are what make every pointer the kernels form stay inside its slice.
    assert!(x.len() >= m * k, "linear_packed: x too short for {m}x{k}");
    assert!(y.len() >= m * n, "linear_packed: y too short for {m}x{n}");
    if let Some(b) = bias {
        assert_eq!(b.len(), n, "linear_packed: bias length");
    }
    #[cfg(not(target_arch = "x86_64"))]
    let isa = match isa {
        Isa::Avx512 | Isa::Avx2 => Isa::Portable,
        other => other,
    };
    if m == 0 || n == 0 {
        return;
    }
    if w.ty.reduced_compute() {
        super::profile::timed(super::profile::Kind::Linear, 2 * m * k * n, || {
            lowp::linear(isa, x, w, bias, act, y, m)
        });
        return;
    }
    let job = Job {
        isa,
        // Two panels per tile on the AVX-512 kernel for f32 weights (half-precision ones are
        // widened a slice at a time into a one-panel buffer).
        wide: wide && isa == Isa::Avx512 && w.ty == WeightType::F32,
        x,
        w,
        bias,
        act,
        y: SharedMut(y.as_mut_ptr()),
        m,
    };
    super::profile::timed(super::profile::Kind::Linear, 2 * m * k * n, || job.split());
}

impl Job<'_> {
    /// Runs the whole call, split over the current pool's threads.
    fn split(&self) {
        let (k, n, m) = (self.w.k, self.w.n, self.m);
        let mr = self.isa.mr();
        split_work(
            m.div_ceil(mr),
            n.div_ceil(NR),
            m * k * n,
            |t0, t1, j0, j1| self.run(t0 * mr, (t1 * mr).min(m), j0, j1),
        );
    }
}

/// Runs `run(t0, t1, j0, j1)` over row tiles `0..tiles` × weight panels `0..panels`, split
/// over the current pool's threads when the call (`macs` multiply-adds) is worth it. The
/// weight panels are split when there are enough to balance (each task then reads a disjoint
/// part of the weights); otherwise (few outputs, many rows) the row tiles are.
fn split_work(
    tiles: usize,
    panels: usize,
    macs: usize,
    run: impl Fn(usize, usize, usize, usize) + Sync,
) {
    let threads = crate::kernels::threads();
    if threads <= 1 || macs < PAR_MIN_MACS || panels.max(tiles) < 2 {
        run(0, tiles, 0, panels);
        return;
    }
    let by_panels = panels >= 2 * threads || panels >= tiles;
    let units = if by_panels { panels } else { tiles };
    let tasks = threads.min(units);
    let edge = |t: usize| units * t / tasks;
    (0..tasks).into_par_iter().for_each(|t| {
        let (lo, hi) = (edge(t), edge(t + 1));
        if by_panels {
            run(0, tiles, lo, hi);
        } else {
            run(lo, hi, 0, panels);
        }
    });
}

/// The size of the parts when `units` is cut into as few equal parts of at most `max` as
/// possible (at least 1). M blocks are cut so: every block streams all of a task's weight
/// panels past it, so a small last block (104 rows as 96 + 8) would read them all again for a
/// few rows.
pub(super) fn equal_part(units: usize, max: usize) -> usize {
    units.div_ceil(units.div_ceil(max).max(1)).max(1)
}

/// Rows per M block for a task of `rows` rows: equal parts of at most [`MC`], rounded up to
/// whole AVX-512 tiles.
fn m_block(rows: usize) -> usize {
    equal_part(rows, MC).next_multiple_of(MR512).min(MC)
}

/// The row tiles `(first row, rows)` of rows `r0..r1` for a kernel of `mr` rows: full tiles
/// and the remainder. With `balance` (a kernel that reads its rows through pointers and runs
/// any row count) a remainder under half a tile joins the last full tile and the two run as
/// halves: 104 rows on 6-row tiles as 16 × 6 + 4 + 4 rather than 17 × 6 + 2, so every weight
/// vector loaded serves at least 4 rows.
fn row_tiles(
    r0: usize,
    r1: usize,
    mr: usize,
    balance: bool,
) -> impl Iterator<Item = (usize, usize)> {
    let (full, edge) = ((r1 - r0) / mr, (r1 - r0) % mr);
    let split = balance && full > 0 && edge > 0 && edge < mr / 2;
    let whole = if split { full - 1 } else { full };
    let tail = r0 + whole * mr;
    let (a, b) = if split {
        ((mr + edge).div_ceil(2), (mr + edge) / 2)
    } else {
        (edge, 0)
    };
    (0..whole).map(move |t| (r0 + t * mr, mr)).chain(
        [(tail, a), (tail + a, b)]
            .into_iter()
            .filter(|&(_, rows)| rows > 0),
    )
}

/// Hints part `part` of `parts` equal parts (whole 64-byte lines) of the `bytes` bytes at
/// `base` into the caches: a panel's tiles each ask for their share of the next panel.
#[inline(always)]
pub(super) fn prefetch_part(base: *const u8, bytes: usize, parts: usize, part: usize) {
    let (l0, l1) = part_lines(bytes, parts, part);
    #[cfg(target_arch = "x86_64")]
    for l in l0..l1 {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T1};
        // SAFETY: prefetch is a hint that reads nothing architecturally and never faults.
        unsafe { _mm_prefetch::<_MM_HINT_T1>(base.wrapping_add(l * 64) as *const i8) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (base, l1);
}

/// The 64-byte lines `l0..l1` of part `part` of `parts` equal parts of `bytes` bytes.
pub(super) fn part_lines(bytes: usize, parts: usize, part: usize) -> (usize, usize) {
    let lines = bytes.div_ceil(64);
    let share = lines.div_ceil(parts.max(1));
    let l0 = (part * share).min(lines);
    (l0, (l0 + share).min(lines))
}

/// One call's operands, shared by its tasks.
struct Job<'a> {
    isa: Isa,
    /// Whether pairs of full panels run on the 12×32 AVX-512 tile ([`wide_tiles`]).
    wide: bool,
    x: &'a [f32],
    w: &'a PackedWeights,
    bias: Option<&'a [f32]>,
    act: Activation,
    /// Output `[m, n]`; tasks write disjoint blocks.
    y: SharedMut,
    m: usize,
}

impl Job<'_> {
    /// Computes output rows `r0..r1` × panels `j0..j1`.
    fn run(&self, r0: usize, r1: usize, j0: usize, j1: usize) {
        let (k, n) = (self.w.k, self.w.n);
        debug_assert!(r1 <= self.m && j1 <= n.div_ceil(NR));
        if k == 0 {
            for j in j0..j1 {
                let (c0, c1) = (j * NR, (j * NR + NR).min(n));
                for r in r0..r1 {
                    let row = self.out_row(r, c0, c1);
                    match self.bias {
                        Some(b) => row.copy_from_slice(&b[c0..c1]),
                        None => row.fill(0.0),
                    }
                    self.activate(row);
                }
            }
            return;
        }
        // Half-precision panel slices widened once per M block (see `panel`); on the stack, so
        // a call allocates nothing.
        let mut widened = Widened([0.0; KC * NR]);
        if self.isa == Isa::Avx512 {
            // The AVX-512 kernel reads its 12 rows from one packed block (one pointer, each
            // step's 12 values adjacent) rather than 12 row pointers the registers cannot hold.
            // The block is per thread and reused, so a call allocates nothing after the first.
            ROW_BLOCK.with(|cell| match cell.try_borrow_mut() {
                Ok(mut block) => self.run_blocks(r0, r1, j0, j1, &mut widened, Some(&mut block)),
                Err(_) => self.run_blocks(r0, r1, j0, j1, &mut widened, Some(&mut RowBlock::new())),
            });
        } else {
            self.run_blocks(r0, r1, j0, j1, &mut widened, None);
        }
    }

    /// [`Job::run`] over K and M blocks; `rows` is the packed row block of the AVX-512 kernel.
    fn run_blocks(
        &self,
        r0: usize,
        r1: usize,
        j0: usize,
        j1: usize,
        widened: &mut Widened,
        mut rows: Option<&mut RowBlock>,
    ) {
        let k = self.w.k;
        for kb in (0..k).step_by(KC) {
            let kc = KC.min(k - kb);
            let (first, last) = (kb == 0, kb + kc == k);
            let block = m_block(r1 - r0);
            for mb in (r0..r1).step_by(block) {
                let mb_end = (mb + block).min(r1);
                let packed = rows.as_deref_mut().map(|block| {
                    block.fill(self.x, k, mb, mb_end, kb, kc);
                    &*block
                });
                let mut j = j0;
                while j < j1 {
                    let width = if self.wide && j + 1 < j1 && (j + 2) * NR <= self.w.n {
                        2
                    } else {
                        1
                    };
                    let next = j + width..(j + 2 * width).min(j1);
                    self.panel(
                        kb, kc, first, last, mb, mb_end, j, width, next, widened, packed,
                    );
                    j += width;
                }
            }
        }
    }

    /// Rows `r0..r1` of panels `j..j + width` (`width` 2: two full f32 panels on the 12×32
    /// AVX-512 tile) over multiply steps `kb..kb + kc`; `next` are the panels that follow.
    #[allow(clippy::too_many_arguments)]
    fn panel(
        &self,
        kb: usize,
        kc: usize,
        first: bool,
        last: bool,
        r0: usize,
        r1: usize,
        j: usize,
        width: usize,
        next: std::ops::Range<usize>,
        widened: &mut Widened,
        packed: Option<&RowBlock>,
    ) {
        let (k, n) = (self.w.k, self.w.n);
        let c0 = j * NR;
        let cols = (width * NR).min(n - c0);
        debug_assert!(width == 1 || (self.wide && cols == 2 * NR));
        let mut bias = [0.0f32; 2 * NR];
        if let Some(b) = self.bias {
            bias[..cols].copy_from_slice(&b[c0..c0 + cols]);
        }
        let (bias1, bias2) = bias.split_at(NR);
        let (bias1, bias2): (&[f32; NR], &[f32; NR]) =
            (bias1.try_into().unwrap(), bias2.try_into().unwrap());
        let start = if first { Some(bias1) } else { None };
        let mut b = self.w.panel_ptr(j, kb);
        let mut ty = self.w.ty;
        // The AVX2 kernel widens f16/bf16 weights inside its loop, on the same ports as the
        // multiply-adds; with several row tiles to run, widening the slice once and running the
        // f32 kernel is faster. Widening is exact, so the results are the same bits.
        #[cfg(target_arch = "x86_64")]
        let mr = self.isa.mr();
        if self.isa.has_avx2() && ty != WeightType::F32 && r1 - r0 > mr {
            // SAFETY: the panel slice holds kc × NR values of `ty` (kb + kc ≤ k); `widened`
            // has room for KC × NR ≥ kc × NR; the CPU has f16c and avx2 (Isa::Avx2).
            unsafe { avx2::widen(ty, b as *const u16, widened.0.as_mut_ptr(), kc * NR) };
            b = widened.0.as_ptr() as *const u8;
            ty = WeightType::F32;
        }
        // The vector kernels run an edge tile's `rows` rows only; the portable one always runs
        // MR (its extra rows repeat the last real one and go to the scratch tile).
        let exact = self.isa != Isa::Portable;
        // The next panel's slice comes from memory (a model's weights are read once a step, so
        // none are cached): hint its lines a share per tile, so they arrive while this panel's
        // tiles run instead of stalling the next panel's first tile.
        let (slice_bytes, tiles) = (kc * NR * self.w.ty.size(), (r1 - r0).div_ceil(mr));
        for (t, (i0, rows)) in row_tiles(r0, r1, mr, packed.is_none() && exact).enumerate() {
            // The 12×32 tile issues its share itself, one line per panel per multiply step: a
            // burst of 50 hints ahead of the tile filled the line-fill buffers and stalled
            // (7% of a FLAME-base step on a Xeon).
            let mut hints = [(std::ptr::null::<u8>(), 0usize); 2];
            for (h, q) in hints.iter_mut().zip(next.clone()) {
                if width == 2 {
                    let (l0, l1) = part_lines(slice_bytes, tiles, t);
                    *h = (self.w.panel_ptr(q, kb).wrapping_add(l0 * 64), l1 - l0);
                } else {
                    prefetch_part(self.w.panel_ptr(q, kb), slice_bytes, tiles, t);
                }
            }
            // The next tile's output rows are far apart (stride n) and, in wide layers, not in
            // cache: ask for them now so the kernel's loads (K blocks after the first) and
            // stores do not wait on memory. A hint only; it changes no result.
            for c in (c0..c0 + cols).step_by(NR) {
                if i0 + rows < r1 {
                    self.prefetch_tile(i0 + rows, mr.min(r1 - i0 - rows), c);
                } else if c + width * NR < n {
                    self.prefetch_tile(r0, mr.min(r1 - r0), c + width * NR);
                }
            }
            let a = match packed {
                Some(block) => TileRows::Packed(block.tile(i0 - r0)),
                // Missing rows of an edge tile repeat the last real row; their results are
                // dropped.
                None => TileRows::Pointers(std::array::from_fn(|i| {
                    // SAFETY: row i0 + min(i, rows-1) < m and kb < k, inside the checked m×k.
                    unsafe { self.x.as_ptr().add((i0 + i.min(rows - 1)) * k + kb) }
                })),
            };
            let y = self.y.get();
            let run = if exact { rows } else { mr };
            #[cfg(target_arch = "x86_64")]
            if width == 2 {
                let (TileRows::Packed(a), Some(_)) = (a, packed) else {
                    unreachable!("the 12x32 tile reads a packed row block")
                };
                let b1 = self.w.panel_ptr(j + 1, kb) as *const f32;
                let start = start.map(|s| (s, bias2));
                use avx512::tile_f32_wide;
                // SAFETY: wide tiles run only on the avx512 kernel (avx512f, avx2, fma
                // detected) with f32 panels; both panels are full (c0 + 32 ≤ n), so the tile
                // rows i0..i0+rows, columns c0..c0+32 lie inside y; a holds kc steps of the
                // block's tile and b, b1 kc rows of their panels; this task alone writes them.
                unsafe {
                    with_rows!(run; 1 2 3 4 5 6 7 8 9 10 11 12; tile_f32_wide(
                        kc, a, b as *const f32, b1, y.add(i0 * n + c0), n, start, hints))
                };
                if last {
                    for i in 0..rows {
                        self.activate(self.out_row(i0 + i, c0, c0 + cols));
                    }
                }
                continue;
            }
            if cols == NR && (rows == mr || exact) {
                // SAFETY: the tile rows i0..i0+rows and columns c0..c0+NR lie inside y (m×n);
                // a and b point at kc readable steps; this task alone writes the tile.
                unsafe { self.kernel(ty, kc, run, a, b, y.add(i0 * n + c0), n, start) };
            } else {
                let mut tile = [0.0f32; MR512 * NR];
                for i in 0..rows {
                    if !first {
                        tile[i * NR..i * NR + cols].copy_from_slice(self.out_row(
                            i0 + i,
                            c0,
                            c0 + cols,
                        ));
                    }
                }
                // SAFETY: the kernel writes run×NR ≤ mr×NR values into `tile` (ldc NR); a and b
                // as above.
                unsafe { self.kernel(ty, kc, run, a, b, tile.as_mut_ptr(), NR, start) };
                for i in 0..rows {
                    self.out_row(i0 + i, c0, c0 + cols)
                        .copy_from_slice(&tile[i * NR..i * NR + cols]);
                }
            }
            if last {
                for i in 0..rows {
                    self.activate(self.out_row(i0 + i, c0, c0 + cols));
                }
            }
        }
    }

    /// Hints the cache lines of the output tile at rows `r..r + rows`, columns `c0..c0 + NR`.
    #[inline(always)]
    fn prefetch_tile(&self, r: usize, rows: usize, c0: usize) {
        #[cfg(target_arch = "x86_64")]
        if self.isa.has_avx2() {
            use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
            let cols = NR.min(self.w.n - c0);
            for i in 0..rows {
                // wrapping_add: forming the address needs no unsafe; it is inside y anyway
                // (r + i < m, c0 + cols ≤ n), and a prefetch never faults.
                let first = self.y.get().wrapping_add((r + i) * self.w.n + c0);
                let last = first.wrapping_add(cols - 1);
                // SAFETY: prefetch is a hint that reads nothing architecturally.
                unsafe {
                    _mm_prefetch::<_MM_HINT_T0>(first as *const i8);
                    _mm_prefetch::<_MM_HINT_T0>(last as *const i8);
                }
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = (r, rows, c0);
    }

    /// Columns `c0..c1` of output row `r`.
    #[allow(clippy::mut_from_ref)]
    fn out_row(&self, r: usize, c0: usize, c1: usize) -> &mut [f32] {
        debug_assert!(r < self.m && c1 <= self.w.n);
        // SAFETY: inside the checked m×n output; each (row, panel) block belongs to one task and
        // the returned slice is dropped before that task forms another view of it.
        unsafe { std::slice::from_raw_parts_mut(self.y.get().add(r * self.w.n + c0), c1 - c0) }
    }

    fn activate(&self, v: &mut [f32]) {
        self.act.apply(v)
    }

    /// Runs the micro-kernel for this call's ISA on panel rows of type `ty`.
    ///
    /// # Safety
    /// `a` must be readable for `kc` steps of the kernel's rows (row pointers for the AVX2 and
    /// portable kernels, a packed tile for the AVX-512 one), `b` for `kc` panel rows of type
    /// `ty`, and `c` writable (and readable unless `start` is given) for `rows` rows of `NR`
    /// values at stride `ldc` (`rows` ≤ `isa.mr()`; the portable kernel always writes MR).
    #[allow(clippy::too_many_arguments)]
    unsafe fn kernel(
        &self,
        ty: WeightType,
        kc: usize,
        rows: usize,
        a: TileRows,
        b: *const u8,
        c: *mut f32,
        ldc: usize,
        start: Option<&[f32; NR]>,
    ) {
        let a = match (self.isa, a) {
            #[cfg(target_arch = "x86_64")]
            (Isa::Avx512, TileRows::Packed(a)) => {
                use avx512::{tile_bf16 as bf16_tile, tile_f16 as f16_tile, tile_f32 as f32_tile};
                // SAFETY: Avx512 is only chosen when the CPU has avx512f, avx2, fma and f16c;
                // pointer contracts as documented above.
                unsafe {
                    match ty {
                        WeightType::F32 => with_rows!(rows; 1 2 3 4 5 6 7 8 9 10 11 12;
                            f32_tile(kc, a, b as *const f32, c, ldc, start)),
                        WeightType::F16 => with_rows!(rows; 1 2 3 4 5 6 7 8 9 10 11 12;
                            f16_tile(kc, a, b as *const u16, c, ldc, start)),
                        WeightType::Bf16 => with_rows!(rows; 1 2 3 4 5 6 7 8 9 10 11 12;
                            bf16_tile(kc, a, b as *const u16, c, ldc, start)),
                        WeightType::Bf16Compute | WeightType::Int8 => {
                            unreachable!("reduced-precision weights run in packed::lowp")
                        }
                    }
                }
                return;
            }
            (_, TileRows::Pointers(a)) => a,
            (isa, TileRows::Packed(_)) => unreachable!("{isa:?} reads row pointers"),
        };
        let a = &a;
        match (self.isa, ty) {
            #[cfg(target_arch = "x86_64")]
            (Isa::Avx2, ty) => {
                use avx2::{tile_bf16 as bf16_tile, tile_f16 as f16_tile, tile_f32 as f32_tile};
                // SAFETY: Avx2 is only chosen after detecting avx2, fma and f16c (tests force
                // only the portable kernel); pointer contracts as documented above.
                unsafe {
                    match ty {
                        WeightType::F32 => with_rows!(rows; 1 2 3 4 5 6;
                            f32_tile(kc, a, b as *const f32, c, ldc, start)),
                        WeightType::F16 => with_rows!(rows; 1 2 3 4 5 6;
                            f16_tile(kc, a, b as *const u16, c, ldc, start)),
                        WeightType::Bf16 => with_rows!(rows; 1 2 3 4 5 6;
                            bf16_tile(kc, a, b as *const u16, c, ldc, start)),
                        WeightType::Bf16Compute | WeightType::Int8 => {
                            unreachable!("reduced-precision weights run in packed::lowp")
                        }
                    }
                }
            }
            (_, ty) => {
                let tile = |p: usize| -> [f32; NR] {
                    // SAFETY: p < kc panel rows are readable (contract above).
                    std::array::from_fn(|cc| unsafe {
                        match ty {
                            WeightType::F32 => *(b as *const f32).add(p * NR + cc),
                            WeightType::F16 => {
                                f16::from_bits(*(b as *const u16).add(p * NR + cc)).to_f32()
                            }
                            WeightType::Bf16 => {
                                bf16::from_bits(*(b as *const u16).add(p * NR + cc)).to_f32()
                            }
                            WeightType::Bf16Compute | WeightType::Int8 => {
                                unreachable!("reduced-precision weights run in packed::lowp")
                            }
                        }
                    })
                };
                // The portable kernel runs all MR rows (the caller gives it room for them).
                let _ = rows;
                // SAFETY: forwarded contract.
                unsafe { portable_tile(kc, a, tile, c, ldc, start) }
            }
        }
    }
}

/// Calls the const-generic micro-kernel `$f::<R>` with `R = $rows`, one of the listed counts:
/// an edge tile of R rows runs R rows of multiply-adds, not the full tile's.
#[cfg(target_arch = "x86_64")]
macro_rules! with_rows {
    ($rows:expr; $($r:literal)+; $f:ident $args:tt) => {
        match $rows {
            $($r => $f::<$r> $args,)+
            r => unreachable!("a tile of {r} rows"),
        }
    };
}
#[cfg(target_arch = "x86_64")]
use with_rows;

/// The portable micro-kernel: `c[MR×NR] (+)= a · b` with multiply-then-add chains.
///
/// # Safety
/// As [`Job::kernel`].
unsafe fn portable_tile(
    kc: usize,
    a: &[*const f32; MR],
    b: impl Fn(usize) -> [f32; NR],
    c: *mut f32,
    ldc: usize,
    start: Option<&[f32; NR]>,
) {
    let mut acc = [[0.0f32; NR]; MR];
    for (i, row) in acc.iter_mut().enumerate() {
        *row = match start {
            Some(s) => *s,
            // SAFETY: c is readable for MR rows of NR at stride ldc when start is None.
            None => std::array::from_fn(|cc| unsafe { *c.add(i * ldc + cc) }),
        };
    }
    for p in 0..kc {
        let bp = b(p);
        for (i, row) in acc.iter_mut().enumerate() {
            // SAFETY: a[i] is readable for kc values.
            let ai = unsafe { *a[i].add(p) };
            for (v, &bv) in row.iter_mut().zip(&bp) {
                *v += ai * bv;
            }
        }
    }
    for (i, row) in acc.iter().enumerate() {
        for (cc, &v) in row.iter().enumerate() {
            // SAFETY: c is writable for MR rows of NR at stride ldc.
            unsafe { *c.add(i * ldc + cc) = v };
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    //! The 6×16 AVX2/FMA micro-kernel: 12 accumulators, one panel row (two vectors) loaded
    //! and widened per step, each activation broadcast once.

    use super::{WeightType, MR, NR};
    use std::arch::x86_64::*;

    macro_rules! tile_kernel {
        ($name:ident, $elem:ty, |$b:ident, $p:ident| $load:expr) => {
            /// `c[R×NR] (+)= a · b` over `kc` steps, rows `a[..R]` (`R ≤ MR`; see
            /// `Job::kernel` for the contract).
            ///
            /// # Safety
            /// The CPU supports avx2, fma and f16c; pointer contract of `Job::kernel` for `R`
            /// rows.
            #[target_feature(enable = "avx2,fma,f16c")]
            pub(super) unsafe fn $name<const R: usize>(
                kc: usize,
                a: &[*const f32; MR],
                $b: *const $elem,
                c: *mut f32,
                ldc: usize,
                start: Option<&[f32; NR]>,
            ) {
                // SAFETY (whole body): every load/store is unaligned-tolerant and stays inside
                // the ranges the contract grants: a[i][..kc], b[..kc·NR], c rows of NR values.
                unsafe {
                    let mut acc = [[_mm256_setzero_ps(); 2]; R];
                    for (i, v) in acc.iter_mut().enumerate() {
                        let (lo, hi) = match start {
                            Some(s) => (
                                _mm256_loadu_ps(s.as_ptr()),
                                _mm256_loadu_ps(s.as_ptr().add(8)),
                            ),
                            None => (
                                _mm256_loadu_ps(c.add(i * ldc)),
                                _mm256_loadu_ps(c.add(i * ldc + 8)),
                            ),
                        };
                        *v = [lo, hi];
                    }
                    for $p in 0..kc {
                        let (b0, b1): (__m256, __m256) = $load;
                        for (i, v) in acc.iter_mut().enumerate() {
                            let ai = _mm256_broadcast_ss(&*a[i].add($p));
                            v[0] = _mm256_fmadd_ps(ai, b0, v[0]);
                            v[1] = _mm256_fmadd_ps(ai, b1, v[1]);
                        }
                    }
                    for (i, v) in acc.iter().enumerate() {
                        _mm256_storeu_ps(c.add(i * ldc), v[0]);
                        _mm256_storeu_ps(c.add(i * ldc + 8), v[1]);
                    }
                }
            }
        };
    }

    /// `dst[..n] = src[..n]` widened from f16 or bf16 (exact).
    ///
    /// # Safety
    /// The CPU supports avx2 and f16c; `src` readable and `dst` writable for `n` values.
    #[target_feature(enable = "avx2,f16c")]
    pub(super) unsafe fn widen(ty: WeightType, src: *const u16, dst: *mut f32, n: usize) {
        // SAFETY (whole body): loads and stores stay inside src[..n] and dst[..n].
        unsafe {
            let mut i = 0;
            while i + 8 <= n {
                let h = _mm_loadu_si128(src.add(i) as *const __m128i);
                let v = match ty {
                    WeightType::F16 => _mm256_cvtph_ps(h),
                    _ => _mm256_castsi256_ps(_mm256_slli_epi32::<16>(_mm256_cvtepu16_epi32(h))),
                };
                _mm256_storeu_ps(dst.add(i), v);
                i += 8;
            }
            for i in i..n {
                let bits = *src.add(i);
                *dst.add(i) = match ty {
                    WeightType::F16 => half::f16::from_bits(bits).to_f32(),
                    _ => half::bf16::from_bits(bits).to_f32(),
                };
            }
        }
    }

    tile_kernel!(tile_f32, f32, |b, p| (
        _mm256_loadu_ps(b.add(p * NR)),
        _mm256_loadu_ps(b.add(p * NR + 8))
    ));
    tile_kernel!(tile_f16, u16, |b, p| (
        _mm256_cvtph_ps(_mm_loadu_si128(b.add(p * NR) as *const __m128i)),
        _mm256_cvtph_ps(_mm_loadu_si128(b.add(p * NR + 8) as *const __m128i))
    ));
    tile_kernel!(tile_bf16, u16, |b, p| (
        // bf16 is the top half of an f32: zero-extend to 32 bits and shift into place.
        _mm256_castsi256_ps(_mm256_slli_epi32::<16>(_mm256_cvtepu16_epi32(
            _mm_loadu_si128(b.add(p * NR) as *const __m128i)
        ))),
        _mm256_castsi256_ps(_mm256_slli_epi32::<16>(_mm256_cvtepu16_epi32(
            _mm_loadu_si128(b.add(p * NR + 8) as *const __m128i)
        )))
    ));
}

#[cfg(target_arch = "x86_64")]
mod avx512 {
    //! The 12×16 AVX-512 micro-kernel: 12 accumulators of one 16-lane vector, one panel row
    //! (one 64-byte line) loaded and widened per step, each activation broadcast from the
    //! packed row block. Every output is the same chain of fused multiply-adds as in the AVX2
    //! kernel, so the two give the same bits.

    use super::{MR512, NR};
    use std::arch::x86_64::*;

    macro_rules! tile_kernel {
        ($name:ident, $elem:ty, |$b:ident, $p:ident| $load:expr) => {
            /// `c[R×NR] (+)= a · b` over `kc` steps, `a` a tile of a `RowBlock` (its first
            /// `R ≤ 12` rows).
            ///
            /// # Safety
            /// The CPU supports avx512f, avx2, fma and f16c; `a` readable for `kc · 12`
            /// values, `b` for `kc` panel rows, `c` as in `Job::kernel` for `R` rows.
            #[target_feature(enable = "avx512f,avx2,fma,f16c")]
            pub(super) unsafe fn $name<const R: usize>(
                kc: usize,
                a: *const f32,
                $b: *const $elem,
                c: *mut f32,
                ldc: usize,
                start: Option<&[f32; NR]>,
            ) {
                // SAFETY (whole body): every load/store is unaligned-tolerant and stays inside
                // the ranges the contract grants.
                unsafe {
                    let mut acc = [_mm512_setzero_ps(); R];
                    for (i, v) in acc.iter_mut().enumerate() {
                        *v = match start {
                            Some(s) => _mm512_loadu_ps(s.as_ptr()),
                            None => _mm512_loadu_ps(c.add(i * ldc)),
                        };
                    }
                    for $p in 0..kc {
                        let b0: __m512 = $load;
                        let ap = a.add($p * MR512);
                        for (i, v) in acc.iter_mut().enumerate() {
                            *v = _mm512_fmadd_ps(_mm512_set1_ps(*ap.add(i)), b0, *v);
                        }
                    }
                    for (i, v) in acc.iter().enumerate() {
                        _mm512_storeu_ps(c.add(i * ldc), *v);
                    }
                }
            }
        };
    }

    /// `c[R×2NR] (+)= a · [b0 b1]`: two panels per step (the 12×32 tile), each output the same
    /// chain of fused multiply-adds as in [`tile_f32`]. `start` holds the two panels' biases.
    ///
    /// `hints` are up to two runs of 64-byte lines (start, count) to hint into L2, one line of
    /// each per step.
    ///
    /// # Safety
    /// As [`tile_f32`], with `b0` and `b1` each readable for `kc` panel rows and `c` for `R`
    /// rows of `2·NR` values.
    #[allow(clippy::too_many_arguments)]
    #[target_feature(enable = "avx512f,avx2,fma,f16c")]
    pub(super) unsafe fn tile_f32_wide<const R: usize>(
        kc: usize,
        a: *const f32,
        b0: *const f32,
        b1: *const f32,
        c: *mut f32,
        ldc: usize,
        start: Option<(&[f32; NR], &[f32; NR])>,
        hints: [(*const u8, usize); 2],
    ) {
        // SAFETY (whole body): every load/store is unaligned-tolerant and stays inside the
        // ranges the contract grants.
        unsafe {
            let mut lo = [_mm512_setzero_ps(); R];
            let mut hi = [_mm512_setzero_ps(); R];
            for i in 0..R {
                (lo[i], hi[i]) = match start {
                    Some((s0, s1)) => (_mm512_loadu_ps(s0.as_ptr()), _mm512_loadu_ps(s1.as_ptr())),
                    None => (
                        _mm512_loadu_ps(c.add(i * ldc)),
                        _mm512_loadu_ps(c.add(i * ldc + NR)),
                    ),
                };
            }
            for p in 0..kc {
                // Hints only (never fault, read nothing): step p asks for line p of each.
                for &(base, lines) in &hints {
                    if p < lines {
                        _mm_prefetch::<_MM_HINT_T1>(base.wrapping_add(p * 64) as *const i8);
                    }
                }
                let (w0, w1) = (
                    _mm512_loadu_ps(b0.add(p * NR)),
                    _mm512_loadu_ps(b1.add(p * NR)),
                );
                let ap = a.add(p * MR512);
                for i in 0..R {
                    let x = _mm512_set1_ps(*ap.add(i));
                    lo[i] = _mm512_fmadd_ps(x, w0, lo[i]);
                    hi[i] = _mm512_fmadd_ps(x, w1, hi[i]);
                }
            }
            for i in 0..R {
                _mm512_storeu_ps(c.add(i * ldc), lo[i]);
                _mm512_storeu_ps(c.add(i * ldc + NR), hi[i]);
            }
        }
    }

    /// 12 independent multiply-add chains of `n` steps on 256-bit vectors, for
    /// `super::full_width_fma512`.
    ///
    /// # Safety
    /// The CPU supports avx2 and fma.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn chains256(n: usize) -> f32 {
        let (a, b) = (_mm256_set1_ps(1.000_001), _mm256_set1_ps(0.999_999));
        let mut acc = [_mm256_setzero_ps(); 12];
        for _ in 0..n {
            for v in acc.iter_mut() {
                *v = _mm256_fmadd_ps(a, b, *v);
            }
        }
        let mut out = [0.0f32; 8];
        // SAFETY: out holds 8 f32s.
        unsafe {
            _mm256_storeu_ps(
                out.as_mut_ptr(),
                acc.iter().fold(a, |s, &v| _mm256_add_ps(s, v)),
            )
        };
        out[0]
    }

    /// As [`chains256`] on 512-bit vectors.
    ///
    /// # Safety
    /// The CPU supports avx512f.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn chains512(n: usize) -> f32 {
        let (a, b) = (_mm512_set1_ps(1.000_001), _mm512_set1_ps(0.999_999));
        let mut acc = [_mm512_setzero_ps(); 12];
        for _ in 0..n {
            for v in acc.iter_mut() {
                *v = _mm512_fmadd_ps(a, b, *v);
            }
        }
        _mm512_reduce_add_ps(acc.iter().fold(a, |s, &v| _mm512_add_ps(s, v)))
    }

    tile_kernel!(tile_f32, f32, |b, p| _mm512_loadu_ps(b.add(p * NR)));
    tile_kernel!(tile_f16, u16, |b, p| _mm512_cvtph_ps(_mm256_loadu_si256(
        b.add(p * NR) as *const __m256i
    )));
    tile_kernel!(tile_bf16, u16, |b, p| _mm512_castsi512_ps(
        _mm512_slli_epi32::<16>(_mm512_cvtepu16_epi32(_mm256_loadu_si256(
            b.add(p * NR) as *const __m256i
        )))
    ));
}

/// A `Linear` layer on packed weights: weight, optional bias, fused activation.
#[derive(Debug)]
pub struct PackedLinear {
    weight: PackedWeights,
    bias: Option<Vec<f32>>,
}

impl PackedLinear {
    /// Packs `weight` (`[n_out, n_in]`) as `ty`; the bias (`[n_out]`) stays f32.
    pub fn new(
        weight: &[f32],
        bias: Option<&[f32]>,
        n_in: usize,
        n_out: usize,
        ty: WeightType,
    ) -> PackedLinear {
        if let Some(b) = bias {
            assert_eq!(b.len(), n_out, "PackedLinear: bias length");
        }
        PackedLinear {
            weight: PackedWeights::pack(weight, n_out, n_in, ty),
            bias: bias.map(<[f32]>::to_vec),
        }
    }

    /// A layer on weights packed already (a quantised file's int8 rows); the bias
    /// (`[n_out]`) stays f32.
    pub fn from_packed(weight: PackedWeights, bias: Option<&[f32]>) -> PackedLinear {
        if let Some(b) = bias {
            assert_eq!(b.len(), weight.n, "PackedLinear: bias length");
        }
        PackedLinear {
            weight,
            bias: bias.map(<[f32]>::to_vec),
        }
    }

    /// Input features (`n_in`).
    pub fn inputs(&self) -> usize {
        self.weight.k
    }

    /// Output features (`n_out`).
    pub fn outputs(&self) -> usize {
        self.weight.n
    }

    /// The packed weight (its type, size in memory, values).
    pub fn weights(&self) -> &PackedWeights {
        &self.weight
    }

    /// `y[rows, out] = act(x[rows, in] · Wᵀ + b)`.
    pub fn forward(&self, x: &[f32], rows: usize, y: &mut [f32], act: Activation) {
        linear_packed(x, &self.weight, self.bias.as_deref(), act, y, rows);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::{in_pool, isas, same_bits, Rng};

    /// Every kernel this CPU runs, the AVX-512 one with each f32 tile (`true`: 12×32).
    fn kernels() -> Vec<(Isa, bool)> {
        let mut all: Vec<_> = isas().into_iter().map(|isa| (isa, false)).collect();
        if Isa::Avx512.supported() {
            all.insert(1, (Isa::Avx512, true));
        }
        all
    }

    /// Reference in f64 on the weights as the kernel sees them (narrowed), plus `Σ|x||w|`.
    fn naive(
        x: &[f32],
        w: &[f32],
        bias: Option<&[f32]>,
        m: usize,
        k: usize,
        n: usize,
    ) -> (Vec<f64>, Vec<f64>) {
        let mut y = vec![0.0; m * n];
        let mut mag = vec![0.0; m * n];
        for i in 0..m {
            for j in 0..n {
                let mut s = bias.map_or(0.0, |b| b[j] as f64);
                let mut g = s.abs();
                for p in 0..k {
                    let t = x[i * k + p] as f64 * w[j * k + p] as f64;
                    s += t;
                    g += t.abs();
                }
                y[i * n + j] = s;
                mag[i * n + j] = g;
            }
        }
        (y, mag)
    }

    fn narrowed(w: &[f32], ty: WeightType) -> Vec<f32> {
        w.iter()
            .map(|&v| match ty {
                WeightType::F32 => v,
                WeightType::F16 => f16::from_f32(v).to_f32(),
                WeightType::Bf16 => bf16::from_f32(v).to_f32(),
                WeightType::Bf16Compute | WeightType::Int8 => unreachable!("tested in lowp"),
            })
            .collect()
    }

    const SHAPES: &[(usize, usize, usize)] = &[
        (1, 1, 1),
        (1, 3, 5),
        (3, 1, 17),
        (5, 7, 1),
        (2, 0, 3),
        (6, 16, 16),
        (7, 300, 33),
        (13, 257, 16),
        (197, 3, 5),
        (64, 65, 33),
        (100, 520, 47),
        (20, 384, 70),
        // Three equal M blocks of 84 rows (7 AVX-512 tiles each), K blocks of 256 and 2.
        (252, 258, 40),
    ];

    #[test]
    fn int8_weights_from_a_file_pack_as_rounding_at_load_does() {
        // A quantised file's integers with the scales rounding at load would choose give the
        // same words, column sums and scales, so the products are the ones every int8 kernel
        // test checks.
        let mut rng = Rng::new(11);
        for &(_, k, n) in SHAPES {
            let w = rng.vec(n * k);
            let at_load = PackedWeights::pack(&w, n, k, WeightType::Int8);
            let q: Vec<i8> = w
                .iter()
                .enumerate()
                .map(|(i, &v)| {
                    let s = at_load.scales[i / k];
                    let inv = if s > 0.0 { 1.0 / s } else { 0.0 };
                    (v * inv).round_ties_even().clamp(-127.0, 127.0) as i8
                })
                .collect();
            let from_file = PackedWeights::from_int8(&q, &at_load.scales, n, k);
            assert_eq!(from_file.words(), at_load.words(), "{n}x{k}");
            assert_eq!(from_file.colsum, at_load.colsum, "{n}x{k}");
            assert_eq!(from_file.unpack(), at_load.unpack(), "{n}x{k}");
        }
    }

    #[test]
    fn a_repacked_right_hand_matrix_gives_the_same_bits_as_its_packed_transpose() {
        // repack_kn(b [k, n]) is pack(bᵀ [n, k]); the same buffer serves shrinking and
        // growing shapes.
        let mut rng = Rng::new(5);
        let mut pw = PackedWeights::empty();
        for &(m, k, n) in SHAPES.iter().chain(SHAPES.iter().rev()) {
            let x = rng.vec(m * k);
            let b = rng.vec(k * n);
            let bt: Vec<f32> = (0..n * k).map(|i| b[(i % k) * n + i / k]).collect();
            pw.repack_kn(&b, k, n);
            let packed = PackedWeights::pack(&bt, n, k, WeightType::F32);
            for isa in isas() {
                let mut y1 = vec![0.0; m * n];
                let mut y2 = vec![0.0; m * n];
                linear_packed_on(isa, &x, &pw, None, Activation::None, &mut y1, m);
                linear_packed_on(isa, &x, &packed, None, Activation::None, &mut y2, m);
                assert!(same_bits(&y1, &y2), "{isa:?} {m}x{k}x{n}");
            }
        }
    }

    #[test]
    fn matches_naive_on_odd_shapes_every_kernel_and_type() {
        let mut rng = Rng::new(11);
        let u = f32::EPSILON as f64 / 2.0;
        for &(m, k, n) in SHAPES {
            let x = rng.vec(m * k);
            let w = rng.vec(n * k);
            let bias = rng.vec(n);
            for ty in [WeightType::F32, WeightType::F16, WeightType::Bf16] {
                let packed = PackedWeights::pack(&w, n, k, ty);
                let wn = narrowed(&w, ty);
                for (isa, wide) in kernels() {
                    for b in [None, Some(&bias[..])] {
                        let mut y = vec![f32::NAN; m * n + 3];
                        y[m * n..].fill(7.0);
                        linear_packed_tiles(isa, wide, &x, &packed, b, Activation::None, &mut y, m);
                        assert_eq!(&y[m * n..], &[7.0; 3], "wrote past the output");
                        let (want, mag) = naive(&x, &wn, b, m, k, n);
                        for (i, (&g, (&wv, &s))) in y.iter().zip(want.iter().zip(&mag)).enumerate()
                        {
                            let tol = 2.0 * (k + 2) as f64 * u * s + 1e-30;
                            assert!(
                                (g as f64 - wv).abs() <= tol,
                                "{isa:?} wide={wide} {ty:?} {m}x{k}x{n} bias={} [{i}]: {g} vs {wv}",
                                b.is_some()
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn the_avx512_and_avx2_kernels_give_the_same_bits() {
        // Both run each output as the same chain of fused multiply-adds; only the tiling
        // differs (12×16 or 12×32 vs 6×16), so every shape, edge tiles, odd panel counts and K
        // blocks included, agrees bit for bit.
        if !(Isa::Avx512.supported() && Isa::Avx2.supported()) {
            eprintln!("the_avx512_and_avx2_kernels_give_the_same_bits: skipped, no AVX-512 here");
            return;
        }
        let mut rng = Rng::new(16);
        for &(m, k, n) in SHAPES.iter().chain(&[
            (25, 600, 40),
            (97, 257, 33),
            (12, 16, 16),
            (30, 40, 96),
            (131, 520, 80),
        ]) {
            let (x, w, bias) = (rng.vec(m * k), rng.vec(n * k), rng.vec(n));
            for ty in [WeightType::F32, WeightType::F16, WeightType::Bf16] {
                let packed = PackedWeights::pack(&w, n, k, ty);
                for act in [Activation::None, Activation::Gelu] {
                    let run = |isa, wide| {
                        let mut y = vec![0.0; m * n];
                        linear_packed_tiles(isa, wide, &x, &packed, Some(&bias), act, &mut y, m);
                        y
                    };
                    let avx2 = run(Isa::Avx2, false);
                    for wide in [false, true] {
                        assert!(
                            same_bits(&run(Isa::Avx512, wide), &avx2),
                            "wide={wide} {ty:?} {act:?} {m}x{k}x{n}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn unpack_returns_the_stored_weights() {
        let mut rng = Rng::new(15);
        for &(n, k) in &[(1, 1), (17, 5), (33, 40), (16, 3), (5, 0)] {
            let w = rng.vec(n * k);
            for ty in [WeightType::F32, WeightType::F16, WeightType::Bf16] {
                let got = PackedWeights::pack(&w, n, k, ty).unpack();
                let want = narrowed(&w, ty);
                assert!(same_bits(&got, &want), "{ty:?} {n}x{k}");
                if ty != WeightType::F32 && n * k > 0 {
                    assert!(got != w, "{ty:?} {n}x{k}: nothing was narrowed");
                }
            }
        }
    }

    #[test]
    fn fused_activations_equal_separate_passes() {
        let mut rng = Rng::new(12);
        let (m, k, n) = (29, 300, 37);
        let (x, w, bias) = (rng.vec(m * k), rng.vec(n * k), rng.vec(n));
        let packed = PackedWeights::pack(&w, n, k, WeightType::F32);
        for isa in isas() {
            let mut plain = vec![0.0; m * n];
            linear_packed_on(
                isa,
                &x,
                &packed,
                Some(&bias),
                Activation::None,
                &mut plain,
                m,
            );
            for (act, f) in [
                (Activation::Relu, relu as fn(&mut [f32])),
                (Activation::Gelu, gelu_erf),
            ] {
                let mut want = plain.clone();
                f(&mut want);
                let mut got = vec![0.0; m * n];
                linear_packed_on(isa, &x, &packed, Some(&bias), act, &mut got, m);
                assert!(same_bits(&got, &want), "{isa:?} {act:?}");
            }
        }
    }

    #[test]
    fn half_weights_equal_f32_on_prerounded_weights() {
        let mut rng = Rng::new(13);
        let (m, k, n) = (31, 530, 45);
        let (x, w, bias) = (rng.vec(m * k), rng.vec(n * k), rng.vec(n));
        for ty in [WeightType::F16, WeightType::Bf16] {
            let half = PackedWeights::pack(&w, n, k, ty);
            let full = PackedWeights::pack(&narrowed(&w, ty), n, k, WeightType::F32);
            assert_eq!(half.bytes() * 2, full.bytes());
            for isa in isas() {
                let mut a = vec![0.0; m * n];
                let mut b = vec![0.0; m * n];
                linear_packed_on(isa, &x, &half, Some(&bias), Activation::Gelu, &mut a, m);
                linear_packed_on(isa, &x, &full, Some(&bias), Activation::Gelu, &mut b, m);
                assert!(same_bits(&a, &b), "{isa:?} {ty:?}");
            }
        }
    }

    #[test]
    fn bit_identical_across_thread_counts() {
        let mut rng = Rng::new(14);
        for &(m, k, n) in &[
            (398, 768, 100),
            (400, 300, 2304),
            (20, 768, 3072),
            (1, 3072, 768),
            (130, 1030, 48),
        ] {
            let (x, w, bias) = (rng.vec(m * k), rng.vec(n * k), rng.vec(n));
            for ty in [WeightType::F32, WeightType::Bf16] {
                let packed = PackedWeights::pack(&w, n, k, ty);
                for (isa, wide) in kernels() {
                    let run = |threads: usize| {
                        in_pool(threads, || {
                            let mut y = vec![0.0; m * n];
                            linear_packed_tiles(
                                isa,
                                wide,
                                &x,
                                &packed,
                                Some(&bias),
                                Activation::Relu,
                                &mut y,
                                m,
                            );
                            y
                        })
                    };
                    let base = run(1);
                    for threads in [2, 3] {
                        assert!(
                            same_bits(&base, &run(threads)),
                            "{isa:?} wide={wide} {ty:?} {m}x{k}x{n}: {threads} threads differ from 1"
                        );
                    }
                }
            }
        }
    }
}
