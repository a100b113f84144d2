//! Tokenization for the BERT-family encoders: a wrapper over the `tokenizers` crate that reads a
//! Hugging Face tokenizer.json (BERT WordPiece, RoBERTa byte-level BPE) and yields ids plus an
//! attention mask with Hugging Face's `truncation=True` semantics and optional fixed-length
//! padding. It holds no model weights.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::str::FromStr;

use tokenizers::{Encoding, Tokenizer, TruncationDirection};

use crate::error::{bad_file, invalid_arg, Error, Result};

/// Token ids and their attention mask (1 = real token, 0 = padding), of equal length.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Tokens {
    /// Token ids, special tokens and padding included.
    pub ids: Vec<u32>,
    /// 1 for a real token, 0 for padding; one per id.
    pub mask: Vec<u8>,
}

impl Tokens {
    /// Tokens, padding included.
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    /// Whether there are no tokens at all.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }
}

/// How a prompt fits the text encoder's window: what the encoder saw and what was cut off.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PromptInfo {
    /// Tokens of the whole prompt, special tokens included.
    pub tokens: usize,
    /// Tokens the encoder saw (at most `window`).
    pub kept: usize,
    /// The encoder's window: the most tokens it sees, special tokens included.
    pub window: usize,
    /// The text that was cut off (empty when nothing was): the prompt from its first dropped
    /// token on, as the tokenizer saw it (CLIP lower-cases and cleans the text first).
    pub dropped: String,
    /// The prompt is empty or blank: the generation runs on the unconditional input alone.
    pub unconditional: bool,
}

impl PromptInfo {
    /// Whether the window cut the prompt.
    pub fn truncated(&self) -> bool {
        self.tokens > self.kept
    }
}

/// A tokenizer.json tokenizer whose ids are known to fit the encoder's vocabulary.
///
/// The inner tokenizer is never reconfigured after load, so one instance serves many threads;
/// lengths are applied per call instead.
#[derive(Clone)]
pub struct TextTokenizer {
    inner: Tokenizer,
    /// Special tokens the post-processor puts around one sequence (`[CLS]`/`[SEP]`, `<s>`/`</s>`).
    num_special: usize,
    pad_id: u32,
}

impl std::fmt::Debug for TextTokenizer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TextTokenizer")
            .field("vocab", &self.inner.get_vocab_size(true))
            .field("num_special", &self.num_special)
            .field("pad_id", &self.pad_id)
            .finish()
    }
}

/// A tokenizer.json that cannot be used: the model file's fault.
fn file_err(context: &str) -> impl Fn(Box<dyn std::error::Error + Send + Sync>) -> Error + '_ {
    move |e| bad_file!("tokenizer (`flame.tokenizer`): {context}: {e}")
}

fn tok_err(context: &str) -> impl Fn(Box<dyn std::error::Error + Send + Sync>) -> Error + '_ {
    move |e| Error::Tokenizer(format!("{context}: {e}"))
}

