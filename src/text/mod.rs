//! Text encoders: turn a prompt into the token states and pooled vector a denoiser conditions on.
//!
//! - [`tokenizer`]: tokenizer.json (WordPiece, byte-level BPE) → ids + attention mask.
//! - [`bert`]: the BERT/RoBERTa encoder (FLAME's RoBERTa, sentence-transformers' MiniLM) and
//!   mean pooling.
//!
//! CLIP's text tower will be added later as its own file. The encoders only read weights and
//! run kernels; which encoder a model uses is the model file's configuration's business.

pub mod bert;
pub mod tokenizer;

pub use bert::{roberta_position_ids, EncoderKind, TextEncoder, TextOutput};
pub use tokenizer::{TextTokenizer, Tokens};
