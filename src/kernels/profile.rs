//! Opt-in accounting of where a forward pass spends its time: wall time and floating-point
//! operations of the linear layers and of attention, summed over calls. Off by default; when
//! off, a kernel call pays one relaxed atomic load. `flame-bench` turns it on to report the
//! GFLOP/s reached inside the linear layers against the machine's GEMM peak.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Instant;

static ON: AtomicBool = AtomicBool::new(false);
static LINEAR_NS: AtomicU64 = AtomicU64::new(0);
static LINEAR_FLOP: AtomicU64 = AtomicU64::new(0);
static ATTENTION_NS: AtomicU64 = AtomicU64::new(0);
static ATTENTION_FLOP: AtomicU64 = AtomicU64::new(0);
static MOE_NS: AtomicU64 = AtomicU64::new(0);
static MOE_FLOP: AtomicU64 = AtomicU64::new(0);

/// Totals since the last [`take`].
#[derive(Clone, Copy, Debug, Default)]
pub struct Profile {
    /// Wall time inside the linear layers (packed GEMMs), in seconds.
    pub linear_seconds: f64,
    /// Floating-point operations of the linear layers: 2 per multiply-add (2·rows·in·out a
    /// call), bias and activation not counted.
    pub linear_flop: f64,
    /// Wall time inside attention (scores, softmax, weighted sum), in seconds.
    pub attention_seconds: f64,
    /// Floating-point operations of attention: 4·L_q·L_k·width a call (q·kᵀ and p·v, causal
    /// blocks counted in full, softmax not counted).
    pub attention_flop: f64,
    /// Mixtures of experts as a whole (gate, routing, experts, projection), their linear
    /// layers also counted in `linear_*`.
    pub moe_seconds: f64,
    /// Floating-point operations of the mixtures of experts (2 per multiply-add, counted as if
    /// no expert choice were dropped for capacity).
    pub moe_flop: f64,
}

/// Starts or stops the accounting (process-wide).
pub fn enable(on: bool) {
    ON.store(on, Ordering::Relaxed);
}

/// Returns the totals and resets them.
pub fn take() -> Profile {
    let s = |a: &AtomicU64| a.swap(0, Ordering::Relaxed) as f64;
    Profile {
        linear_seconds: s(&LINEAR_NS) * 1e-9,
        linear_flop: s(&LINEAR_FLOP),
        attention_seconds: s(&ATTENTION_NS) * 1e-9,
        attention_flop: s(&ATTENTION_FLOP),
        moe_seconds: s(&MOE_NS) * 1e-9,
        moe_flop: s(&MOE_FLOP),
    }
}

#[derive(Clone, Copy)]
pub(crate) enum Kind {
    Linear,
    Attention,
    Moe,
}

/// Runs `f`, charging its wall time and `flop` to `kind` when accounting is on (not inside
/// [`super::serial`], whose caller charges the whole: calls running at once on several threads
/// would add up their wall times).
#[inline]
pub(crate) fn timed<R>(kind: Kind, flop: usize, f: impl FnOnce() -> R) -> R {
    if !ON.load(Ordering::Relaxed) || super::in_serial() {
        return f();
    }
    let t = Instant::now();
    let r = f();
    let ns = t.elapsed().as_nanos() as u64;
    let (time, ops) = match kind {
        Kind::Linear => (&LINEAR_NS, &LINEAR_FLOP),
        Kind::Attention => (&ATTENTION_NS, &ATTENTION_FLOP),
        Kind::Moe => (&MOE_NS, &MOE_FLOP),
    };
    time.fetch_add(ns, Ordering::Relaxed);
    ops.fetch_add(flop as u64, Ordering::Relaxed);
    r
}
