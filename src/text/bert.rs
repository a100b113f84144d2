//! The BERT-family text encoder (BERT, MiniLM, RoBERTa): embeddings, post-LN transformer layers and
//! the tanh pooler, run on the crate's kernels (Hugging Face transformers' `modeling_roberta.py`
//! and `modeling_bert.py`; docs/official/text-encoders.md#roberta-base,
//! docs/official/text-encoders.md#bert-and-all-minilm-l6-v2,
//! docs/official/flame.md#roberta-prompt-encoding).
//!
//! BERT and RoBERTa differ here only in position ids; the tensor names are Hugging Face's,
//! under a caller-given prefix. Sentence-transformers' mean pooling lives on [`TextOutput`].

use crate::checkpoint::{ModelFile, Tensor};
use crate::config::TextEncoderConfig;
use crate::error::{bad_file, invalid_arg, Result};
use crate::kernels::{
    add_layer_norm, embedding, layer_norm, multi_head_attention, tanh, Activation, WeightType,
};

use super::layers::{Dense, Norm};
use super::tokenizer::{TextTokenizer, Tokens};

/// Which position-id rule the encoder follows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EncoderKind {
    /// Positions 0..n−1.
    Bert,
    /// Positions counted over non-pad ids, offset by the pad id (see [`roberta_position_ids`]).
    Roberta,
}

/// RoBERTa's position ids: with m = (id ≠ pad), pos = cumsum(m)·m + pad, so real tokens get
/// pad+1, pad+2, … and pad tokens get `pad` (the position table's padding row).
pub fn roberta_position_ids(ids: &[u32], pad: u32) -> Vec<u32> {
    let mut count = 0u32;
    ids.iter()
        .map(|&id| {
            if id == pad {
                pad
            } else {
                count += 1;
                count + pad
            }
        })
        .collect()
}

/// Per-token hidden states of one text, with the pooler output and the mask they were run with.
#[derive(Clone, Debug)]
pub struct TextOutput {
    /// Number of tokens (padding included).
    pub len: usize,
    /// `last_hidden_state`, `[len, hidden]` row-major.
    pub hidden: Vec<f32>,
    /// `tanh(dense(hidden[0]))`, `[hidden]` (what FLAME conditions on).
    pub pooled: Vec<f32>,
    /// The attention mask, `[len]`.
    pub mask: Vec<u8>,
}

impl TextOutput {
    /// Channels per token (the length of `pooled`).
    pub fn hidden_size(&self) -> usize {
        self.pooled.len()
    }

    /// Sentence-transformers' embedding: the mean of `hidden` over mask-1 tokens (divided by
    /// max(count, 1e-9)), then divided by max(‖·‖₂, 1e-12) (sentence-transformers' `Pooling` and
    /// `Normalize`; docs/official/text-encoders.md#sentence-embedding).
    pub fn mean_pooled_normalized(&self) -> Vec<f32> {
        let e = self.hidden_size();
        let mut sum = vec![0f32; e];
        let mut count = 0f32;
        for (row, _) in self
            .hidden
            .chunks_exact(e)
            .zip(&self.mask)
            .filter(|(_, &m)| m != 0)
        {
            sum.iter_mut().zip(row).for_each(|(s, &h)| *s += h);
            count += 1.0;
        }
        let count = count.max(1e-9);
        sum.iter_mut().for_each(|s| *s /= count);
        let norm = sum.iter().map(|s| s * s).sum::<f32>().sqrt().max(1e-12);
        sum.iter_mut().for_each(|s| *s /= norm);
        sum
    }
}

/// One post-LN encoder layer.
struct Layer {
    /// query | key | value.
    qkv: Dense,
    attn_out: Dense,
    attn_norm: Norm,
    intermediate: Dense,
    output: Dense,
    out_norm: Norm,
}

/// Sizes shared by every layer.
#[derive(Clone, Copy)]
struct Dims {
    hidden: usize,
    heads: usize,
    intermediate: usize,
    eps: f32,
}

