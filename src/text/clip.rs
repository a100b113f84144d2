//! The CLIP text tower (OpenAI CLIP as MDM uses it): token + position embeddings, pre-LN
//! blocks with a causal mask and QuickGELU, the final LayerNorm, pooling at the first
//! end-of-text token and the text projection (openai/CLIP `clip/model.py`;
//! docs/official/text-encoders.md#clip-text-tower, docs/official/mdm.md#clip-prompt-encoding).
//!
//! Tensor names are Hugging Face's (`CLIPTextModelWithProjection`) under a caller-given prefix:
//! `{prefix}text_model.embeddings.…`, `{prefix}text_model.encoder.layers.N.…`,
//! `{prefix}text_model.final_layer_norm.…` and `{prefix}text_projection.weight` (`[E, W]`, the
//! transpose of OpenAI's `text_projection`).
//!
//! Tokenization runs a tokenizer.json (the Hugging Face layout of CLIP's BPE) after
//! [`clean_text`], a small subset of the official ftfy + HTML clean-up, and follows
//! `clip.tokenize(…, context_length=c, truncate=True)` padded with 0 to the full context.

use serde::Deserialize;

use crate::checkpoint::{ModelFile, Tensor};
use crate::error::{bad_file, invalid_arg, Result};
use crate::kernels::{
    add_inplace, embedding, multi_head_attention, quick_gelu, Activation, WeightType,
};

use super::layers::{Dense, Norm};
use super::tokenizer::{PromptInfo, TextTokenizer};

/// The CLIP text tower's sizes (ViT-B/32: vocab 49408, width 512, 12 layers, 8 heads,
/// MLP 2048, projection 512). Checked by [`ClipConfig::validate`] (in [`crate::config`]).
#[derive(Clone, Debug, Deserialize, PartialEq)]
pub struct ClipConfig {
    /// Tokens in the embedding table (49408 for OpenAI's BPE).
    pub vocab_size: usize,
    /// Channels of the residual stream.
    pub width: usize,
    /// Transformer blocks.
    pub layers: usize,
    /// Attention heads per block (they divide `width`).
    pub heads: usize,
    /// Channels of each block's MLP (`mlp.fc1` out); files written before it was stored have
    /// none, meaning 4 × width (OpenAI CLIP). See [`ClipConfig::mlp_size`].
    #[serde(default)]
    pub intermediate_size: Option<usize>,
    /// Positions in the table; every text is padded to this length (77).
    #[serde(default = "clip_context")]
    pub context_length: usize,
    /// Channels of the text vector the final projection gives (what the denoisers read).
    pub projection_dim: usize,
    #[serde(default = "clip_ln_eps")]
    /// Epsilon of every LayerNorm (default 1e-5, PyTorch's).
    pub layer_norm_eps: f32,
}

fn clip_context() -> usize {
    77
}

impl ClipConfig {
    /// Channels of each block's MLP: `intermediate_size`, or 4 × width when absent.
    pub fn mlp_size(&self) -> usize {
        self.intermediate_size.unwrap_or(4 * self.width)
    }
}

fn clip_ln_eps() -> f32 {
    1e-5
}

/// What [`ClipTextEncoder::encode`] computes for one text.
#[derive(Clone, Debug)]
pub struct ClipOutput {
    /// The token ids run through the tower (start, text, end, 0-padding), `[n]`.
    pub ids: Vec<u32>,
    /// `ln_final` over every position (HF `last_hidden_state`), `[n, width]` row-major.
    pub tokens: Vec<f32>,
    /// The row of `tokens` at [`ClipOutput::pooled_index`] (HF `pooler_output`), `[width]`.
    pub pooled: Vec<f32>,
    /// `pooled · text_projection` (OpenAI `encode_text`, HF `text_embeds`), `[projection_dim]`.
    pub projected: Vec<f32>,
    /// First position of the largest id (the first `<|endoftext|>`).
    pub pooled_index: usize,
}

/// One pre-LN residual block.
struct Block {
    ln1: Norm,
    /// q | k | v.
    qkv: Dense,
    out: Dense,
    ln2: Norm,
    fc1: Dense,
    fc2: Dense,
}

impl Block {
    fn load(file: &ModelFile, p: &str, w: usize, mlp: usize, ty: WeightType) -> Result<Block> {
        let qkv = ["q", "k", "v"].map(|n| format!("{p}self_attn.{n}_proj"));
        let qkv = qkv.each_ref().map(String::as_str);
        let one = |name: &str, n_in: usize, n_out: usize| {
            Dense::load(file, &[&format!("{p}{name}")], n_in, n_out, true, ty)
        };
        Ok(Block {
            ln1: Norm::load(file, &format!("{p}layer_norm1"), w)?,
            qkv: Dense::load(file, &qkv, w, w, true, ty)?,
            out: one("self_attn.out_proj", w, w)?,
            ln2: Norm::load(file, &format!("{p}layer_norm2"), w)?,
            fc1: one("mlp.fc1", w, mlp)?,
            fc2: one("mlp.fc2", mlp, w)?,
        })
    }