impl TextTokenizer {
    /// Builds the tokenizer from tokenizer.json text and checks that every id it can produce
    /// (vocabulary, added tokens, post-processor specials, `pad_id`) is below `vocab_size`, so an
    /// embedding lookup can never go out of bounds. The text comes from the model file, so
    /// every failure here is [`Error::BadModelFile`].
    pub fn from_json(json: &str, vocab_size: usize, pad_id: u32) -> Result<TextTokenizer> {
        // tokenizers 0.22 panics (`expect("Helper")`) on a syntax error inside the `decoder`
        // field instead of returning it, so the syntax is checked first.
        serde_json::from_str::<serde::de::IgnoredAny>(json).map_err(|e| {
            file_err("cannot build a tokenizer from the tokenizer.json text")(
                format!("not valid JSON: {e}").into(),
            )
        })?;
        let mut inner = Tokenizer::from_str(json).map_err(file_err(
            "cannot build a tokenizer from the tokenizer.json text",
        ))?;
        // Files carry their own truncation/padding (all-MiniLM-L6-v2's pads every text to 128);
        // lengths are the caller's choice here, so both are switched off once, at load.
        inner
            .with_truncation(None)
            .map_err(file_err("cannot switch off the tokenizer's truncation"))?;
        inner.with_padding(None);

        let specials = inner
            .post_process(Encoding::default(), None, true)
            .map_err(file_err(
                "the tokenizer's post-processor failed on an empty text",
            ))?;
        let num_special = specials.get_ids().len();

        let mut produced: Vec<(u32, String)> = inner
            .get_vocab(true)
            .into_iter()
            .map(|(t, i)| (i, t))
            .collect();
        produced.extend(
            specials
                .get_ids()
                .iter()
                .zip(specials.get_tokens())
                .map(|(&i, t)| (i, t.clone())),
        );
        produced.push((pad_id, "<padding>".into()));
        if let Some((id, token)) = produced.iter().max_by_key(|(i, _)| *i) {
            if *id as usize >= vocab_size {
                return Err(bad_file!(
                    "the tokenizer produces id {id} (`{token}`) but the text encoder's vocab_size is {vocab_size}"
                ));
            }
        }
        Ok(TextTokenizer {
            inner,
            num_special,
            pad_id,
        })
    }

    /// How many special tokens a single text gets (2 for BERT and RoBERTa).
    pub fn num_special_tokens(&self) -> usize {
        self.num_special
    }

    /// The id padding positions hold.
    pub fn pad_id(&self) -> u32 {
        self.pad_id
    }

    /// Tokenizes `text`: content tokens are cut so that, with the special tokens, at most
    /// `max_length` remain (Hugging Face `truncation=True`); with `pad`, `pad_id` fills up to
    /// `max_length` with mask 0. Any text is accepted; only a `max_length` too small for the
    /// special tokens is an error.
    pub fn encode(&self, text: &str, max_length: usize, pad: bool) -> Result<Tokens> {
        let budget = max_length.checked_sub(self.num_special).ok_or_else(|| {
            invalid_arg!(
                "max_length {max_length} leaves no room for the {} special tokens",
                self.num_special
            )
        })?;
        // The tokenizers crate is not known to panic on text, but a C caller must never see an
        // unwind, so a panic becomes an error like any other tokenizer failure.
        let enc = catch_unwind(AssertUnwindSafe(|| self.encode_truncated(text, budget)))
            .map_err(|_| Error::Tokenizer("the tokenizer panicked on this text".into()))??;
        let mut ids = enc.get_ids().to_vec();
        let mut mask: Vec<u8> = enc
            .get_attention_mask()
            .iter()
            .map(|&m| u8::from(m != 0))
            .collect();
        if ids.len() > max_length {
            return Err(Error::Tokenizer(format!(
                "the post-processor produced {} tokens, more than max_length {max_length}",
                ids.len()
            )));
        }
        if pad {
            ids.resize(max_length, self.pad_id);
            mask.resize(max_length, 0);
        }
        Ok(Tokens { ids, mask })
    }

    /// How `text` fits a window of `max_length` tokens (special tokens included), with the
    /// same cut as [`TextTokenizer::encode`].
    pub fn fit(&self, text: &str, max_length: usize) -> Result<PromptInfo> {
        let budget = max_length.checked_sub(self.num_special).ok_or_else(|| {
            invalid_arg!(
                "max_length {max_length} leaves no room for the {} special tokens",
                self.num_special
            )
        })?;
        let enc = catch_unwind(AssertUnwindSafe(|| self.inner.encode(text, false)))
            .map_err(|_| Error::Tokenizer("the tokenizer panicked on this text".into()))?
            .map_err(tok_err("cannot tokenize the text"))?;
        let content = enc.get_ids().len();
        // Offsets are byte offsets into `text`; a token that starts inside a character (byte
        // fallback) is moved back to that character's start.
        let dropped = match enc.get_offsets().get(budget) {
            Some(&(start, _)) if content > budget => {
                let mut at = start.min(text.len());
                while !text.is_char_boundary(at) {
                    at -= 1;
                }
                text[at..].trim().to_string()
            }
            _ => String::new(),
        };
        Ok(PromptInfo {
            tokens: content + self.num_special,
            kept: content.min(budget) + self.num_special,
            window: max_length,
            dropped,
            unconditional: text.trim().is_empty(),
        })
    }

