//! Reverse-mode products (vector-Jacobian products) for the paths gradient-guided editing
//! differentiates: MoLA's MPGD (sony/MoLA `models/mola_module.py`;
//! docs/official/mola-mld.md#mola-mpgd-editing) moves x̂0 along
//! `−∇ Σ_{frame, joint} ‖(J(x̂0) − c) ⊙ m‖₂`, with `J` = VAE decoder → de-normalisation →
//! joint positions. There is no general autograd engine: each operation on those paths has its
//! hand-written backward here ([`ops`], [`kinematics`]) or beside its forward (the layers'
//! `backward_input`), checked against PyTorch autograd. The kernels stay free of model
//! knowledge; what a model's backward chain is, the model says.
//!
//! [`ops`]: crate::grad::ops
//! [`kinematics`]: crate::grad::kinematics

pub mod kinematics;
pub mod ops;
#[cfg(test)]
mod tests;

pub use kinematics::{positions, positions_vjp};
pub use ops::{denormalize_backward, l2_norm_sum_grad, relu_backward, upsample_nearest2_backward};