    /// x ← x + out(causal_attn(LN1 x)); x ← x + fc2(QuickGELU(fc1(LN2 x))).
    fn forward(&self, x: &mut [f32], n: usize, w: usize, heads: usize, eps: f32) {
        let h = self.ln1.apply(x, w, eps);
        let qkv = self.qkv.apply(&h, n, Activation::None);
        let mut ctx = vec![0f32; n * w];
        multi_head_attention(
            &qkv,
            3 * w,
            &qkv[w..],
            3 * w,
            &qkv[2 * w..],
            3 * w,
            n,
            n,
            heads,
            w / heads,
            None,
            true,
            &mut ctx,
        );
        add_inplace(x, &self.out.apply(&ctx, n, Activation::None));
        let h = self.ln2.apply(x, w, eps);
        let mut m = self.fc1.apply(&h, n, Activation::None);
        quick_gelu(&mut m);
        add_inplace(x, &self.fc2.apply(&m, n, Activation::None));
    }
}

/// A loaded CLIP text tower with its tokenizer. Immutable after load, so one instance can
/// serve many threads.
pub struct ClipTextEncoder {
    cfg: ClipConfig,
    tokenizer: TextTokenizer,
    token_embedding: Tensor,
    position_embedding: Tensor,
    blocks: Vec<Block>,
    final_norm: Norm,
    projection: Dense,
}

impl std::fmt::Debug for ClipTextEncoder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ClipTextEncoder")
            .field("cfg", &self.cfg)
            .finish_non_exhaustive()
    }
}

impl ClipTextEncoder {
    /// Loads the tower whose tensors are `{prefix}text_model.…` and
    /// `{prefix}text_projection.weight` (prefix `""` for a bare Hugging Face
    /// CLIPTextModelWithProjection file). Tensors are requested embeddings → layers → final
    /// norm → projection, so a bad file's error names the first bad tensor. The tokenizer must
    /// put exactly two special tokens around a text; padding uses id 0 (OpenAI).
    pub fn load(
        file: &ModelFile,
        prefix: &str,
        cfg: &ClipConfig,
        tokenizer_json: &str,
    ) -> Result<ClipTextEncoder> {
        ClipTextEncoder::load_with(file, prefix, cfg, tokenizer_json, WeightType::F32)
    }

    /// [`ClipTextEncoder::load`] with the linear weights held (and multiplied) as `ty`.
    pub fn load_with(
        file: &ModelFile,
        prefix: &str,
        cfg: &ClipConfig,
        tokenizer_json: &str,
        ty: WeightType,
    ) -> Result<ClipTextEncoder> {
        cfg.validate(file, prefix)?;
        let (p, w, mlp) = (prefix, cfg.width, cfg.mlp_size());
        let token_embedding = file.tensor(
            &format!("{p}text_model.embeddings.token_embedding.weight"),
            &[cfg.vocab_size, w],
        )?;
        let position_embedding = file.tensor(
            &format!("{p}text_model.embeddings.position_embedding.weight"),
            &[cfg.context_length, w],
        )?;
        let blocks = (0..cfg.layers)
            .map(|i| {
                let block = format!("{p}text_model.encoder.layers.{i}.");
                Block::load(file, &block, w, mlp, ty)
            })
            .collect::<Result<Vec<_>>>()?;
        let final_norm = Norm::load(file, &format!("{p}text_model.final_layer_norm"), w)?;
        let projection = Dense::load(
            file,
            &[&format!("{p}text_projection")],
            w,
            cfg.projection_dim,
            false,
            ty,
        )?;
        let tokenizer = TextTokenizer::from_json(tokenizer_json, cfg.vocab_size, 0)?;
        if tokenizer.num_special_tokens() != 2 {
            return Err(bad_file!(
                "the CLIP tokenizer adds {} special tokens to a text, expected 2 \
                 (<|startoftext|> … <|endoftext|>)",
                tokenizer.num_special_tokens()
            ));
        }
        Ok(ClipTextEncoder {
            cfg: cfg.clone(),
            tokenizer,
            token_embedding,
            position_embedding,
            blocks,
            final_norm,
            projection,
        })
    }

    /// Bytes of the packed linear weights.
    pub fn linear_weight_bytes(&self) -> usize {
        let block = |b: &Block| {
            [&b.qkv, &b.out, &b.fc1, &b.fc2]
                .iter()
                .map(|d| d.weight_bytes())
                .sum::<usize>()
        };
        self.blocks.iter().map(block).sum::<usize>() + self.projection.weight_bytes()
    }

