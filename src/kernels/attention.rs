//! Multi-head scaled dot-product attention.
//!
//! Work is split into (query block, head) tasks that write disjoint `[rows, head_dim]` blocks
//! of `out`. The block size is fixed (not derived from the thread count) and every output
//! element comes from one task, in one fixed order of operations, so results are bit-identical
//! for any pool size.
//!
//! Each task holds its scores and a transposed copy of its head's keys in a per-thread slot of
//! an [`AttentionScratch`]; every slot is sized before the tasks start, so a caller that keeps
//! its scratch between calls allocates nothing after the first. The two products (`q·kᵀ` and
//! `p·v`) use a 4×16 register-blocked AVX2+FMA kernel when the CPU has one (the same detection
//! as the linear layers) and plain loops otherwise.

use std::cell::UnsafeCell;

use rayon::prelude::*;

use super::activation::softmax_row;
use super::packed::{detected_isa, Isa};

/// Query rows per task: bounds the score buffer at `Q_BLOCK × lk` and gives 2 cores enough
/// tasks to balance at the sequence lengths we run (~200-400).
const Q_BLOCK: usize = 32;
const _: () = assert!(Q_BLOCK <= 64, "dead-row mask is a u64");

/// Keys per register tile (two AVX2 vectors); score rows are padded to a multiple of it.
const KT: usize = 16;
/// Query rows per register tile.
const RT: usize = 4;

/// Below this many score entries × head_dim, run on the calling thread.
const PAR_MIN_WORK: usize = 1 << 16;

/// Raw output pointer shared by tasks that write disjoint blocks.
#[derive(Clone, Copy)]
struct OutPtr(*mut f32);
// SAFETY: tasks write disjoint (row block, head) regions; see `AttentionScratch::attend`.
unsafe impl Send for OutPtr {}
unsafe impl Sync for OutPtr {}
impl OutPtr {
    fn get(self) -> *mut f32 {
        self.0
    }
}

/// One worker's buffers: scores `[Q_BLOCK, keys_padded]` then keys transposed
/// `[head_dim, keys_padded]`.
struct Slot(UnsafeCell<Vec<f32>>);
// SAFETY: slot `i` is only touched by the task running on rayon worker `i` (or by the calling
// thread when nothing runs in parallel), and a task never yields to another task while it holds
// the slot (it calls nothing that could steal work), so no two threads use a slot at once.
unsafe impl Sync for Slot {}

/// Reusable per-thread buffers of [`multi_head_attention`]-style calls.
#[derive(Default)]
pub struct AttentionScratch {
    slots: Vec<Slot>,
    keys_t: Vec<f32>,
    values: Vec<f32>,
}