impl Layer {
    fn load(file: &ModelFile, p: &str, d: Dims, ty: WeightType) -> Result<Layer> {
        let (e, i) = (d.hidden, d.intermediate);
        let qkv = ["query", "key", "value"].map(|n| format!("{p}attention.self.{n}"));
        let qkv = qkv.each_ref().map(String::as_str);
        Ok(Layer {
            qkv: Dense::load(file, &qkv, e, e, true, ty)?,
            attn_out: Dense::load(
                file,
                &[&format!("{p}attention.output.dense")],
                e,
                e,
                true,
                ty,
            )?,
            attn_norm: Norm::load(file, &format!("{p}attention.output.LayerNorm"), e)?,
            intermediate: Dense::load(file, &[&format!("{p}intermediate.dense")], e, i, true, ty)?,
            output: Dense::load(file, &[&format!("{p}output.dense")], i, e, true, ty)?,
            out_norm: Norm::load(file, &format!("{p}output.LayerNorm"), e)?,
        })
    }

    /// a = LN(dense(attn(x)) + x); returns LN(W2·GELU(W1·a) + a).
    fn forward(&self, x: &[f32], n: usize, key_padding: Option<&[bool]>, d: Dims) -> Vec<f32> {
        let e = d.hidden;
        let qkv = self.qkv.apply(x, n, Activation::None);
        let mut ctx = vec![0f32; n * e];
        let head_dim = e / d.heads;
        multi_head_attention(
            &qkv,
            3 * e,
            &qkv[e..],
            3 * e,
            &qkv[2 * e..],
            3 * e,
            n,
            n,
            d.heads,
            head_dim,
            key_padding,
            false,
            &mut ctx,
        );
        let mut a = self.attn_out.apply(&ctx, n, Activation::None);
        add_layer_norm(
            &mut a,
            x,
            e,
            self.attn_norm.gamma.data(),
            self.attn_norm.beta.data(),
            d.eps,
        );
        let h = self.intermediate.apply(&a, n, Activation::Gelu);
        let mut out = self.output.apply(&h, n, Activation::None);
        add_layer_norm(
            &mut out,
            &a,
            e,
            self.out_norm.gamma.data(),
            self.out_norm.beta.data(),
            d.eps,
        );
        out
    }
}

/// A loaded BERT or RoBERTa encoder with its tokenizer. Immutable after load, so one instance
/// can serve many threads.
pub struct TextEncoder {
    kind: EncoderKind,
    dims: Dims,
    vocab_size: usize,
    max_positions: usize,
    pad_id: u32,
    max_length: usize,
    tokenizer: TextTokenizer,
    word: Tensor,
    position: Tensor,
    token_type: Tensor,
    emb_norm: Norm,
    layers: Vec<Layer>,
    pooler: Dense,
}

impl TextEncoder {
    /// Loads the encoder whose tensors are named `{prefix}embeddings.…`, `{prefix}encoder.layer.N.…`
    /// and `{prefix}pooler.dense.…` (prefix `"text."` in libflame files, `""` in a bare Hugging
    /// Face BertModel/RobertaModel file). Tensors are requested embeddings → layers → pooler, so
    /// a bad file's error names the first bad tensor.
    pub fn load(
        file: &ModelFile,
        prefix: &str,
        cfg: &TextEncoderConfig,
        tokenizer_json: &str,
    ) -> Result<TextEncoder> {
        TextEncoder::load_with(file, prefix, cfg, tokenizer_json, WeightType::F32)
    }

    /// [`TextEncoder::load`] with the linear weights held (and multiplied) as `ty`.
    pub fn load_with(
        file: &ModelFile,
        prefix: &str,
        cfg: &TextEncoderConfig,
        tokenizer_json: &str,
        ty: WeightType,
    ) -> Result<TextEncoder> {
        let kind = cfg.validate(file, prefix)?;
        let dims = Dims {
            hidden: cfg.hidden_size,
            heads: cfg.num_heads,
            intermediate: cfg.intermediate_size,
            eps: cfg.layer_norm_eps,
        };
        let e = dims.hidden;
        let p = prefix;
        let word = file.tensor(
            &format!("{p}embeddings.word_embeddings.weight"),
            &[cfg.vocab_size, e],
        )?;
        let position = file.tensor(
            &format!("{p}embeddings.position_embeddings.weight"),
            &[cfg.max_position_embeddings, e],
        )?;
        let token_type = file.tensor(
            &format!("{p}embeddings.token_type_embeddings.weight"),
            &[cfg.type_vocab_size, e],
        )?;
        let emb_norm = Norm::load(file, &format!("{p}embeddings.LayerNorm"), e)?;
        let layers = (0..cfg.num_layers)
            .map(|i| Layer::load(file, &format!("{p}encoder.layer.{i}."), dims, ty))
            .collect::<Result<Vec<_>>>()?;
        let pooler = Dense::load(file, &[&format!("{p}pooler.dense")], e, e, true, ty)?;
        let tokenizer = TextTokenizer::from_json(tokenizer_json, cfg.vocab_size, cfg.pad_token_id)?;
        if cfg.max_length < tokenizer.num_special_tokens() + 1 {
            return Err(bad_file!(
                "text_encoder.max_length {} leaves no room for text besides the {} special tokens",
                cfg.max_length,
                tokenizer.num_special_tokens()
            ));
        }
        Ok(TextEncoder {
            kind,
            dims,
            vocab_size: cfg.vocab_size,
            max_positions: cfg.max_position_embeddings,
            pad_id: cfg.pad_token_id,
            max_length: cfg.max_length,
            tokenizer,
            word,
            position,
            token_type,
            emb_norm,
            layers,
            pooler,
        })
    }

