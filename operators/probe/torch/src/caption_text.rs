//! A generated caption as text, without losing a byte.
//!
//! The tokens stage's BPE is byte-level: every token stands for bytes, and a decoder may emit
//! bytes that are no UTF-8 (half a character, or a byte no training caption holds: the 256
//! single bytes are all in the vocabulary). `tokenizers` decodes those to U+FFFD, which hides
//! what was generated; here each such byte is written `\xNN`, as Python's `backslashreplace`
//! does, and valid text is exactly what `tokenizers` decodes.

use std::fmt::Write as _;

use tokenizers::Tokenizer;

/// The text of generated token `ids`, special tokens left out, bytes that are not UTF-8 as `\xNN`.
pub fn caption_text(tokenizer: &Tokenizer, ids: &[u32]) -> anyhow::Result<String> {
    let specials = tokenizer.get_added_vocabulary();
    let mut bytes = Vec::new();
    for &id in ids {
        let token = tokenizer.id_to_token(id).ok_or_else(|| anyhow::anyhow!("token {id} is not in the tokenizer's vocabulary"))?;
        if specials.is_special_token(&token) {
            continue;
        }
        for symbol in token.chars() {
            bytes.push(symbol_byte(symbol).ok_or_else(|| anyhow::anyhow!("token {id} ({token:?}) is not byte-level"))?);
        }
    }
    let mut text = String::with_capacity(bytes.len());
    for chunk in bytes.utf8_chunks() {
        text.push_str(chunk.valid());
        for byte in chunk.invalid() {
            write!(text, "\\x{byte:02x}").expect("writing to a String");
        }
    }
    Ok(text)
}

/// The byte a byte-level BPE symbol stands for: GPT-2's table, which `tokenizers`' `ByteLevel`
/// builds (and keeps private): the printable Latin-1 bytes are their own symbol, the other 68
/// take U+0100 onwards in byte order.
fn symbol_byte(symbol: char) -> Option<u8> {
    let printable = |b: u8| matches!(b, b'!'..=b'~' | 0xA1..=0xAC | 0xAE..=0xFF);
    let code = u32::from(symbol);
    match u8::try_from(code) {
        Ok(b) if printable(b) => Some(b),
        _ => (0..=255u8).filter(|&b| !printable(b)).nth(code.checked_sub(256)? as usize),
    }
}

#[cfg(test)]
mod tests {
    use std::collections::HashSet;

    use tokenizers::models::bpe::{BPE, BpeTrainerBuilder};
    use tokenizers::pre_tokenizers::byte_level::ByteLevel;
    use tokenizers::{AddedToken, DecoderWrapper, NormalizerWrapper, PostProcessorWrapper, PreTokenizerWrapper, TokenizerBuilder, TokenizerImpl};

    use super::*;

    /// A byte-level BPE as the tokens stage builds one, learnt from two ASCII captions.
    fn tokenizer() -> Tokenizer {
        let mut trainer = BpeTrainerBuilder::new()
            .show_progress(false)
            .vocab_size(300)
            .special_tokens(vec![AddedToken::from("<|end|>", true)])
            .initial_alphabet(ByteLevel::alphabet().into_iter().collect::<HashSet<char>>())
            .build();
        let mut bpe: TokenizerImpl<BPE, NormalizerWrapper, PreTokenizerWrapper, PostProcessorWrapper, DecoderWrapper> = TokenizerBuilder::new()
            .with_model(BPE::default())
            .with_pre_tokenizer(Some(ByteLevel::default().into()))
            .with_decoder(Some(ByteLevel::default().into()))
            .build()
            .unwrap();
        bpe.train(&mut trainer, ["a car 12 m ahead", "two cars left of the ego"].iter()).unwrap();
        Tokenizer::from(bpe)
    }

    fn symbol(byte: u8) -> char {
        (0..0x200).filter_map(char::from_u32).find(|&c| symbol_byte(c) == Some(byte)).unwrap()
    }

    #[test]
    fn the_symbol_table_is_byte_levels() {
        let symbols: HashSet<char> = (0..=255u8).map(symbol).collect();
        assert_eq!(symbols, ByteLevel::alphabet().into_iter().collect::<HashSet<char>>(), "one symbol per byte, the alphabet's");
    }

    /// Valid text decodes as `tokenizers` decodes it (ASCII, a two-byte character split into
    /// byte tokens, special tokens left out); a byte that is not UTF-8 is written `\xNN` where
    /// `tokenizers` writes U+FFFD.
    #[test]
    fn valid_text_decodes_as_tokenizers_does_and_a_stray_byte_is_named() {
        let t = tokenizer();
        for text in ["a car 12 m ahead", "d\u{e9}j\u{e0} vu, 40 \u{b0}"] {
            let mut ids = t.encode(text, false).unwrap().get_ids().to_vec();
            ids.push(t.token_to_id("<|end|>").unwrap());
            assert_eq!(caption_text(&t, &ids).unwrap(), t.decode(&ids, true).unwrap(), "{text}");
            assert_eq!(caption_text(&t, &ids).unwrap().trim(), text);
        }
        // "é" is C3 A9: its first byte alone, then a car.
        let stray = t.token_to_id(&symbol(0xC3).to_string()).unwrap();
        let mut ids = vec![stray];
        ids.extend(t.encode("a car", false).unwrap().get_ids());
        assert_eq!(t.decode(&ids, true).unwrap(), "\u{fffd} a car", "what the report showed");
        assert_eq!(caption_text(&t, &ids).unwrap(), "\\xc3 a car");
    }
}
