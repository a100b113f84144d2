//! Text encoders: turn a prompt into the token states and pooled vector a denoiser conditions on.
//!
//! - [`tokenizer`]: tokenizer.json (WordPiece, byte-level BPE) → ids + attention mask.
//! - [`bert`]: the BERT/RoBERTa encoder (FLAME's RoBERTa, sentence-transformers' MiniLM) and
//!   mean pooling.
//! - [`clip`]: the CLIP text tower (MDM, Motion Flow Matching) with OpenAI's truncation.
//! - [`t5`]: the T5 v1.0 encoder with sentence-transformers' head (sentence-t5: MotionLCM).
//!
//! The encoders only read weights and
//! run kernels; which encoder a model uses is the model file's configuration's business.
//!
//! [`tokenizer`]: crate::text::tokenizer
//! [`bert`]: crate::text::bert
//! [`clip`]: crate::text::clip
//! [`t5`]: crate::text::t5

pub mod bert;
pub mod clip;
mod layers;
pub mod t5;
pub mod tokenizer;

pub use bert::{roberta_position_ids, EncoderKind, TextEncoder, TextOutput};
pub use clip::{ClipConfig, ClipOutput, ClipTextEncoder};
pub use tokenizer::{PromptInfo, TextTokenizer, Tokens};