    /// Bytes of the packed linear weights.
    pub fn linear_weight_bytes(&self) -> usize {
        let layer = |l: &Layer| {
            [&l.qkv, &l.attn_out, &l.intermediate, &l.output]
                .iter()
                .map(|d| d.weight_bytes())
                .sum::<usize>()
        };
        self.layers.iter().map(layer).sum::<usize>() + self.pooler.weight_bytes()
    }

    /// Which position-id rule the encoder follows (BERT or RoBERTa).
    pub fn kind(&self) -> EncoderKind {
        self.kind
    }

    /// Channels per token of the encoder's output.
    pub fn hidden_size(&self) -> usize {
        self.dims.hidden
    }

    /// The configured prompt length (FLAME: 20), special tokens and padding included.
    pub fn max_length(&self) -> usize {
        self.max_length
    }

    /// The longest token sequence [`TextEncoder::encode_tokens`] accepts (the position table
    /// minus RoBERTa's pad offset).
    pub fn max_sequence_length(&self) -> usize {
        match self.kind {
            EncoderKind::Bert => self.max_positions,
            EncoderKind::Roberta => self.max_positions - self.pad_id as usize - 1,
        }
    }

    /// The tokenizer the model file carries for this encoder.
    pub fn tokenizer(&self) -> &TextTokenizer {
        &self.tokenizer
    }

    /// Tokenize (truncate to `max_length`; pad to `max_length` when `pad` is true).
    pub fn tokenize(&self, text: &str, max_length: usize, pad: bool) -> Result<Tokens> {
        self.tokenizer.encode(text, max_length, pad)
    }

    /// Per-token hidden states and pooler output for one text, FLAME semantics: padded to
    /// `cfg.max_length`, padded keys masked out.
    pub fn encode(&self, text: &str) -> Result<TextOutput> {
        let tokens = self.tokenize(text, self.max_length, true)?;
        self.encode_tokens(&tokens)
    }

    /// Runs the encoder on given tokens (any length up to [`TextEncoder::max_sequence_length`]).
    /// Keys with mask 0 get zero attention weight; their own rows are still computed, as in
    /// Hugging Face. A mask of all zeros gives zero attention output rather than HF's uniform
    /// average.
    pub fn encode_tokens(&self, tokens: &Tokens) -> Result<TextOutput> {
        let n = tokens.ids.len();
        self.check_tokens(tokens)?;
        let e = self.dims.hidden;
        let positions = match self.kind {
            EncoderKind::Bert => (0..n as u32).collect(),
            EncoderKind::Roberta => roberta_position_ids(&tokens.ids, self.pad_id),
        };
        let mut x = vec![0f32; n * e];
        embedding(self.word.data(), e, &tokens.ids, &mut x);
        let mut pos = vec![0f32; n * e];
        embedding(self.position.data(), e, &positions, &mut pos);
        let type0 = &self.token_type.data()[..e];
        for (row, prow) in x.chunks_exact_mut(e).zip(pos.chunks_exact(e)) {
            for ((v, &p), &t) in row.iter_mut().zip(prow).zip(type0) {
                *v += p + t;
            }
        }
        layer_norm(
            &mut x,
            e,
            self.emb_norm.gamma.data(),
            self.emb_norm.beta.data(),
            self.dims.eps,
        );

        let key_padding: Vec<bool> = tokens.mask.iter().map(|&m| m == 0).collect();
        let key_padding = key_padding.iter().any(|&p| p).then_some(&key_padding[..]);
        for layer in &self.layers {
            x = layer.forward(&x, n, key_padding, self.dims);
        }
        let mut pooled = self.pooler.apply(&x[..e], 1, Activation::None);
        tanh(&mut pooled);
        Ok(TextOutput {
            len: n,
            hidden: x,
            pooled,
            mask: tokens.mask.clone(),
        })
    }

