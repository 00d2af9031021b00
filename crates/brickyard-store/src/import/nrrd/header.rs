//! NRRD header grammar: the magic line, `field: value` lines (names
//! matched ignoring case, spaces and underscores), comments, `key:=value`
//! pairs, the `LIST` of data files, the blank line that ends the header; and
//! the syntax of values (vectors, quoted strings, printf-style file names).
//! What the fields mean is `fields`.

use crate::error::{IoContext, Result, StoreError};
use std::io::{BufRead, BufReader, Read};
use std::path::Path;

/// Largest header accepted (a `LIST` of data files can make it long).
const MAX_HEADER_BYTES: u64 = 16 << 20;
/// Longest header line accepted.
const MAX_LINE_BYTES: u64 = 1 << 20;

/// The raw lines of a header.
pub(super) struct Header {
    /// `(canonical name, name as written, value)` of each known field.
    pub(super) fields: Vec<(&'static str, String, String)>,
    /// File names following `data file: LIST`.
    pub(super) list: Vec<String>,
    /// Offset just past the blank line that ends the header, if there is one.
    pub(super) end: Option<u64>,
}

impl Header {
    /// `(name as written, value)` of a field.
    pub(super) fn get(&self, key: &str) -> Option<(&str, &str)> {
        self.fields
            .iter()
            .find(|f| f.0 == key)
            .map(|f| (f.1.as_str(), f.2.as_str()))
    }
}

/// The spec name of a field, from a name matched ignoring case, spaces and
/// underscores. `None` for an unknown field.
fn canonical_field(name: &str) -> Option<&'static str> {
    let n: String = name
        .chars()
        .filter(|c| !matches!(c, ' ' | '_' | '\t'))
        .collect::<String>()
        .to_ascii_lowercase();
    Some(match n.as_str() {
        "type" => "type",
        "dimension" => "dimension",
        "sizes" => "sizes",
        "endian" => "endian",
        "encoding" => "encoding",
        "byteskip" => "byte skip",
        "lineskip" => "line skip",
        "datafile" => "data file",
        "space" => "space",
        "spacedimension" => "space dimension",
        "spacedirections" => "space directions",
        "spaceorigin" => "space origin",
        "spacings" => "spacings",
        "kinds" => "kinds",
        "spaceunits" => "space units",
        "units" => "units",
        "content" => "content",
        "thicknesses" => "thicknesses",
        "axismins" => "axis mins",
        "axismaxs" => "axis maxs",
        "centers" | "centerings" => "centers",
        "labels" => "labels",
        "min" => "min",
        "max" => "max",
        "oldmin" => "old min",
        "oldmax" => "old max",
        "sampleunits" => "sample units",
        "measurementframe" => "measurement frame",
        "blocksize" => "block size",
        "number" => "number",
        _ => return None,
    })
}

/// Read one line (with its `\n`) of at most `MAX_LINE_BYTES`; returns the
/// number of bytes read, 0 at end of file.
fn read_line(r: &mut impl BufRead, buf: &mut Vec<u8>) -> std::io::Result<u64> {
    buf.clear();
    let n = r.take(MAX_LINE_BYTES + 1).read_until(b'\n', buf)?;
    Ok(n as u64)
}

fn trim_eol(line: &[u8]) -> &[u8] {
    let line = line.strip_suffix(b"\n").unwrap_or(line);
    line.strip_suffix(b"\r").unwrap_or(line)
}