    /// The sizes this tower was built with.
    pub fn config(&self) -> &ClipConfig {
        &self.cfg
    }

    /// Channels of the residual stream (per-token states).
    pub fn width(&self) -> usize {
        self.cfg.width
    }

    /// Channels of the projected text vector.
    pub fn projection_dim(&self) -> usize {
        self.cfg.projection_dim
    }

    /// The full context every text is padded to (77).
    pub fn context_length(&self) -> usize {
        self.cfg.context_length
    }

    /// `clip.tokenize(text, context_length, truncate=True)` zero-padded to the full context:
    /// start token, at most `context_length − 2` text tokens, end token (on overflow the end
    /// token takes the place of the last kept one), then 0s. `context_length` must be in
    /// `2..=` [`ClipTextEncoder::context_length`] (MDM: 22). Any text is accepted.
    pub fn tokenize(&self, text: &str, context_length: usize) -> Result<Vec<u32>> {
        self.check_context(context_length)?;
        let mut ids = self
            .tokenizer
            .encode(&clean_text(text), context_length, false)?
            .ids;
        ids.resize(self.cfg.context_length, 0);
        Ok(ids)
    }

    /// How `text` fits `context_length` tokens, cut as [`ClipTextEncoder::tokenize`] cuts it.
    pub fn fit(&self, text: &str, context_length: usize) -> Result<PromptInfo> {
        self.check_context(context_length)?;
        let mut info = self.tokenizer.fit(&clean_text(text), context_length)?;
        info.unconditional = text.trim().is_empty();
        Ok(info)
    }

    fn check_context(&self, context_length: usize) -> Result<()> {
        if context_length < 2 || context_length > self.cfg.context_length {
            return Err(invalid_arg!(
                "context_length {context_length} is not between 2 and the encoder's {}",
                self.cfg.context_length
            ));
        }
        Ok(())
    }

    /// Tokenizes `text` with [`ClipTextEncoder::tokenize`] and runs the tower.
    pub fn encode(&self, text: &str, context_length: usize) -> Result<ClipOutput> {
        let ids = self.tokenize(text, context_length)?;
        self.encode_ids(&ids)
    }

    /// [`ClipTextEncoder::encode`] through the first end token only: its `ids` and `tokens`
    /// stop at [`ClipOutput::pooled_index`], where the pooled and projected vectors are taken.
    /// The attention is causal, so these rows do not depend on the padding after them and are
    /// the same, bit for bit, as `encode`'s first rows, at a fraction of the cost (a 10-token
    /// prompt runs 12 positions instead of 77).
    pub fn encode_through_end(&self, text: &str, context_length: usize) -> Result<ClipOutput> {
        let ids = self.tokenize(text, context_length)?;
        self.encode_ids(&ids[..=end_index(&ids)])
    }

    /// Runs the tower on given ids (1 to `context_length` of them, each below `vocab_size`).
    /// Pooling takes the first position of the largest id, as OpenAI's `argmax`.
    pub fn encode_ids(&self, ids: &[u32]) -> Result<ClipOutput> {
        let n = ids.len();
        if n == 0 || n > self.cfg.context_length {
            return Err(invalid_arg!(
                "ids: {n} tokens, expected 1 to {}",
                self.cfg.context_length
            ));
        }
        if let Some((i, id)) = ids
            .iter()
            .enumerate()
            .find(|(_, &id)| id as usize >= self.cfg.vocab_size)
        {
            return Err(invalid_arg!(
                "ids: id {id} at index {i} is not below vocab_size {}",
                self.cfg.vocab_size
            ));
        }
        let w = self.cfg.width;
        let eps = self.cfg.layer_norm_eps;
        let mut x = vec![0f32; n * w];
        embedding(self.token_embedding.data(), w, ids, &mut x);
        add_inplace(&mut x, &self.position_embedding.data()[..n * w]);
        for block in &self.blocks {
            block.forward(&mut x, n, w, self.cfg.heads, eps);
        }
        let tokens = self.final_norm.apply(&x, w, eps);
        let pooled_index = end_index(ids);
        let pooled = tokens[pooled_index * w..(pooled_index + 1) * w].to_vec();
        let projected = self.projection.apply(&pooled, 1, Activation::None);
        Ok(ClipOutput {
            ids: ids.to_vec(),
            tokens,
            pooled,
            projected,
            pooled_index,
        })
    }
}

/// Position of the first largest id, the first `<|endoftext|>` (OpenAI's `argmax`; `ids` is
/// not empty). Iterator::max_by_key would return the last.
fn end_index(ids: &[u32]) -> usize {
    ids.iter()
        .enumerate()
        .fold(0, |best, (i, &id)| if id > ids[best] { i } else { best })
}