    fn check_tokens(&self, tokens: &Tokens) -> Result<()> {
        let n = tokens.ids.len();
        if n == 0 {
            return Err(invalid_arg!(
                "tokens: empty sequence (at least the first special token is needed)"
            ));
        }
        if tokens.mask.len() != n {
            return Err(invalid_arg!(
                "tokens: {n} ids but {} mask values",
                tokens.mask.len()
            ));
        }
        if n > self.max_sequence_length() {
            return Err(invalid_arg!(
                "tokens: {n} tokens, more than the encoder's {} positions allow",
                self.max_sequence_length()
            ));
        }
        if let Some((i, id)) = tokens
            .ids
            .iter()
            .enumerate()
            .find(|(_, &id)| id as usize >= self.vocab_size)
        {
            return Err(invalid_arg!(
                "tokens: id {id} at index {i} is not below vocab_size {}",
                self.vocab_size
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::text::tokenizer::tests::WORDPIECE;
    use safetensors::tensor::{Dtype, TensorView};

    const _: () = {
        const fn send_sync<T: Send + Sync>() {}
        send_sync::<TextEncoder>();
    };

    #[test]
    fn roberta_positions_skip_padding() {
        assert_eq!(
            roberta_position_ids(&[0, 5, 7, 2, 1, 1], 1),
            [2, 3, 4, 5, 1, 1]
        );
        // A pad id inside the text (a literal "<pad>") is a padding position in HF too.
        assert_eq!(roberta_position_ids(&[0, 1, 7, 2], 1), [2, 1, 3, 4]);
    }

    #[test]
    fn mean_pooling_ignores_padding_and_normalises() {
        let out = TextOutput {
            len: 3,
            hidden: vec![1.0, 0.0, 3.0, 4.0, 100.0, -7.0],
            pooled: vec![0.0; 2],
            mask: vec![1, 1, 0],
        };
        let v = out.mean_pooled_normalized();
        assert!(
            (v[0] - 0.5f32.sqrt()).abs() < 1e-7 && (v[1] - 0.5f32.sqrt()).abs() < 1e-7,
            "{v:?}"
        );
        let zero = TextOutput {
            len: 1,
            hidden: vec![0.0, 0.0],
            pooled: vec![0.0; 2],
            mask: vec![0],
        };
        assert_eq!(zero.mean_pooled_normalized(), [0.0, 0.0]);
    }

    fn tiny_config() -> TextEncoderConfig {
        TextEncoderConfig {
            kind: "bert".into(),
            vocab_size: 9,
            hidden_size: 4,
            num_layers: 2,
            num_heads: 2,
            intermediate_size: 8,
            max_position_embeddings: 8,
            type_vocab_size: 2,
            layer_norm_eps: 1e-12,
            pad_token_id: 0,
            max_length: 8,
            hidden_act: "gelu".into(),
        }
    }

    /// Every tensor of the tiny config under prefix `text.`, minus `skip`, with `resize` shaped [1].
    fn tiny_file(skip: &[&str], resize: &str) -> ModelFile {
        let (e, i) = (4, 8);
        let mut shapes: Vec<(String, Vec<usize>)> = vec![
            ("embeddings.word_embeddings.weight".into(), vec![9, e]),
            ("embeddings.position_embeddings.weight".into(), vec![8, e]),
            ("embeddings.token_type_embeddings.weight".into(), vec![2, e]),
            ("embeddings.LayerNorm.weight".into(), vec![e]),
            ("embeddings.LayerNorm.bias".into(), vec![e]),
            ("pooler.dense.weight".into(), vec![e, e]),
            ("pooler.dense.bias".into(), vec![e]),
        ];
        for l in 0..2 {
            for (name, out, inp) in [
                ("attention.self.query", e, e),
                ("attention.self.key", e, e),
                ("attention.self.value", e, e),
                ("attention.output.dense", e, e),
                ("intermediate.dense", i, e),
                ("output.dense", e, i),
            ] {
                shapes.push((format!("encoder.layer.{l}.{name}.weight"), vec![out, inp]));
                shapes.push((format!("encoder.layer.{l}.{name}.bias"), vec![out]));
            }
            for name in ["attention.output.LayerNorm", "output.LayerNorm"] {
                shapes.push((format!("encoder.layer.{l}.{name}.weight"), vec![e]));
                shapes.push((format!("encoder.layer.{l}.{name}.bias"), vec![e]));
            }
        }
        let data: Vec<(String, Vec<usize>, Vec<u8>)> = shapes
            .into_iter()
            .filter(|(n, _)| !skip.contains(&n.as_str()))
            .map(|(n, s)| {
                let s = if n == resize { vec![1] } else { s };
                let bytes = vec![0u8; 4 * s.iter().product::<usize>()];
                (format!("text.{n}"), s, bytes)
            })
            .collect();
        let views: Vec<(String, TensorView)> = data
            .iter()
            .map(|(n, s, b)| {
                (
                    n.clone(),
                    TensorView::new(Dtype::F32, s.clone(), b).unwrap(),
                )
            })
            .collect();
        ModelFile::from_bytes(&safetensors::serialize(views, &None).unwrap()).unwrap()
    }

    fn load_err(file: &ModelFile, cfg: &TextEncoderConfig) -> String {
        TextEncoder::load(file, "text.", cfg, WORDPIECE)
            .err()
            .expect("load must fail")
            .to_string()
    }

    #[test]
    fn loads_a_complete_file() {
        let enc =
            TextEncoder::load(&tiny_file(&[], ""), "text.", &tiny_config(), WORDPIECE).unwrap();
        assert_eq!(
            (
                enc.hidden_size(),
                enc.max_length(),
                enc.max_sequence_length()
            ),
            (4, 8, 8)
        );
        assert_eq!(
            enc.tokenize("a person", 8, false).unwrap().ids,
            [2, 4, 5, 3]
        );
    }

    #[test]
    fn names_the_first_bad_tensor() {
        let cfg = tiny_config();
        let skip = [
            "encoder.layer.1.output.dense.bias",
            "encoder.layer.0.attention.self.key.weight",
            "pooler.dense.weight",
        ];
        assert_eq!(
            load_err(&tiny_file(&skip, ""), &cfg),
            "bad model file: tensor `text.encoder.layer.0.attention.self.key.weight` is missing"
        );
        assert_eq!(
            load_err(
                &tiny_file(&["pooler.dense.bias"], "embeddings.LayerNorm.bias"),
                &cfg
            ),
            "bad model file: tensor `text.embeddings.LayerNorm.bias` has shape [1], expected [4]"
        );
    }

    #[test]
    fn rejects_inconsistent_configs() {
        let file = tiny_file(&[], "");
        let with = |f: fn(&mut TextEncoderConfig)| {
            let mut c = tiny_config();
            f(&mut c);
            load_err(&file, &c)
        };
        assert!(with(|c| c.max_length = 9)
            .contains("max_length 9 (+0 position offset) exceeds max_position_embeddings 8"));
        let roberta = with(|c| {
            c.kind = "roberta".into();
            c.pad_token_id = 1;
            c.max_length = 7;
        });
        assert!(
            roberta.contains("max_length 7 (+2 position offset) exceeds"),
            "{roberta}"
        );
        assert!(with(|c| c.kind = "gpt".into()).contains("unknown text_encoder.kind `gpt`"));
        assert!(with(|c| c.num_heads = 3).contains("not divisible"));
        assert!(with(|c| c.hidden_act = "relu".into()).contains("hidden_act `relu`"));
        assert!(with(|c| c.max_length = 2).contains("leaves no room for text"));
    }

    #[test]
    fn tokenizer_ids_must_fit_the_vocabulary() {
        let json = WORDPIECE.replace(r#"".":8}"#, r#"".":8,"run":40}"#);
        let e = TextEncoder::load(&tiny_file(&[], ""), "text.", &tiny_config(), &json)
            .err()
            .unwrap();
        assert!(matches!(e, crate::Error::BadModelFile(_)));
        assert!(
            e.to_string()
                .contains("produces id 40 (`run`) but the text encoder's vocab_size is 9"),
            "{e}"
        );
        let e = TextEncoder::load(&tiny_file(&[], ""), "text.", &tiny_config(), "{oops")
            .err()
            .unwrap();
        assert!(matches!(e, crate::Error::BadModelFile(_)), "{e}");
    }
}