impl AttentionScratch {
    /// Multi-head attention, as [`multi_head_attention`], with buffers kept in `self`.
    #[allow(clippy::too_many_arguments)]
    pub fn attend(
        &mut self,
        q: &[f32],
        q_stride: usize,
        k: &[f32],
        k_stride: usize,
        v: &[f32],
        v_stride: usize,
        lq: usize,
        lk: usize,
        heads: usize,
        head_dim: usize,
        key_padding: Option<&[bool]>,
        causal: bool,
        out: &mut [f32],
    ) {
        let e = heads * head_dim;
        assert!(out.len() >= lq * e, "attention: out too short");
        let rows_fit =
            |len: usize, rows: usize, stride: usize| rows == 0 || len >= (rows - 1) * stride + e;
        assert!(rows_fit(q.len(), lq, q_stride), "attention: q too short");
        assert!(rows_fit(k.len(), lk, k_stride), "attention: k too short");
        assert!(rows_fit(v.len(), lk, v_stride), "attention: v too short");
        if let Some(p) = key_padding {
            assert_eq!(p.len(), lk, "attention: key_padding length");
        }
        if lq == 0 || e == 0 {
            return;
        }
        if lk == 0 {
            out[..lq * e].fill(0.0);
            return;
        }

        // PyTorch computes head_dim ** -0.5 in double and applies it as an f32 scalar.
        let scale = (1.0 / (head_dim as f64).sqrt()) as f32;
        let blocks = lq.div_ceil(Q_BLOCK);
        let tasks = blocks * heads;
        let out_ptr = OutPtr(out.as_mut_ptr());
        let isa = detected_isa();
        let kp = lk.div_ceil(KT) * KT;
        let slot_len = Q_BLOCK * kp;

        let work = lq.saturating_mul(lk).saturating_mul(e);
        let parallel = tasks > 1 && work >= PAR_MIN_WORK && crate::kernels::threads() > 1;
        let slots = if parallel {
            crate::kernels::threads()
        } else {
            1
        };
        // Size every slot now, on this thread: tasks never allocate.
        if self.slots.len() < slots {
            self.slots
                .resize_with(slots, || Slot(UnsafeCell::new(Vec::new())));
        }
        for slot in &mut self.slots[..slots] {
            let buf = slot.0.get_mut();
            if buf.len() < slot_len {
                buf.resize(slot_len, 0.0);
            }
        }
        // kᵀ of every head, [heads, head_dim, kp], zero past `lk`, and v of every head,
        // [heads, lk, head_dim]: made once per call (by head, on the threads that then run
        // that head's query blocks) and read by every query block of that head, contiguous
        // rather than at the projection's row stride (a new page per key).
        let kt_len = heads * head_dim * kp;
        if self.keys_t.len() < kt_len {
            self.keys_t.resize(kt_len, 0.0);
        }
        let v_len = heads * lk * head_dim;
        if self.values.len() < v_len {
            self.values.resize(v_len, 0.0);
        }
        let gather = |(h, (kt, vh)): (usize, (&mut [f32], &mut [f32]))| {
            let col = h * head_dim;
            for (j, dst) in vh.chunks_exact_mut(head_dim).enumerate() {
                dst.copy_from_slice(&v[j * v_stride + col..j * v_stride + col + head_dim]);
                for (c, &x) in k[j * k_stride + col..j * k_stride + col + head_dim]
                    .iter()
                    .enumerate()
                {
                    kt[c * kp + j] = x;
                }
            }
            for row in kt.chunks_exact_mut(kp) {
                row[lk..].fill(0.0);
            }
        };
        let (keys_t, values) = (&mut self.keys_t[..kt_len], &mut self.values[..v_len]);
        if parallel {
            keys_t
                .par_chunks_mut(head_dim * kp)
                .zip(values.par_chunks_mut(lk * head_dim))
                .enumerate()
                .for_each(gather);
        } else {
            keys_t
                .chunks_mut(head_dim * kp)
                .zip(values.chunks_mut(lk * head_dim))
                .enumerate()
                .for_each(gather);
        }
        let (keys_t, values) = (&self.keys_t[..kt_len], &self.values[..v_len]);
        let slots_ref = &self.slots;

        let task = |t: usize| {
            let slot = if parallel {
                rayon::current_thread_index().expect("attention tasks run on the pool")
            } else {
                0
            };
            // SAFETY: see `Slot`: this thread alone uses slot `slot` while the task runs.
            let buf = unsafe { &mut *slots_ref[slot].0.get() };
            let scores = &mut buf[..slot_len];

            let (h, block) = (t / blocks, t % blocks);
            let i0 = block * Q_BLOCK;
            let rows = Q_BLOCK.min(lq - i0);
            // Causal rows of this block see at most keys 0..i0+rows; the rest would be masked.
            let keys = if causal { lk.min(i0 + rows) } else { lk };
            let ktp = keys.div_ceil(KT) * KT;
            let col = h * head_dim;

            let q_block = &q[i0 * q_stride + col..];
            let kt = &keys_t[h * head_dim * kp..(h + 1) * head_dim * kp];
            scores_qk(
                isa, q_block, q_stride, kt, kp, ktp, rows, head_dim, scale, scores,
            );

            let mut dead_rows = 0u64; // bit r: row r has no visible key (Q_BLOCK <= 64)
            for r in 0..rows {
                let row = &mut scores[r * ktp..r * ktp + keys];
                if let Some(p) = key_padding {
                    for (s, &pad) in row.iter_mut().zip(p) {
                        if pad {
                            *s = f32::NEG_INFINITY;
                        }
                    }
                }
                // Causal rows normalise only their visible keys (the rest are exactly 0), so a
                // row's sum runs over the same values in the same order whatever follows it:
                // padding a sequence leaves its prefix bit-identical.
                let visible = if causal { (i0 + r + 1).min(keys) } else { keys };
                row[visible..].fill(0.0);
                if !softmax_row(&mut row[..visible]) {
                    dead_rows |= 1 << r;
                }
            }

            // SAFETY: this task alone writes rows i0..i0+rows, columns col..col+head_dim of
            // `out` (bounds asserted above); no other reference to `out` is used meanwhile.
            let dst = unsafe {
                std::slice::from_raw_parts_mut(
                    out_ptr.get().add(i0 * e + col),
                    (rows - 1) * e + head_dim,
                )
            };
            weighted_values(
                isa,
                scores,
                ktp,
                &values[h * lk * head_dim..(h + 1) * lk * head_dim],
                head_dim,
                rows,
                keys,
                head_dim,
                dst,
                e,
            );
            // All-zero weights already give zeros unless v holds inf/NaN; make it exact.
            for r in (0..rows).filter(|r| dead_rows >> r & 1 == 1) {
                dst[r * e..r * e + head_dim].fill(0.0);
            }
        };

        // q·kᵀ and p·v, 2 flop per multiply-add each (causal blocks counted in full).
        let flop = 4 * lq * lk * e;
        super::profile::timed(super::profile::Kind::Attention, flop, || {
            if parallel {
                (0..tasks).into_par_iter().for_each(task);
            } else {
                (0..tasks).for_each(task);
            }
        });
    }
}