/// The part of the official clean-up (`ftfy.fix_text`, then `html.unescape` twice) that the
/// tokenizer.json normaliser (NFC, whitespace collapse, lower-case) lacks, for the characters
/// prompts plausibly contain: curly quotes → straight (ftfy `uncurl_quotes`), the Latin
/// ligatures U+FB00–FB06 and Ĳ/ĳ (ftfy `fix_latin_ligatures`), full-width ASCII and the
/// ideographic space (ftfy `fix_character_width`), then the entities `&amp; &lt; &gt; &quot;
/// &apos; &nbsp;` and numeric `&#N;`/`&#xH;` decoded twice. Plain ASCII without `&` is returned
/// unchanged. Other ftfy repairs (mojibake, control characters, …) are not done.
pub fn clean_text(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '\u{02bc}' | '\u{2018}'..='\u{201b}' => out.push('\''),
            '\u{201c}'..='\u{201f}' => out.push('"'),
            '\u{fb00}' => out.push_str("ff"),
            '\u{fb01}' => out.push_str("fi"),
            '\u{fb02}' => out.push_str("fl"),
            '\u{fb03}' => out.push_str("ffi"),
            '\u{fb04}' => out.push_str("ffl"),
            '\u{fb05}' => out.push_str("\u{17f}t"),
            '\u{fb06}' => out.push_str("st"),
            '\u{0132}' => out.push_str("IJ"),
            '\u{0133}' => out.push_str("ij"),
            '\u{3000}' => out.push(' '),
            '\u{ff01}'..='\u{ff5e}' => {
                out.push(char::from_u32(c as u32 - 0xfee0).unwrap_or(c));
            }
            _ => out.push(c),
        }
    }
    if out.contains('&') {
        out = unescape_html(&unescape_html(&out));
    }
    out
}

/// Decodes the few named and the numeric character references listed in [`clean_text`];
/// anything else (unknown names, missing `;`, invalid code points) stays as written.
fn unescape_html(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    let mut rest = s;
    while let Some(amp) = rest.find('&') {
        out.push_str(&rest[..amp]);
        let tail = &rest[amp..];
        let decoded = tail[1..]
            .char_indices()
            .take(10)
            .find(|&(_, c)| c == ';')
            .and_then(|(semi, _)| {
                let name = &tail[1..1 + semi];
                decode_entity(name).map(|c| (c, semi + 2))
            });
        match decoded {
            Some((c, len)) => {
                out.push(c);
                rest = &tail[len..];
            }
            None => {
                out.push('&');
                rest = &tail[1..];
            }
        }
    }
    out.push_str(rest);
    out
}

fn decode_entity(name: &str) -> Option<char> {
    let numeric = |digits: &str, radix| {
        u32::from_str_radix(digits, radix)
            .ok()
            .filter(|&v| v != 0)
            .and_then(char::from_u32)
    };
    match name {
        "amp" => Some('&'),
        "lt" => Some('<'),
        "gt" => Some('>'),
        "quot" => Some('"'),
        "apos" => Some('\''),
        "nbsp" => Some('\u{a0}'),
        _ => {
            let num = name.strip_prefix('#')?;
            match num.strip_prefix(['x', 'X']) {
                Some(hex) if !hex.is_empty() && hex.chars().all(|c| c.is_ascii_hexdigit()) => {
                    numeric(hex, 16)
                }
                None if !num.is_empty() && num.chars().all(|c| c.is_ascii_digit()) => {
                    numeric(num, 10)
                }
                _ => None,
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const _: () = {
        const fn send_sync<T: Send + Sync>() {}
        send_sync::<ClipTextEncoder>();
    };

    #[test]
    fn clean_text_subset() {
        assert_eq!(clean_text("a person walks."), "a person walks.");
        assert_eq!(
            clean_text("he said \u{201c}jump\u{201d} and didn\u{2019}t"),
            "he said \"jump\" and didn't"
        );
        assert_eq!(clean_text("the \u{fb01}nal \u{fb02}ip"), "the final flip");
        assert_eq!(clean_text("\u{ff21}\u{ff42}\u{3000}\u{ff01}"), "Ab !");
        assert_eq!(clean_text("tom &amp; jerry &lt;3"), "tom & jerry <3");
        assert_eq!(
            clean_text("&amp;amp; &#65;&#x42; &bogus; & &"),
            "& AB &bogus; & &"
        );
        assert_eq!(
            clean_text("&#0; &#xZZ; &#; &#99999999;"),
            "&#0; &#xZZ; &#; &#99999999;"
        );
        assert_eq!(clean_text("&&amp;&"), "&&&");
    }
}
