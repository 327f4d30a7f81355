//! One problem in a pipeline file, and the nesting bound checked before the TOML parser runs:
//! what the checks and the command line's overrides both report with.

/// One problem in a pipeline file.
#[derive(Clone, Debug)]
pub struct Diagnostic {
    pub line: usize,
    pub key: String,
    pub message: String,
    pub help: Option<String>,
}

/// The deepest nesting of keys, tables and arrays a pipeline file may use (the shipped ones use
/// five); deeper input would exhaust the TOML parser's recursion limit.
pub(super) const MAX_DEPTH: usize = 32;

/// The first line nested deeper than [`MAX_DEPTH`], with its depth: each open array or inline
/// table counts one, and each dot of a key (a header's, or a key's before its `=`) one more.
/// Dots in values (numbers, strings) and list items do not nest. This only needs to find input
/// far beyond any real pipeline before the parser's recursion limit does.
pub(super) fn too_deep(text: &str) -> Option<(usize, usize)> {
    #[derive(Clone, Copy, PartialEq)]
    enum Quoted {
        Basic,
        Literal,
        MultiBasic,
        MultiLiteral,
    }
    let bytes = text.as_bytes();
    let at = |i: usize, s: &[u8]| bytes[i..].starts_with(s);
    // Each open array or inline table with the dots of the key that holds it.
    let mut open: Vec<(u8, usize)> = Vec::new();
    let (mut dots, mut in_key, mut quoted, mut line, mut i) = (0usize, true, None::<Quoted>, 1usize, 0usize);
    while i < bytes.len() {
        let b = bytes[i];
        i += 1;
        if b == b'\n' {
            line += 1;
            if matches!(quoted, Some(Quoted::Basic | Quoted::Literal)) {
                quoted = None; // unterminated: the parser will say so
            }
            if open.is_empty() {
                (dots, in_key) = (0, true);
            }
            continue;
        }
        match (quoted, b) {
            (Some(Quoted::Basic | Quoted::MultiBasic), b'\\') => i += 1,
            (Some(Quoted::Basic), b'"') | (Some(Quoted::Literal), b'\'') => quoted = None,
            (Some(Quoted::MultiBasic), b'"') if at(i, b"\"\"") => (quoted, i) = (None, i + 2),
            (Some(Quoted::MultiLiteral), b'\'') if at(i, b"''") => (quoted, i) = (None, i + 2),
            (Some(_), _) => {}
            (None, b'#') => i = bytes[i..].iter().position(|&c| c == b'\n').map_or(bytes.len(), |p| i + p),
            (None, b'"') if at(i, b"\"\"") => (quoted, i) = (Some(Quoted::MultiBasic), i + 2),
            (None, b'"') => quoted = Some(Quoted::Basic),
            (None, b'\'') if at(i, b"''") => (quoted, i) = (Some(Quoted::MultiLiteral), i + 2),
            (None, b'\'') => quoted = Some(Quoted::Literal),
            (None, b'=') => in_key = false,
            (None, b'.') if in_key => dots += 1,
            // A header's brackets (`[a.b]`, `[[a]]`) open nothing: its dots count as a key's.
            (None, b'[' | b']') if open.is_empty() && in_key => {}
            (None, b'[' | b'{') => {
                open.push((b, dots));
                (dots, in_key) = (0, b == b'{');
            }
            (None, b']' | b'}') => {
                dots = open.pop().map_or(0, |o| o.1);
                in_key = false;
            }
            (None, b',') if open.last().is_some_and(|o| o.0 == b'{') => (dots, in_key) = (0, true),
            _ => {}
        }
        let depth = open.len() + open.iter().map(|o| o.1).sum::<usize>() + dots;
        if depth > MAX_DEPTH {
            return Some((line, depth));
        }
    }
    None
}