/// Multi-head attention over already-projected q, k, v.
///
/// `q` holds `lq` rows, row `i` starting at `i * q_stride`, each row `heads * head_dim` values
/// (head `h` at columns `h*head_dim..`); `k`, `v` likewise with `lk` rows and their own strides
/// (so q/k/v can be read straight out of a packed `[L, 3E]` projection). Scores are
/// `q_h · k_hᵀ / sqrt(head_dim)`; `key_padding[j] == true` excludes key `j` (weight exactly 0);
/// `causal` excludes keys `j > i`. A query row whose keys are all excluded yields zeros.
/// `out` is `[lq, heads * head_dim]`, heads concatenated in order. Allocates its buffers; a
/// caller that runs attention repeatedly keeps an [`AttentionScratch`] instead.
#[allow(clippy::too_many_arguments)]
pub fn multi_head_attention(
    q: &[f32],
    q_stride: usize,
    k: &[f32],
    k_stride: usize,
    v: &[f32],
    v_stride: usize,
    lq: usize,
    lk: usize,
    heads: usize,
    head_dim: usize,
    key_padding: Option<&[bool]>,
    causal: bool,
    out: &mut [f32],
) {
    AttentionScratch::default().attend(
        q,
        q_stride,
        k,
        k_stride,
        v,
        v_stride,
        lq,
        lk,
        heads,
        head_dim,
        key_padding,
        causal,
        out,
    );
}

/// `scores[r·kp + j] = scale · Σ_c q[r·qs + c] · kt[c·kts + j]` for `r < rows`, `j < kp`
/// (`kp ≤ kts`, a multiple of [`KT`]). Each score is one sum over `c` in order, on every path.
#[allow(clippy::too_many_arguments)]
fn scores_qk(
    isa: Isa,
    q: &[f32],
    qs: usize,
    kt: &[f32],
    kts: usize,
    kp: usize,
    rows: usize,
    hd: usize,
    scale: f32,
    scores: &mut [f32],
) {
    assert!(kp <= kts && kp.is_multiple_of(KT));
    assert!(hd == 0 || kt.len() >= (hd - 1) * kts + kp);
    assert!(scores.len() >= rows * kp);
    assert!(rows == 0 || q.len() >= (rows - 1) * qs + hd);
    #[cfg(target_arch = "x86_64")]
    match isa {
        // SAFETY: the CPU has AVX-512F (detected); bounds asserted above.
        Isa::Avx512 => {
            return unsafe { avx512::scores_qk(q, qs, kt, kts, kp, rows, hd, scale, scores) }
        }
        // SAFETY: the CPU has AVX2 and FMA (detected); bounds asserted above.
        Isa::Avx2 => {
            return unsafe { avx2::scores_qk(q, qs, kt, kts, kp, rows, hd, scale, scores) }
        }
        Isa::Portable => {}
    }
    let _ = isa;
    for r in 0..rows {
        let qr = &q[r * qs..r * qs + hd];
        let row = &mut scores[r * kp..(r + 1) * kp];
        row.fill(0.0);
        for (c, &a) in qr.iter().enumerate() {
            for (s, &b) in row.iter_mut().zip(&kt[c * kts..c * kts + kp]) {
                *s += a * b;
            }
        }
        for s in row.iter_mut() {
            *s *= scale;
        }
    }
}

