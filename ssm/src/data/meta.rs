//! `meta.json`: a flat JSON object `{"format": 1, "dt": <positive>, "steps": <int >= 1>}`,
//! optionally with `"prior_from_detection": true` or `false` (absent: `false`).
//!
//! A small dedicated parser rather than `serde_json`: it knows the line of
//! every key (for error messages) and parses numbers with the standard
//! library's correctly rounded `f64` parser, so `dt` round-trips bit for bit
//! (serde_json's default float parser does not guarantee that).

use super::error::DataError;
use super::{Meta, FORMAT_VERSION};

fn err(line: usize, field: &str, message: impl Into<String>) -> DataError {
    DataError::Meta { line, field: field.to_string(), message: message.into() }
}

/// Checks the values of a [`Meta`] (reported at `line`).
pub(crate) fn check_meta(meta: &Meta, line: usize) -> Result<(), DataError> {
    check_dt(meta.dt, line)?;
    check_steps(meta.steps as u64, line)
}

fn check_dt(dt: f64, line: usize) -> Result<(), DataError> {
    if dt.is_finite() && dt > 0.0 {
        Ok(())
    } else {
        Err(err(line, "dt", format!("must be a positive finite number, found {dt}")))
    }
}

fn check_steps(steps: u64, line: usize) -> Result<(), DataError> {
    if steps >= 1 && usize::try_from(steps).is_ok() {
        Ok(())
    } else {
        Err(err(line, "steps", format!("must be at least 1, found {steps}")))
    }
}

/// A JSON scalar token with its line.
#[derive(Debug, PartialEq)]
enum Value {
    Number(String),
    Other(String),
}

/// The optional boolean field `prior_from_detection`.
const PRIOR_FROM_DETECTION: &str = "prior_from_detection";

struct Lexer<'a> {
    s: &'a [u8],
    pos: usize,
    line: usize,
}

impl<'a> Lexer<'a> {
    fn skip_ws(&mut self) {
        while let Some(&c) = self.s.get(self.pos) {
            match c {
                b'\n' => {
                    self.line += 1;
                    self.pos += 1;
                }
                b' ' | b'\t' | b'\r' => self.pos += 1,
                _ => break,
            }
        }
    }

    fn peek(&mut self) -> Option<u8> {
        self.skip_ws();
        self.s.get(self.pos).copied()
    }

    fn expect(&mut self, c: u8, what: &str) -> Result<(), DataError> {
        match self.peek() {
            Some(x) if x == c => {
                self.pos += 1;
                Ok(())
            }
            Some(x) => Err(err(self.line, "-", format!("syntax error: expected {what}, found `{}`", x as char))),
            None => Err(err(self.line, "-", format!("syntax error: expected {what}, found end of file"))),
        }
    }

    fn string(&mut self) -> Result<String, DataError> {
        self.expect(b'"', "a string")?;
        let start = self.pos;
        while let Some(&c) = self.s.get(self.pos) {
            match c {
                b'"' => {
                    let text = String::from_utf8_lossy(&self.s[start..self.pos]).into_owned();
                    self.pos += 1;
                    return Ok(text);
                }
                b'\\' => self.pos += 2,
                b'\n' => {
                    return Err(err(self.line, "-", "syntax error: unterminated string"));
                }
                _ => self.pos += 1,
            }
        }
        Err(err(self.line, "-", "syntax error: unterminated string"))
    }

    /// A scalar value: a number, a string, or a bare word. Arrays and objects
    /// are reported as `Other` after skipping them.
    fn value(&mut self) -> Result<Value, DataError> {
        match self.peek() {
            None => Err(err(self.line, "-", "syntax error: expected a value, found end of file")),
            Some(b'"') => Ok(Value::Other(format!("\"{}\"", self.string()?))),
            Some(b'{') | Some(b'[') => {
                let mut depth = 0usize;
                while let Some(&c) = self.s.get(self.pos) {
                    self.pos += 1;
                    match c {
                        b'{' | b'[' => depth += 1,
                        b'}' | b']' => {
                            depth -= 1;
                            if depth == 0 {
                                return Ok(Value::Other("a nested value".into()));
                            }
                        }
                        b'\n' => self.line += 1,
                        _ => {}
                    }
                }
                Err(err(self.line, "-", "syntax error: unterminated value"))
            }
            Some(_) => {
                let start = self.pos;
                while let Some(&c) = self.s.get(self.pos) {
                    if c.is_ascii_alphanumeric() || matches!(c, b'-' | b'+' | b'.') {
                        self.pos += 1;
                    } else {
                        break;
                    }
                }
                if start == self.pos {
                    return Err(err(
                        self.line,
                        "-",
                        format!("syntax error: unexpected `{}`", self.s[self.pos] as char),
                    ));
                }
                let text = String::from_utf8_lossy(&self.s[start..self.pos]).into_owned();
                let numeric = text.bytes().next().is_some_and(|c| c == b'-' || c.is_ascii_digit());
                Ok(if numeric { Value::Number(text) } else { Value::Other(text) })
            }
        }
    }
}