    fn encode_truncated(&self, text: &str, budget: usize) -> Result<Encoding> {
        let mut enc = self
            .inner
            .encode(text, false)
            .map_err(tok_err("cannot tokenize the text"))?;
        enc.truncate(budget, 0, TruncationDirection::Right);
        // The cut-off tail would otherwise be post-processed too, for nothing.
        drop(enc.take_overflowing());
        self.inner
            .post_process(enc, None, true)
            .map_err(tok_err("the tokenizer's post-processor failed"))
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A minimal BERT-style tokenizer.json: WordPiece over 9 tokens, `[CLS] … [SEP]` around a text.
    pub(crate) const WORDPIECE: &str = r###"{"version":"1.0","truncation":null,"padding":null,
      "added_tokens":[
        {"id":0,"content":"[PAD]","single_word":false,"lstrip":false,"rstrip":false,"normalized":false,"special":true},
        {"id":1,"content":"[UNK]","single_word":false,"lstrip":false,"rstrip":false,"normalized":false,"special":true},
        {"id":2,"content":"[CLS]","single_word":false,"lstrip":false,"rstrip":false,"normalized":false,"special":true},
        {"id":3,"content":"[SEP]","single_word":false,"lstrip":false,"rstrip":false,"normalized":false,"special":true}],
      "normalizer":{"type":"BertNormalizer","clean_text":true,"handle_chinese_chars":true,"strip_accents":null,"lowercase":true},
      "pre_tokenizer":{"type":"BertPreTokenizer"},
      "post_processor":{"type":"BertProcessing","sep":["[SEP]",3],"cls":["[CLS]",2]},
      "decoder":null,
      "model":{"type":"WordPiece","unk_token":"[UNK]","continuing_subword_prefix":"##","max_input_chars_per_word":100,
        "vocab":{"[PAD]":0,"[UNK]":1,"[CLS]":2,"[SEP]":3,"a":4,"person":5,"walk":6,"##s":7,".":8}}}"###;

    /// Found by fuzzing (model_header): a syntax error inside `decoder` made the tokenizers
    /// crate panic while loading the model.
    #[test]
    fn a_syntax_error_in_the_decoder_is_an_error() {
        let json = WORDPIECE.replace(
            r#""decoder":null"#,
            "\"decoder\":{\"type\":\"Byte\u{1}Level\"}",
        );
        assert_ne!(json, WORDPIECE);
        let e = TextTokenizer::from_json(&json, 9, 0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("not valid JSON"), "{e}");
    }

    fn tok() -> TextTokenizer {
        TextTokenizer::from_json(WORDPIECE, 9, 0).unwrap()
    }

    #[test]
    fn adds_specials_truncates_and_pads() {
        let t = tok();
        assert_eq!(t.num_special_tokens(), 2);
        let full = t.encode("A Person walks.", 16, false).unwrap();
        assert_eq!(
            full,
            Tokens {
                ids: vec![2, 4, 5, 6, 7, 8, 3],
                mask: vec![1; 7]
            }
        );
        let cut = t.encode("A Person walks.", 4, false).unwrap();
        assert_eq!(cut.ids, [2, 4, 5, 3]);
        let padded = t.encode("a person", 6, true).unwrap();
        assert_eq!(
            padded,
            Tokens {
                ids: vec![2, 4, 5, 3, 0, 0],
                mask: vec![1, 1, 1, 1, 0, 0]
            }
        );
        let exact = t.encode("a person", 2, true).unwrap();
        assert_eq!(exact.ids, [2, 3]);
    }

    #[test]
    fn any_text_tokenizes() {
        let t = tok();
        let long = "walks ".repeat(100_000);
        for text in [
            "",
            "   ",
            "!?!",
            "🙂",
            "Une personne saute 🙂 très haut",
            "\u{0}\u{200b}",
            &long,
        ] {
            let out = t.encode(text, 8, true).unwrap();
            assert_eq!((out.ids.len(), out.ids[0]), (8, 2), "{text:?}");
        }
        assert_eq!(t.encode("", 8, false).unwrap().ids, [2, 3]);
        assert_eq!(t.encode("🙂", 8, false).unwrap().ids, [2, 1, 3]);
    }

