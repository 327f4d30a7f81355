//! Number words: "three" -> 3, "twenty one" / "twenty-one" -> 21, and back.

use crate::Token;

const ONES: [&str; 20] = [
    "zero",
    "one",
    "two",
    "three",
    "four",
    "five",
    "six",
    "seven",
    "eight",
    "nine",
    "ten",
    "eleven",
    "twelve",
    "thirteen",
    "fourteen",
    "fifteen",
    "sixteen",
    "seventeen",
    "eighteen",
    "nineteen",
];
const TENS: [&str; 10] = ["", "", "twenty", "thirty", "forty", "fifty", "sixty", "seventy", "eighty", "ninety"];

/// `n` in words (0..=99; larger numbers as digits).
pub fn number_word(n: u32) -> String {
    match n {
        0..=19 => ONES[n as usize].into(),
        20..=99 if n.is_multiple_of(10) => TENS[n as usize / 10].into(),
        20..=99 => format!("{}-{}", TENS[n as usize / 10], ONES[n as usize % 10]),
        _ => n.to_string(),
    }
}

/// Replaces number words (and "a pair of", "a couple of") with numbers.
pub(crate) fn words_to_numbers(tokens: Vec<Token<'_>>) -> Vec<Token<'_>> {
    let value = |t: Option<&Token>| -> Option<(u32, bool)> {
        let Some(Token::Word(w)) = t else { return None };
        if let Some(i) = ONES.iter().position(|o| o == w) {
            return Some((i as u32, false));
        }
        TENS.iter().position(|o| !o.is_empty() && o == w).map(|i| (i as u32 * 10, true))
    };
    let is = |t: Option<&Token>, w: &str| matches!(t, Some(Token::Word(x)) if *x == w);
    let mut out = Vec::with_capacity(tokens.len());
    let mut i = 0;
    while i < tokens.len() {
        if is(tokens.get(i), "a") && (is(tokens.get(i + 1), "pair") || is(tokens.get(i + 1), "couple")) && is(tokens.get(i + 2), "of") {
            out.push(Token::Number(2));
            i += 3;
            continue;
        }
        match value(tokens.get(i)) {
            Some((tens, true)) => {
                // "twenty one", "twenty-one"
                let skip = usize::from(is(tokens.get(i + 1), "-"));
                match value(tokens.get(i + 1 + skip)) {
                    Some((ones, false)) if ones > 0 && ones < 10 => {
                        out.push(Token::Number(tens + ones));
                        i += 2 + skip;
                    }
                    _ => {
                        out.push(Token::Number(tens));
                        i += 1;
                    }
                }
            }
            Some((n, false)) => {
                out.push(Token::Number(n));
                i += 1;
            }
            None => {
                out.push(tokens[i]);
                i += 1;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn words_and_numbers_round_trip() {
        for n in 0..100 {
            let text = format!("{} cars", number_word(n));
            assert_eq!(crate::numbers::words_to_numbers(crate::tokenize(&text))[0], Token::Number(n), "{text}");
        }
        assert_eq!(words_to_numbers(crate::tokenize("a pair of cars"))[0], Token::Number(2));
    }
}
