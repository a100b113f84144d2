//! The layers both text encoders are built from, as read from a model file: stacked `Linear`s
//! on packed weights and `LayerNorm` parameters.

use crate::checkpoint::{ModelFile, Tensor};
use crate::error::Result;
use crate::kernels::{layer_norm, Activation, PackedLinear, WeightType};

/// Linear layers in PyTorch layout (`weight [out, in]`) sharing an input, stacked into one
/// packed GEMM whose outputs sit side by side (one layer, or q|k|v); biases all or none.
pub(super) struct Dense(PackedLinear);

impl Dense {
    pub(super) fn load(
        file: &ModelFile,
        names: &[&str],
        n_in: usize,
        n_out: usize,
        bias: bool,
        ty: WeightType,
    ) -> Result<Dense> {
        let (mut w, mut b) = (Vec::new(), Vec::new());
        for name in names {
            w.extend_from_slice(
                file.tensor(&format!("{name}.weight"), &[n_out, n_in])?
                    .data(),
            );
            file.release(&format!("{name}.weight"));
            if bias {
                b.extend_from_slice(file.tensor(&format!("{name}.bias"), &[n_out])?.data());
            }
        }
        let n = names.len() * n_out;
        let b = bias.then_some(&b[..]);
        Ok(Dense(PackedLinear::new(&w, b, n_in, n, ty)))
    }

    /// `act(x [rows, n_in] · Wᵀ + b)` → `[rows, n_out]`.
    pub(super) fn apply(&self, x: &[f32], rows: usize, act: Activation) -> Vec<f32> {
        let mut y = vec![0f32; rows * self.0.outputs()];
        self.0.forward(x, rows, &mut y, act);
        y
    }

    pub(super) fn weight_bytes(&self) -> usize {
        self.0.weights().bytes()
    }
}

/// `LayerNorm` parameters.
pub(super) struct Norm {
    pub(super) gamma: Tensor,
    pub(super) beta: Tensor,
}

impl Norm {
    pub(super) fn load(file: &ModelFile, name: &str, dim: usize) -> Result<Norm> {
        let gamma = file.tensor(&format!("{name}.weight"), &[dim])?;
        let beta = file.tensor(&format!("{name}.bias"), &[dim])?;
        Ok(Norm { gamma, beta })
    }

    /// A normalised copy of `x`.
    pub(super) fn apply(&self, x: &[f32], dim: usize, eps: f32) -> Vec<f32> {
        let mut y = x.to_vec();
        layer_norm(&mut y, dim, self.gamma.data(), self.beta.data(), eps);
        y
    }
}