pub(super) fn read_header(path: &Path, src: impl Read) -> Result<Header> {
    let mut r = BufReader::new(src);
    let mut line = Vec::new();
    let mut pos = read_line(&mut r, &mut line).at(path)?;

    // Magic.
    let first = trim_eol(&line).trim_ascii_end();
    let shown = String::from_utf8_lossy(&first[..first.len().min(24)]).into_owned();
    match first.strip_prefix(b"NRRD000") {
        Some([v @ b'1'..=b'5']) => {
            tracing::debug!("{}: NRRD000{}", path.display(), *v as char);
        }
        Some([b'6'..=b'9']) => {
            return Err(StoreError::unsupported(
                path,
                "magic",
                format!("{shown:?} is newer than NRRD0005, the latest version this reader knows"),
            ))
        }
        _ => {
            return Err(StoreError::invalid(
                path,
                "magic",
                format!("expected \"NRRD0001\"..\"NRRD0005\" on the first line, found {shown:?}"),
            ))
        }
    }

    let mut header = Header {
        fields: Vec::new(),
        list: Vec::new(),
        end: None,
    };
    let mut in_list = false;
    let mut lineno = 1usize;
    loop {
        if pos > MAX_HEADER_BYTES {
            return Err(StoreError::invalid(
                path,
                "header",
                format!("no blank line ends the header within its first {MAX_HEADER_BYTES} bytes"),
            ));
        }
        let n = read_line(&mut r, &mut line).at(path)?;
        if n == 0 {
            break; // end of file: a detached header may end without a blank line
        }
        lineno += 1;
        pos += n;
        if !line.ends_with(b"\n") && n > MAX_LINE_BYTES {
            return Err(StoreError::invalid(
                path,
                "header",
                format!("line {lineno} is longer than {MAX_LINE_BYTES} bytes"),
            ));
        }
        let raw = trim_eol(&line);
        if raw.is_empty() {
            header.end = Some(pos);
            break;
        }
        let Ok(text) = std::str::from_utf8(raw) else {
            return Err(StoreError::invalid(
                path,
                "header",
                format!(
                    "line {lineno} is not text (is the blank line that must end the header \
                     missing before the data?)"
                ),
            ));
        };
        if in_list {
            header.list.push(text.trim().to_string());
            continue;
        }
        if text.starts_with('#') {
            continue;
        }
        let kv = text.find(":=");
        let colon = text
            .find(": ")
            .or_else(|| text.ends_with(':').then(|| text.len() - 1))
            .or_else(|| text.find(':').filter(|&i| kv != Some(i)));
        let colon = match colon {
            Some(c) if kv.is_none_or(|k| c < k) => c,
            _ if kv.is_some() => continue, // key:=value
            _ => {
                return Err(StoreError::invalid(
                    path,
                    "header",
                    format!(
                        "line {lineno}: expected \"field: value\" or \"key:=value\", found {:?}",
                        truncate(text, 80)
                    ),
                ))
            }
        };
        let name = text[..colon].trim();
        let value = text[colon + 1..].trim();
        let Some(canon) = canonical_field(name) else {
            tracing::debug!("{}: ignoring unknown NRRD field {name:?}", path.display());
            continue;
        };
        if header.fields.iter().any(|f| f.0 == canon) {
            return Err(StoreError::invalid(
                path,
                name,
                format!("given twice (line {lineno})"),
            ));
        }
        if canon == "data file" && value.split_whitespace().next() == Some("LIST") {
            in_list = true;
        }
        header
            .fields
            .push((canon, name.to_string(), value.to_string()));
    }
    Ok(header)
}

pub(super) fn truncate(s: &str, n: usize) -> String {
    if s.chars().count() > n {
        let t: String = s.chars().take(n).collect();
        format!("{t}...")
    } else {
        s.to_string()
    }
}

/// Parse `(a,b,c) none (d,e,f)`; `None` on a syntax error.
pub(super) fn parse_vectors(s: &str) -> Option<Vec<Option<Vec<f64>>>> {
    let mut out = Vec::new();
    let mut rest = s.trim();
    while !rest.is_empty() {
        if rest
            .get(..4)
            .is_some_and(|w| w.eq_ignore_ascii_case("none"))
        {
            out.push(None);
            rest = rest[4..].trim_start();
            continue;
        }
        let r = rest.strip_prefix('(')?;
        let end = r.find(')')?;
        let v = r[..end]
            .split(',')
            .map(|t| t.trim().parse::<f64>().ok())
            .collect::<Option<Vec<f64>>>()?;
        out.push(Some(v));
        rest = r[end + 1..].trim_start();
    }
    Some(out)
}