/// Parses and validates the text of `meta.json`.
pub(crate) fn parse_meta(text: &str) -> Result<Meta, DataError> {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let mut lx = Lexer { s: text.as_bytes(), pos: 0, line: 1 };
    lx.expect(b'{', "`{`")?;
    let mut fields: Vec<(String, usize, Value)> = Vec::new();
    if lx.peek() == Some(b'}') {
        lx.pos += 1;
    } else {
        loop {
            let key_line = {
                lx.skip_ws();
                lx.line
            };
            let key = lx.string()?;
            lx.expect(b':', "`:`")?;
            let value = lx.value()?;
            if fields.iter().any(|(k, _, _)| *k == key) {
                return Err(err(key_line, &key, "duplicate field"));
            }
            fields.push((key, key_line, value));
            match lx.peek() {
                Some(b',') => lx.pos += 1,
                _ => {
                    lx.expect(b'}', "`,` or `}`")?;
                    break;
                }
            }
        }
    }
    let end_line = lx.line;
    if lx.peek().is_some() {
        return Err(err(lx.line, "-", "syntax error: trailing characters after the object"));
    }

    for (key, line, _) in &fields {
        if !matches!(key.as_str(), "format" | "dt" | "steps" | PRIOR_FROM_DETECTION) {
            return Err(err(
                *line,
                key,
                "unknown field (expected only `format`, `dt`, `steps` and `prior_from_detection`)",
            ));
        }
    }
    let get = |name: &str| -> Result<(usize, &str), DataError> {
        match fields.iter().find(|(k, _, _)| k == name) {
            None => Err(err(end_line, name, "missing field")),
            Some((_, line, Value::Number(t))) => Ok((*line, t.as_str())),
            Some((_, line, Value::Other(t))) => Err(err(*line, name, format!("expected a number, found {t}"))),
        }
    };
    let integer = |name: &str| -> Result<(usize, u64), DataError> {
        let (line, t) = get(name)?;
        t.parse::<u64>()
            .map(|v| (line, v))
            .map_err(|_| err(line, name, format!("expected a non-negative integer, found {t}")))
    };

    let (line, format) = integer("format")?;
    if format != u64::from(FORMAT_VERSION) {
        return Err(err(
            line,
            "format",
            format!("unsupported format version {format} (this code reads version {FORMAT_VERSION})"),
        ));
    }
    let (dt_line, dt_text) = get("dt")?;
    let dt: f64 = dt_text.parse().map_err(|_| err(dt_line, "dt", format!("malformed number {dt_text}")))?;
    check_dt(dt, dt_line)?;
    let (steps_line, steps) = integer("steps")?;
    check_steps(steps, steps_line)?;
    let prior_from_detection = match fields.iter().find(|(k, _, _)| k == PRIOR_FROM_DETECTION) {
        None => false,
        Some((_, _, Value::Other(t))) if t == "true" => true,
        Some((_, _, Value::Other(t))) if t == "false" => false,
        Some((_, line, Value::Number(t) | Value::Other(t))) => {
            return Err(err(*line, PRIOR_FROM_DETECTION, format!("expected true or false, found {t}")))
        }
    };
    Ok(Meta { dt, steps: steps as usize, prior_from_detection })
}

/// The text of `meta.json` for `meta` (numbers in shortest round-trip form).
/// The optional field is written only when `true`, so other datasets keep their
/// three-field file.
pub(crate) fn render_meta(meta: &Meta) -> String {
    let prior =
        if meta.prior_from_detection { format!(",\n  \"{PRIOR_FROM_DETECTION}\": true") } else { String::new() };
    format!("{{\n  \"format\": {FORMAT_VERSION},\n  \"dt\": {:?},\n  \"steps\": {}{prior}\n}}\n", meta.dt, meta.steps)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_renders() {
        let m = Meta::new(1.0 / 3.0, 26);
        let back = parse_meta(&render_meta(&m)).unwrap();
        assert_eq!(back.dt.to_bits(), m.dt.to_bits());
        assert_eq!(back.steps, 26);
        let m = parse_meta(r#"{"format": 1, "dt": 0.3333, "steps": 26}"#).unwrap();
        assert_eq!(m.steps, 26);
        let tiny = Meta::new(1e-300, 1);
        assert_eq!(parse_meta(&render_meta(&tiny)).unwrap(), tiny);
        assert!(!render_meta(&tiny).contains(PRIOR_FROM_DETECTION));
        let from_detection = Meta { prior_from_detection: true, ..m };
        assert_eq!(parse_meta(&render_meta(&from_detection)).unwrap(), from_detection);
        let m = parse_meta(r#"{"format": 1, "dt": 0.1, "steps": 2, "prior_from_detection": false}"#).unwrap();
        assert!(!m.prior_from_detection);
    }

    #[test]
    fn errors_name_line_and_field() {
        let e = parse_meta("{\n\"format\": 1,\n\"dt\": -1,\n\"steps\": 3}").unwrap_err();
        assert_eq!((e.line(), e.column()), (Some(3), Some("dt")));
        let e = parse_meta("{\"format\": 2, \"dt\": 1, \"steps\": 3}").unwrap_err();
        assert_eq!(e.column(), Some("format"));
        let e = parse_meta("{\"format\": 1, \"dt\": 1, \"steps\": 0}").unwrap_err();
        assert_eq!(e.column(), Some("steps"));
        let e = parse_meta("{\"format\": 1, \"dt\": 1}").unwrap_err();
        assert_eq!(e.column(), Some("steps"));
        let e = parse_meta("{\"format\": 1, \"dt\": NaN, \"steps\": 2}").unwrap_err();
        assert_eq!(e.column(), Some("dt"));
        let e = parse_meta("{\"format\": 1, \"dt\": 1, \"steps\": 2, \"prior_from_detection\": 1}").unwrap_err();
        assert_eq!(e.column(), Some("prior_from_detection"));
        let e = parse_meta("{\"format\": 1, \"dt\": 1, \"steps\": 2, \"x\": 1}").unwrap_err();
        assert_eq!(e.column(), Some("x"));
        assert!(parse_meta("{\"format\": 1, \"dt\": 1, \"steps\": 2").is_err());
        assert!(parse_meta("").is_err());
        assert!(parse_meta("{\"format\": 1, \"dt\": [1, {2]], \"steps\": 2}").is_err());
    }
}
