//! Prompt text (any bytes, made UTF-8 the lossy way, as a C caller's prompt is) through every
//! tokenizer kind: the RoBERTa byte-level BPE of the FLAME fixture, the CLIP tokenizer of the
//! MDM fixture and the full 49408-token CLIP vocabulary (with CLIP's text clean-up), and a BERT
//! WordPiece tokenizer. The first byte picks the tokenizer, `max_length`/`context_length` (0 to 93) and padding.
#![no_main]

use std::sync::OnceLock;

use flame::models::Model;
use flame::text::{clip, TextTokenizer};
use flame_fuzz::FIXTURES;
use libfuzzer_sys::fuzz_target;

static CLIP_JSON: &str = include_str!("../../tests/fixtures/clip_tokenizer/tokenizer.json");

/// A BERT-style tokenizer.json: WordPiece with BERT's normaliser (clean-up, Chinese characters,
/// accents, lower case) and `[CLS] … [SEP]`.
const WORDPIECE: &str = r###"{"version":"1.0","truncation":null,"padding":null,
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
    "vocab":{"[PAD]":0,"[UNK]":1,"[CLS]":2,"[SEP]":3,"a":4,"person":5,"walk":6,"##s":7,".":8,"##e":9,"é":10}}}"###;

struct Tokenizers {
    flame: Model,
    mdm: Model,
    clip: TextTokenizer,
    wordpiece: TextTokenizer,
}

fn tokenizers() -> &'static Tokenizers {
    static T: OnceLock<Tokenizers> = OnceLock::new();
    T.get_or_init(|| Tokenizers {
        flame: Model::from_bytes(FIXTURES[0]).expect("flame_tiny loads"),
        mdm: Model::from_bytes(FIXTURES[1]).expect("mdm_tiny loads"),
        clip: TextTokenizer::from_json(CLIP_JSON, 49408, 0).expect("CLIP tokenizer builds"),
        wordpiece: TextTokenizer::from_json(WORDPIECE, 11, 0).expect("WordPiece builds"),
    })
}

/// Checks what every successful tokenization promises: ids and mask of equal length, at most
/// `max_length` of them (exactly that with padding), every id inside the vocabulary.
fn check(tokens: &flame::text::Tokens, max_length: usize, pad: bool, vocab: usize) {
    assert_eq!(tokens.ids.len(), tokens.mask.len());
    assert!(tokens.len() <= max_length);
    if pad {
        assert_eq!(tokens.len(), max_length);
    }
    assert!(tokens.ids.iter().all(|&i| (i as usize) < vocab));
}

fuzz_target!(|data: &[u8]| {
    let Some((&knob, rest)) = data.split_first() else {
        return;
    };
    let text = String::from_utf8_lossy(rest);
    let t = tokenizers();
    let max_length = (knob & 0x1f) as usize * 3;
    let pad = knob & 0x20 != 0;

    // One tokenizer per execution (the knob's top two bits): the byte-level BPE
    // pre-tokeniser's regular expression is slow under instrumentation.
    match knob >> 6 {
        0 => {
            let roberta = t
                .flame
                .text_encoder()
                .expect("flame_tiny has a RoBERTa encoder");
            if let Ok(tokens) = roberta.tokenize(&text, max_length, pad) {
                check(&tokens, max_length, pad, 979);
            }
        }
        1 => {
            if let flame::models::TextModel::Clip { encoder, .. } = t.mdm.text_model() {
                if let Ok(ids) = encoder.tokenize(&text, max_length) {
                    assert_eq!(ids.len(), encoder.context_length());
                    assert!(ids.iter().all(|&i| i < 979));
                }
            }
        }
        2 => {
            if let Ok(tokens) = t.clip.encode(&clip::clean_text(&text), max_length, pad) {
                check(&tokens, max_length, pad, 49408);
            }
        }
        _ => {
            if let Ok(tokens) = t.wordpiece.encode(&text, max_length, pad) {
                check(&tokens, max_length, pad, 11);
            }
        }
    }
});