/// Parse `"mm" "mm" ""`; `None` on a syntax error.
pub(super) fn parse_quoted(s: &str) -> Option<Vec<String>> {
    let mut out = Vec::new();
    let mut chars = s.trim().chars().peekable();
    loop {
        while chars.next_if(|c| c.is_whitespace()).is_some() {}
        match chars.next() {
            None => return Some(out),
            Some('"') => {}
            Some(_) => return None,
        }
        let mut word = String::new();
        loop {
            match chars.next()? {
                '"' => break,
                '\\' => word.push(chars.next()?),
                c => word.push(c),
            }
        }
        out.push(word);
    }
}

/// A printf-style file name with one integer conversion (`%d`, `%03i`, ...).
pub(super) struct NameFormat {
    prefix: String,
    suffix: String,
    left: bool,
    plus: bool,
    space: bool,
    zero: bool,
    width: usize,
    precision: Option<usize>,
}

impl NameFormat {
    pub(super) fn parse(f: &str) -> std::result::Result<NameFormat, String> {
        let mut prefix = String::new();
        let mut chars = f.chars().peekable();
        while let Some(c) = chars.next() {
            if c != '%' {
                prefix.push(c);
                continue;
            }
            if chars.next_if_eq(&'%').is_some() {
                prefix.push('%');
                continue;
            }
            let mut fmt = NameFormat {
                prefix,
                suffix: String::new(),
                left: false,
                plus: false,
                space: false,
                zero: false,
                width: 0,
                precision: None,
            };
            while let Some(flag) = chars.next_if(|c| matches!(c, '-' | '+' | ' ' | '0' | '#')) {
                match flag {
                    '-' => fmt.left = true,
                    '+' => fmt.plus = true,
                    ' ' => fmt.space = true,
                    '0' => fmt.zero = true,
                    _ => {}
                }
            }
            let digits = |chars: &mut std::iter::Peekable<std::str::Chars>| {
                let mut n = 0usize;
                while let Some(d) = chars.next_if(|c| c.is_ascii_digit()) {
                    n = n
                        .saturating_mul(10)
                        .saturating_add(d as usize - '0' as usize);
                }
                n.min(64)
            };
            fmt.width = digits(&mut chars);
            if chars.next_if_eq(&'.').is_some() {
                fmt.precision = Some(digits(&mut chars));
            }
            while chars
                .next_if(|c| matches!(c, 'h' | 'l' | 'j' | 'z' | 't'))
                .is_some()
            {}
            match chars.next() {
                Some('d' | 'i' | 'u') => {}
                other => {
                    return Err(format!(
                        "the format {f:?} must have one integer conversion (%d, %i or %u), \
                         found {}",
                        other.map_or("the end".to_string(), |c| format!("%{c}"))
                    ))
                }
            }
            while let Some(c) = chars.next() {
                if c == '%' {
                    if chars.next_if_eq(&'%').is_some() {
                        fmt.suffix.push('%');
                        continue;
                    }
                    return Err(format!("the format {f:?} has more than one % conversion"));
                }
                fmt.suffix.push(c);
            }
            return Ok(fmt);
        }
        Err(format!(
            "the format {f:?} has no integer conversion such as %03d"
        ))
    }

    pub(super) fn render(&self, v: i64) -> String {
        let mut digits = v.unsigned_abs().to_string();
        if let Some(p) = self.precision {
            if digits.len() < p {
                digits = "0".repeat(p - digits.len()) + &digits;
            }
        }
        let sign = if v < 0 {
            "-"
        } else if self.plus {
            "+"
        } else if self.space {
            " "
        } else {
            ""
        };
        let len = sign.len() + digits.len();
        let pad = self.width.saturating_sub(len);
        let body = if self.left {
            format!("{sign}{digits}{}", " ".repeat(pad))
        } else if self.zero && self.precision.is_none() {
            format!("{sign}{}{digits}", "0".repeat(pad))
        } else {
            format!("{}{sign}{digits}", " ".repeat(pad))
        };
        format!("{}{body}{}", self.prefix, self.suffix)
    }
}