/// `out[r·os + c] = Σ_{j<keys} p[r·kp + j] · v[j·vs + c]` for `r < rows`, `c < hd`, each a sum
/// over `j` in order.
#[allow(clippy::too_many_arguments)]
fn weighted_values(
    isa: Isa,
    p: &[f32],
    kp: usize,
    v: &[f32],
    vs: usize,
    rows: usize,
    keys: usize,
    hd: usize,
    out: &mut [f32],
    os: usize,
) {
    assert!(keys <= kp && (rows == 0 || p.len() >= (rows - 1) * kp + keys));
    assert!(keys == 0 || v.len() >= (keys - 1) * vs + hd);
    assert!(rows == 0 || out.len() >= (rows - 1) * os + hd);
    #[cfg(target_arch = "x86_64")]
    match isa {
        // SAFETY: the CPU has AVX-512F (detected); bounds asserted above.
        Isa::Avx512 => {
            return unsafe { avx512::weighted_values(p, kp, v, vs, rows, keys, hd, out, os) }
        }
        // SAFETY: the CPU has AVX2 and FMA (detected); bounds asserted above.
        Isa::Avx2 => {
            return unsafe { avx2::weighted_values(p, kp, v, vs, rows, keys, hd, out, os) }
        }
        Isa::Portable => {}
    }
    let _ = isa;
    for r in 0..rows {
        let o = &mut out[r * os..r * os + hd];
        o.fill(0.0);
        for j in 0..keys {
            let w = p[r * kp + j];
            for (x, &b) in o.iter_mut().zip(&v[j * vs..j * vs + hd]) {
                *x += w * b;
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;

    use super::{KT, RT};

    /// See [`super::scores_qk`]; tiles of `R` rows × 16 keys.
    #[target_feature(enable = "avx2,fma")]
    #[allow(clippy::too_many_arguments)]
    pub(super) unsafe fn scores_qk(
        q: &[f32],
        qs: usize,
        kt: &[f32],
        kts: usize,
        kp: usize,
        rows: usize,
        hd: usize,
        scale: f32,
        scores: &mut [f32],
    ) {
        let mut r = 0;
        while r < rows {
            let n = RT.min(rows - r);
            for j in (0..kp).step_by(KT) {
                match n {
                    4 => qk_tile::<4>(q, qs, kt, kts, kp, r, j, hd, scale, scores),
                    3 => qk_tile::<3>(q, qs, kt, kts, kp, r, j, hd, scale, scores),
                    2 => qk_tile::<2>(q, qs, kt, kts, kp, r, j, hd, scale, scores),
                    _ => qk_tile::<1>(q, qs, kt, kts, kp, r, j, hd, scale, scores),
                }
            }
            r += n;
        }
    }

    #[target_feature(enable = "avx2,fma")]
    #[allow(clippy::too_many_arguments)]
    #[inline]
    unsafe fn qk_tile<const R: usize>(
        q: &[f32],
        qs: usize,
        kt: &[f32],
        kts: usize,
        kp: usize,
        r0: usize,
        j: usize,
        hd: usize,
        scale: f32,
        scores: &mut [f32],
    ) {
        let mut acc = [[_mm256_setzero_ps(); 2]; R];
        let (qp, kp_ptr) = (q.as_ptr(), kt.as_ptr());
        for c in 0..hd {
            let b = kp_ptr.add(c * kts + j);
            let (b0, b1) = (_mm256_loadu_ps(b), _mm256_loadu_ps(b.add(8)));
            for (i, a) in acc.iter_mut().enumerate() {
                let x = _mm256_broadcast_ss(&*qp.add((r0 + i) * qs + c));
                a[0] = _mm256_fmadd_ps(x, b0, a[0]);
                a[1] = _mm256_fmadd_ps(x, b1, a[1]);
            }
        }
        let s = _mm256_set1_ps(scale);
        for (i, a) in acc.iter().enumerate() {
            let dst = scores.as_mut_ptr().add((r0 + i) * kp + j);
            _mm256_storeu_ps(dst, _mm256_mul_ps(a[0], s));
            _mm256_storeu_ps(dst.add(8), _mm256_mul_ps(a[1], s));
        }
    }

    /// See [`super::weighted_values`]; tiles of `R` rows × 16 columns, the last columns
    /// (`hd % 16`) by 8-wide then scalar steps.
    #[target_feature(enable = "avx2,fma")]
    #[allow(clippy::too_many_arguments)]
    pub(super) unsafe fn weighted_values(
        p: &[f32],
        kp: usize,
        v: &[f32],
        vs: usize,
        rows: usize,
        keys: usize,
        hd: usize,
        out: &mut [f32],
        os: usize,
    ) {
        let mut r = 0;
        while r < rows {
            let n = RT.min(rows - r);
            match n {
                4 => pv_rows::<4>(p, kp, v, vs, r, keys, hd, out, os),
                3 => pv_rows::<3>(p, kp, v, vs, r, keys, hd, out, os),
                2 => pv_rows::<2>(p, kp, v, vs, r, keys, hd, out, os),
                _ => pv_rows::<1>(p, kp, v, vs, r, keys, hd, out, os),
            }
            r += n;
        }
    }

    #[target_feature(enable = "avx2,fma")]
    #[allow(clippy::too_many_arguments)]
    #[inline]
    unsafe fn pv_rows<const R: usize>(
        p: &[f32],
        kp: usize,
        v: &[f32],
        vs: usize,
        r0: usize,
        keys: usize,
        hd: usize,
        out: &mut [f32],
        os: usize,
    ) {
        let (pp, vp, op) = (p.as_ptr(), v.as_ptr(), out.as_mut_ptr());
        let mut c = 0;
        while c + 16 <= hd {
            let mut acc = [[_mm256_setzero_ps(); 2]; R];
            for j in 0..keys {
                let b = vp.add(j * vs + c);
                let (b0, b1) = (_mm256_loadu_ps(b), _mm256_loadu_ps(b.add(8)));
                for (i, a) in acc.iter_mut().enumerate() {
                    let x = _mm256_broadcast_ss(&*pp.add((r0 + i) * kp + j));
                    a[0] = _mm256_fmadd_ps(x, b0, a[0]);
                    a[1] = _mm256_fmadd_ps(x, b1, a[1]);
                }
            }
            for (i, a) in acc.iter().enumerate() {
                let dst = op.add((r0 + i) * os + c);
                _mm256_storeu_ps(dst, a[0]);
                _mm256_storeu_ps(dst.add(8), a[1]);
            }
            c += 16;
        }
        while c + 8 <= hd {
            let mut acc = [_mm256_setzero_ps(); R];
            for j in 0..keys {
                let b0 = _mm256_loadu_ps(vp.add(j * vs + c));
                for (i, a) in acc.iter_mut().enumerate() {
                    let x = _mm256_broadcast_ss(&*pp.add((r0 + i) * kp + j));
                    *a = _mm256_fmadd_ps(x, b0, *a);
                }
            }
            for (i, a) in acc.iter().enumerate() {
                _mm256_storeu_ps(op.add((r0 + i) * os + c), *a);
            }
            c += 8;
        }
        for c in c..hd {
            for i in 0..R {
                let mut s = 0.0f32;
                for j in 0..keys {
                    s = (*pp.add((r0 + i) * kp + j)).mul_add(*vp.add(j * vs + c), s);
                }
                *op.add((r0 + i) * os + c) = s;
            }
        }
    }
}

/// The AVX-512 tiles: the same sums in the same order (one FMA per term, from zero) as the
/// AVX2 ones, so the two paths give the same bits; wider tiles need fewer loads per FMA.
#[cfg(target_arch = "x86_64")]
mod avx512 {
    use std::arch::x86_64::*;

    use super::KT;

    /// Query rows per `q·kᵀ` tile (two 16-key vectors per row: 16 accumulators).
    const QR: usize = 8;
    /// Query rows per `p·v` tile (up to four 16-column vectors per row: 24 accumulators).
    const PR: usize = 6;

    /// See [`super::scores_qk`]; tiles of up to 8 rows × 32 keys (16 on the last odd tile).
    #[target_feature(enable = "avx512f,avx2,fma")]
    #[allow(clippy::too_many_arguments)]
    pub(super) unsafe fn scores_qk(
        q: &[f32],
        qs: usize,
        kt: &[f32],
        kts: usize,
        kp: usize,
        rows: usize,
        hd: usize,
        scale: f32,
        scores: &mut [f32],
    ) {
        let mut r = 0;
        while r < rows {
            let n = QR.min(rows - r);
            let mut j = 0;
            while j < kp {
                let two = j + 2 * KT <= kp;
                macro_rules! tile {
                    ($($n:literal)*) => {
                        match (n, two) {
                            $(($n, true) => qk_tile::<$n, 2>(q, qs, kt, kts, kp, r, j, hd, scale, scores),
                              ($n, false) => qk_tile::<$n, 1>(q, qs, kt, kts, kp, r, j, hd, scale, scores),)*
                            _ => unreachable!(),
                        }
                    };
                }
                tile!(1 2 3 4 5 6 7 8);
                j += if two { 2 * KT } else { KT };
            }
            r += n;
        }
    }

    #[target_feature(enable = "avx512f,avx2,fma")]
    #[allow(clippy::too_many_arguments)]
    #[inline]
    unsafe fn qk_tile<const R: usize, const V: usize>(
        q: &[f32],
        qs: usize,
        kt: &[f32],
        kts: usize,
        kp: usize,
        r0: usize,
        j: usize,
        hd: usize,
        scale: f32,
        scores: &mut [f32],
    ) {
        let mut acc = [[_mm512_setzero_ps(); V]; R];
        let (qp, kp_ptr) = (q.as_ptr(), kt.as_ptr());
        for c in 0..hd {
            let b = kp_ptr.add(c * kts + j);
            let mut bv = [_mm512_setzero_ps(); V];
            for (v, x) in bv.iter_mut().enumerate() {
                *x = _mm512_loadu_ps(b.add(16 * v));
            }
            for (i, a) in acc.iter_mut().enumerate() {
                let x = _mm512_set1_ps(*qp.add((r0 + i) * qs + c));
                for v in 0..V {
                    a[v] = _mm512_fmadd_ps(x, bv[v], a[v]);
                }
            }
        }
        let s = _mm512_set1_ps(scale);
        for (i, a) in acc.iter().enumerate() {
            let dst = scores.as_mut_ptr().add((r0 + i) * kp + j);
            for (v, x) in a.iter().enumerate() {
                _mm512_storeu_ps(dst.add(16 * v), _mm512_mul_ps(*x, s));
            }
        }
    }

    /// See [`super::weighted_values`]; tiles of up to 6 rows × 64 columns, the last vector of
    /// a row masked when `hd` is not a multiple of 16.
    #[target_feature(enable = "avx512f,avx2,fma")]
    #[allow(clippy::too_many_arguments)]
    pub(super) unsafe fn weighted_values(
        p: &[f32],
        kp: usize,
        v: &[f32],
        vs: usize,
        rows: usize,
        keys: usize,
        hd: usize,
        out: &mut [f32],
        os: usize,
    ) {
        let mut r = 0;
        while r < rows {
            let n = PR.min(rows - r);
            let mut c = 0;
            while c < hd {
                let cols = (hd - c).min(64);
                let vecs = cols.div_ceil(16);
                // Lanes of the last vector that are columns (all 16 unless `hd % 16` cuts it).
                let last: __mmask16 = ((1u32 << (cols - 16 * (vecs - 1))) - 1) as u16;
                macro_rules! tile {
                    ($($n:literal)*) => {
                        match (n, vecs) {
                            $(($n, 4) => pv_tile::<$n, 4>(p, kp, v, vs, r, keys, c, last, out, os),
                              ($n, 3) => pv_tile::<$n, 3>(p, kp, v, vs, r, keys, c, last, out, os),
                              ($n, 2) => pv_tile::<$n, 2>(p, kp, v, vs, r, keys, c, last, out, os),
                              ($n, _) => pv_tile::<$n, 1>(p, kp, v, vs, r, keys, c, last, out, os),)*
                            _ => unreachable!(),
                        }
                    };
                }
                tile!(1 2 3 4 5 6);
                c += cols;
            }
            r += n;
        }
    }

    #[target_feature(enable = "avx512f,avx2,fma")]
    #[allow(clippy::too_many_arguments)]
    #[inline]
    unsafe fn pv_tile<const R: usize, const V: usize>(
        p: &[f32],
        kp: usize,
        v: &[f32],
        vs: usize,
        r0: usize,
        keys: usize,
        c0: usize,
        last: __mmask16,
        out: &mut [f32],
        os: usize,
    ) {
        let (pp, vp, op) = (p.as_ptr(), v.as_ptr(), out.as_mut_ptr());
        let mut acc = [[_mm512_setzero_ps(); V]; R];
        for j in 0..keys {
            let b = vp.add(j * vs + c0);
            let mut bv = [_mm512_setzero_ps(); V];
            for (k, x) in bv.iter_mut().enumerate() {
                // The masked lanes past `hd` read nothing (masked loads do not fault).
                let m = if k + 1 == V { last } else { 0xffff };
                *x = _mm512_maskz_loadu_ps(m, b.add(16 * k));
            }
            for (i, a) in acc.iter_mut().enumerate() {
                let x = _mm512_set1_ps(*pp.add((r0 + i) * kp + j));
                for k in 0..V {
                    a[k] = _mm512_fmadd_ps(x, bv[k], a[k]);
                }
            }
        }
        for (i, a) in acc.iter().enumerate() {
            let dst = op.add((r0 + i) * os + c0);
            for (k, x) in a.iter().enumerate() {
                let m = if k + 1 == V { last } else { 0xffff };
                _mm512_mask_storeu_ps(dst.add(16 * k), m, *x);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::{in_pool, isas, same_bits, Rng};

    /// Both products on every kernel path the CPU runs, at tile edges of each path (rows around
    /// 4, 6 and 8, keys at one and two 16-key vectors, head widths around 8, 16 and 64): the
    /// AVX2 and AVX-512 tiles give the same bits (one FMA per term, in order, from zero); all
    /// are within rounding of f64 sums.
    #[test]
    fn products_agree_on_every_kernel_path() {
        let mut rng = Rng::new(16);
        let paths = isas();
        for (rows, keys, hd) in [
            (1usize, 1usize, 1usize),
            (5, 16, 8),
            (7, 17, 16),
            (9, 33, 17),
            (13, 48, 64),
            (32, 80, 96),
            (14, 31, 100),
            (6, 64, 128),
            (3, 5, 130),
        ] {
            let kp = keys.div_ceil(KT) * KT;
            let (qs, vs, os) = (hd + 3, hd + 5, hd + 2);
            let q = rng.vec(rows * qs);
            let mut kt = rng.vec(hd * kp);
            for c in 0..hd {
                kt[c * kp + keys..(c + 1) * kp].fill(0.0);
            }
            let v = rng.vec(keys * vs);
            let p: Vec<f32> = rng.vec(rows * kp).iter().map(|x| x.abs()).collect();
            let mut results = Vec::new();
            for &isa in &paths {
                let mut scores = vec![f32::NAN; rows * kp];
                scores_qk(isa, &q, qs, &kt, kp, kp, rows, hd, 0.3, &mut scores);
                let mut out = vec![f32::NAN; rows * os];
                weighted_values(isa, &p, kp, &v, vs, rows, keys, hd, &mut out, os);
                for r in 0..rows {
                    for j in 0..keys {
                        let want: f64 = (0..hd)
                            .map(|c| q[r * qs + c] as f64 * kt[c * kp + j] as f64)
                            .sum::<f64>()
                            * 0.3;
                        let got = scores[r * kp + j] as f64;
                        assert!((got - want).abs() < 1e-5 * (1.0 + want.abs()), "{isa:?} qk");
                    }
                    for c in 0..hd {
                        let want: f64 = (0..keys)
                            .map(|j| p[r * kp + j] as f64 * v[j * vs + c] as f64)
                            .sum();
                        let got = out[r * os + c] as f64;
                        assert!((got - want).abs() < 1e-5 * (1.0 + want.abs()), "{isa:?} pv");
                    }
                    // Columns between rows' outputs are not written.
                    assert!(out[r * os + hd..(r + 1) * os].iter().all(|x| x.is_nan()));
                }
                results.push((isa, scores, out));
            }
            let simd: Vec<_> = results.iter().filter(|(i, ..)| i.has_avx2()).collect();
            for w in simd.windows(2) {
                let what = format!("{:?} vs {:?}, {rows}x{keys}x{hd}", w[0].0, w[1].0);
                assert!(same_bits(&w[0].1, &w[1].1), "scores {what}");
                assert!(same_bits(&w[0].2, &w[1].2), "values {what}");
            }
        }
    }

    /// Naive f64 attention; returns `[lq, heads*head_dim]`.
    #[allow(clippy::too_many_arguments)]
    fn naive(
        q: &[f32],
        qs: usize,
        k: &[f32],
        ks: usize,
        v: &[f32],
        vs: usize,
        lq: usize,
        lk: usize,
        heads: usize,
        hd: usize,
        pad: Option<&[bool]>,
        causal: bool,
    ) -> Vec<f64> {
        let e = heads * hd;
        let mut out = vec![0.0; lq * e];
        for h in 0..heads {
            for i in 0..lq {
                let visible: Vec<usize> = (0..lk)
                    .filter(|&j| !(pad.is_some_and(|p| p[j]) || (causal && j > i)))
                    .collect();
                if visible.is_empty() {
                    continue;
                }
                let s: Vec<f64> = visible
                    .iter()
                    .map(|&j| {
                        (0..hd)
                            .map(|d| q[i * qs + h * hd + d] as f64 * k[j * ks + h * hd + d] as f64)
                            .sum::<f64>()
                            / (hd as f64).sqrt()
                    })
                    .collect();
                let max = s.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                let w: Vec<f64> = s.iter().map(|x| (x - max).exp()).collect();
                let sum: f64 = w.iter().sum();
                for d in 0..hd {
                    out[i * e + h * hd + d] = visible
                        .iter()
                        .zip(&w)
                        .map(|(&j, &wj)| wj / sum * v[j * vs + h * hd + d] as f64)
                        .sum();
                }
            }
        }
        out
    }

    fn assert_close(got: &[f32], want: &[f64], what: &str) {
        assert_eq!(got.len(), want.len());
        for (i, (&g, &w)) in got.iter().zip(want).enumerate() {
            assert!(
                (g as f64 - w).abs() <= 2e-6 * (1.0 + w.abs()),
                "{what}[{i}]: {g} vs {w}"
            );
        }
    }

    /// Separate contiguous q, k, v; scaled so softmax is far from uniform.
    fn qkv(rng: &mut Rng, lq: usize, lk: usize, e: usize) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let q = rng.vec(lq * e).iter().map(|x| x * 3.0).collect();
        (q, rng.vec(lk * e), rng.vec(lk * e))
    }

    #[test]
    fn plain_cross_attention() {
        let mut rng = Rng::new(10);
        for (lq, lk, heads, hd) in [
            (1, 1, 1, 1),
            (5, 7, 3, 4),
            (1, 77, 8, 64),
            (70, 3, 2, 5),
            (197, 50, 4, 16),
        ] {
            let e = heads * hd;
            let (q, k, v) = qkv(&mut rng, lq, lk, e);
            let mut out = vec![f32::NAN; lq * e];
            multi_head_attention(
                &q, e, &k, e, &v, e, lq, lk, heads, hd, None, false, &mut out,
            );
            let want = naive(&q, e, &k, e, &v, e, lq, lk, heads, hd, None, false);
            assert_close(&out, &want, &format!("cross {lq}x{lk} h{heads} d{hd}"));
        }
    }

    #[test]
    fn packed_qkv_with_key_padding() {
        let mut rng = Rng::new(11);
        let (l, heads, hd) = (37, 2, 5);
        let e = heads * hd;
        let mut packed = rng.vec(l * 3 * e);
        let pad: Vec<bool> = (0..l).map(|j| j % 5 == 2 || j >= 33).collect();
        // Padded keys/values hold huge numbers: any nonzero weight on them would show.
        for j in (0..l).filter(|&j| pad[j]) {
            packed[j * 3 * e + e..j * 3 * e + 3 * e].fill(1e30);
        }
        let (q, k, v) = (&packed[..], &packed[e..], &packed[2 * e..]);
        let s = 3 * e;
        let mut out = vec![f32::NAN; l * e];
        multi_head_attention(
            q,
            s,
            k,
            s,
            v,
            s,
            l,
            l,
            heads,
            hd,
            Some(&pad),
            false,
            &mut out,
        );
        assert_close(
            &out,
            &naive(q, s, k, s, v, s, l, l, heads, hd, Some(&pad), false),
            "packed+pad",
        );
    }

    #[test]
    fn causal_self_attention() {
        let mut rng = Rng::new(12);
        for (l, heads, hd) in [(1, 1, 3), (70, 4, 8), (33, 3, 1)] {
            let e = heads * hd;
            let (q, k, v) = qkv(&mut rng, l, l, e);
            let mut out = vec![f32::NAN; l * e];
            multi_head_attention(&q, e, &k, e, &v, e, l, l, heads, hd, None, true, &mut out);
            let want = naive(&q, e, &k, e, &v, e, l, l, heads, hd, None, true);
            assert_close(&out, &want, &format!("causal {l} h{heads} d{hd}"));
            // Row 0 sees only key 0: exactly v[0].
            assert_eq!(&out[..e], &v[..e]);
        }
    }

    #[test]
    fn causal_with_more_queries_than_keys() {
        let mut rng = Rng::new(13);
        let (lq, lk, heads, hd) = (45, 20, 2, 3);
        let e = heads * hd;
        let (q, k, v) = qkv(&mut rng, lq, lk, e);
        let mut out = vec![f32::NAN; lq * e];
        multi_head_attention(&q, e, &k, e, &v, e, lq, lk, heads, hd, None, true, &mut out);
        assert_close(
            &out,
            &naive(&q, e, &k, e, &v, e, lq, lk, heads, hd, None, true),
            "causal lq>lk",
        );
    }

    #[test]
    fn fully_masked_rows_are_zero() {
        let mut rng = Rng::new(14);
        let (l, heads, hd) = (40, 2, 4);
        let e = heads * hd;
        let (q, k, v) = qkv(&mut rng, l, l, e);
        // Key 0 padded: under causal masking query 0 has nothing left to attend to.
        let pad: Vec<bool> = (0..l).map(|j| j == 0 || j == 7).collect();
        let mut out = vec![f32::NAN; l * e];
        multi_head_attention(
            &q,
            e,
            &k,
            e,
            &v,
            e,
            l,
            l,
            heads,
            hd,
            Some(&pad),
            true,
            &mut out,
        );
        assert_eq!(&out[..e], &vec![0.0; e][..]);
        assert_close(
            &out,
            &naive(&q, e, &k, e, &v, e, l, l, heads, hd, Some(&pad), true),
            "masked row",
        );

        let all = vec![true; l];
        multi_head_attention(
            &q,
            e,
            &k,
            e,
            &v,
            e,
            l,
            l,
            heads,
            hd,
            Some(&all),
            false,
            &mut out,
        );
        assert!(out.iter().all(|&x| x == 0.0));

        let mut out = vec![f32::NAN; 3 * e];
        multi_head_attention(
            &q,
            e,
            &[],
            e,
            &[],
            e,
            3,
            0,
            heads,
            hd,
            None,
            false,
            &mut out,
        );
        assert!(out.iter().all(|&x| x == 0.0));
    }

    #[test]
    fn bit_identical_across_thread_counts() {
        let mut rng = Rng::new(15);
        let (l, heads, hd) = (203, 4, 64);
        let e = heads * hd;
        let packed = rng.vec(l * 3 * e);
        let pad: Vec<bool> = (0..l).map(|j| j > 190).collect();
        let s = 3 * e;
        for causal in [false, true] {
            let run = |t| {
                in_pool(t, || {
                    let mut out = vec![0.0; l * e];
                    let (q, k, v) = (&packed[..], &packed[e..], &packed[2 * e..]);
                    multi_head_attention(
                        q,
                        s,
                        k,
                        s,
                        v,
                        s,
                        l,
                        l,
                        heads,
                        hd,
                        Some(&pad),
                        causal,
                        &mut out,
                    );
                    out
                })
            };
            let base = run(1);
            assert!(
                same_bits(&base, &run(2)) && same_bits(&base, &run(3)),
                "causal={causal}"
            );
        }
    }
}
