//! What a quantiser needs to know about the activations each linear layer of a model sees:
//! the Gram matrix `Σ xᵀx` of its inputs over calibration runs (GPTQ's Hessian, `H = 2XᵀX`,
//! Frantar et al. 2022, "GPTQ", section 3), recorded while the f32 model samples its own
//! prompts. Used only by [`crate::quantize`]; a model loaded without a recorder pays one branch
//! per layer call.
//!
//! Layers attach themselves at load: [`record_while`] installs a recorder on the loading
//! thread, and every linear layer loaded in it registers the weight rows it was built from.
//! (A thread-local rather than a load option, so that the families' loaders keep their one
//! signature.)

use std::cell::RefCell;
use std::ops::Range;
use std::sync::{Arc, Mutex};

use super::layers::transpose;
use crate::kernels;

/// One linear layer as loaded: which rows of which stored weight it holds, and its inputs.
#[derive(Debug)]
pub struct RecordedLayer {
    /// The stored weight tensor (`x.weight`, `x.in_proj_weight`).
    pub tensor: String,
    /// The rows of that tensor this layer multiplies by (a packed q/k/v split takes part).
    pub rows: Range<usize>,
    /// Input features.
    pub inputs: usize,
    /// `Σ xᵀx` over every input row seen (`inputs × inputs`, row-major).
    pub gram: Vec<f64>,
    /// Largest `|x|` per input feature.
    pub abs_max: Vec<f32>,
    /// Input rows seen.
    pub rows_seen: usize,
}

/// The layers of one model and their recorded inputs.
#[derive(Debug, Default)]
pub struct Recorder {
    layers: Mutex<Vec<RecordedLayer>>,
}

impl Recorder {
    /// The layers in load order (the recorder keeps recording while the model lives).
    pub fn take(&self) -> Vec<RecordedLayer> {
        std::mem::take(&mut *self.layers.lock().unwrap_or_else(|e| e.into_inner()))
    }

    fn register(&self, tensor: &str, rows: Range<usize>, inputs: usize) -> usize {
        let mut layers = self.layers.lock().unwrap_or_else(|e| e.into_inner());
        layers.push(RecordedLayer {
            tensor: tensor.to_string(),
            rows,
            inputs,
            gram: vec![0.0; inputs * inputs],
            abs_max: vec![0.0; inputs],
            rows_seen: 0,
        });
        layers.len() - 1
    }

    fn record(&self, index: usize, x: &[f32], rows: usize) {
        let k = {
            let layers = self.layers.lock().unwrap_or_else(|e| e.into_inner());
            layers[index].inputs
        };
        let x = &x[..rows * k];
        // Xᵀ·X in f32 by the GEMM (one call's rows: at most a few hundred products per sum),
        // accumulated over calls in f64.
        let xt = transpose(x, rows, k);
        let mut g = vec![0.0f32; k * k];
        kernels::matmul_nt(&xt, &xt, &mut g, k, rows, k);
        let mut layers = self.layers.lock().unwrap_or_else(|e| e.into_inner());
        let layer = &mut layers[index];
        for (acc, v) in layer.gram.iter_mut().zip(&g) {
            *acc += *v as f64;
        }
        for row in x.chunks_exact(k) {
            for (m, v) in layer.abs_max.iter_mut().zip(row) {
                *m = m.max(v.abs());
            }
        }
        layer.rows_seen += rows;
    }
}

thread_local! {
    static LOADING: RefCell<Option<Arc<Recorder>>> = const { RefCell::new(None) };
}

/// Runs `load` with `recorder` attached to every linear layer it loads on this thread.
pub fn record_while<R>(recorder: &Arc<Recorder>, load: impl FnOnce() -> R) -> R {
    let before = LOADING.with(|l| l.replace(Some(Arc::clone(recorder))));
    let out = load();
    LOADING.with(|l| *l.borrow_mut() = before);
    out
}

/// A layer's link to its recorder.
pub(crate) struct Probe {
    recorder: Arc<Recorder>,
    index: usize,
}

impl Probe {
    /// The probe of a layer being loaded now (none outside [`record_while`]).
    pub(crate) fn attach(tensor: &str, rows: Range<usize>, inputs: usize) -> Option<Probe> {
        LOADING.with(|l| {
            l.borrow().as_ref().map(|r| Probe {
                recorder: Arc::clone(r),
                index: r.register(tensor, rows, inputs),
            })
        })
    }

    pub(crate) fn record(&self, x: &[f32], rows: usize) {
        self.recorder.record(self.index, x, rows);
    }
}