    #[test]
    fn fit_counts_what_the_window_keeps() {
        let t = tok();
        // [CLS] a person walk ##s . [SEP]: 7 tokens.
        let all = t.fit("A Person walks.", 16).unwrap();
        assert_eq!((all.tokens, all.kept, all.window), (7, 7, 16));
        assert!(!all.truncated() && all.dropped.is_empty() && !all.unconditional);
        // A window of 5 keeps [CLS] a person walk [SEP]: "##s ." is cut, which starts inside
        // "walks" at byte 13.
        let cut = t.fit("A Person walks.", 5).unwrap();
        assert_eq!((cut.tokens, cut.kept), (7, 5));
        assert!(cut.truncated());
        assert_eq!(cut.dropped, "s.");
        assert_eq!(
            t.encode("A Person walks.", 5, false).unwrap().len(),
            cut.kept
        );
        let exact = t.fit("a person", 4).unwrap();
        assert_eq!((exact.tokens, exact.kept, exact.truncated()), (4, 4, false));
        let blank = t.fit("  \t", 4).unwrap();
        assert_eq!((blank.tokens, blank.kept), (2, 2));
        assert!(blank.unconditional);
        assert!(t.fit("a", 1).is_err());
    }

    #[test]
    fn max_length_must_fit_the_specials() {
        let e = tok().encode("a", 1, false).unwrap_err();
        assert!(matches!(e, Error::InvalidArgument(_)), "{e}");
        assert!(
            e.to_string()
                .contains("max_length 1 leaves no room for the 2 special tokens"),
            "{e}"
        );
    }

    #[test]
    fn file_padding_and_truncation_are_ignored() {
        // all-MiniLM-L6-v2's tokenizer.json pads and truncates to 128 by itself.
        let json = WORDPIECE.replace(
            r#""truncation":null,"padding":null"#,
            r#""truncation":{"max_length":3,"strategy":"LongestFirst","stride":0},
               "padding":{"strategy":{"Fixed":128},"direction":"Right","pad_to_multiple_of":null,
                          "pad_id":0,"pad_type_id":0,"pad_token":"[PAD]"}"#,
        );
        let t = TextTokenizer::from_json(&json, 9, 0).unwrap();
        assert_eq!(
            t.encode("a person walks", 16, false).unwrap().ids,
            [2, 4, 5, 6, 7, 3]
        );
    }

    #[test]
    fn garbage_is_a_bad_model_file() {
        for json in ["", "not json", "{}", r#"{"model":{"type":"Nonsense"}}"#] {
            let e = TextTokenizer::from_json(json, 9, 0).unwrap_err();
            assert!(matches!(e, Error::BadModelFile(_)), "{json:?}: {e}");
            assert!(
                e.to_string().starts_with(
                    "bad model file: tokenizer (`flame.tokenizer`): cannot build a tokenizer \
                     from the tokenizer.json text: "
                ),
                "{e}"
            );
        }
    }

    #[test]
    fn ids_beyond_the_vocabulary_are_rejected() {
        let msg = |json: &str, vocab, pad| {
            TextTokenizer::from_json(json, vocab, pad)
                .unwrap_err()
                .to_string()
        };
        assert_eq!(
            msg(WORDPIECE, 8, 0),
            "bad model file: the tokenizer produces id 8 (`.`) but the text encoder's vocab_size is 8"
        );
        let sep50 = WORDPIECE.replace(r#""sep":["[SEP]",3]"#, r#""sep":["[SEP]",50]"#);
        assert!(
            msg(&sep50, 9, 0).contains("produces id 50 (`[SEP]`)"),
            "{}",
            msg(&sep50, 9, 0)
        );
        assert!(msg(WORDPIECE, 9, 9).contains("produces id 9 (`<padding>`)"));
    }
}
