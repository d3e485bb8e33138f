//! The PLY header: format, elements and their properties, read and checked before any
//! data (docs/formats.md).

use std::path::Path;

use super::super::error::{Error, Position};

/// The UTF-8 byte-order mark some Windows editors put before text.
pub(crate) const BOM: &[u8] = b"\xEF\xBB\xBF";

/// Headers longer than this are not PLY headers (a 3DGS header is about 1.5 KB).
const MAX_HEADER: usize = 1 << 20;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Encoding {
    Ascii,
    BinaryLe,
    BinaryBe,
}

impl Encoding {
    pub(crate) fn name(self) -> &'static str {
        match self {
            Encoding::Ascii => "ascii",
            Encoding::BinaryLe => "binary_little_endian",
            Encoding::BinaryBe => "binary_big_endian",
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    /// Both spellings of the PLY spec (`float` and `float32`, ...).
    fn parse(s: &str) -> Option<Scalar> {
        Some(match s {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    pub(crate) fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    pub(crate) fn name(self) -> &'static str {
        match self {
            Scalar::I8 => "char",
            Scalar::U8 => "uchar",
            Scalar::I16 => "short",
            Scalar::U16 => "ushort",
            Scalar::I32 => "int",
            Scalar::U32 => "uint",
            Scalar::F32 => "float",
            Scalar::F64 => "double",
        }
    }

    fn is_integer(self) -> bool {
        !matches!(self, Scalar::F32 | Scalar::F64)
    }

    /// Decodes one value from the front of `b` (at least `size()` bytes long).
    #[inline]
    pub(crate) fn decode(self, b: &[u8], big: bool) -> f64 {
        macro_rules! num {
            ($t:ty, $n:expr) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(&b[..$n]);
                (if big {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                }) as f64
            }};
        }
        match self {
            Scalar::I8 => b[0] as i8 as f64,
            Scalar::U8 => b[0] as f64,
            Scalar::I16 => num!(i16, 2),
            Scalar::U16 => num!(u16, 2),
            Scalar::I32 => num!(i32, 4),
            Scalar::U32 => num!(u32, 4),
            Scalar::F32 => num!(f32, 4),
            Scalar::F64 => num!(f64, 8),
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum PropKind {
    Scalar(Scalar),
    List { count: Scalar, item: Scalar },
}

#[derive(Clone, Debug)]
pub(crate) struct Property {
    pub(crate) name: String,
    pub(crate) kind: PropKind,
}

impl Property {
    /// As written in a header, for `info`.
    pub(crate) fn describe(&self) -> String {
        match self.kind {
            PropKind::Scalar(s) => format!("{} {}", s.name(), self.name),
            PropKind::List { count, item } => {
                format!("list {} {} {}", count.name(), item.name(), self.name)
            }
        }
    }
}

#[derive(Clone, Debug)]
pub(crate) struct Element {
    pub(crate) name: String,
    pub(crate) count: usize,
    pub(crate) props: Vec<Property>,
    /// Header line that declared the element, for messages.
    pub(crate) line: usize,
}

impl Element {
    /// Bytes per binary record when no property is a list.
    pub(crate) fn stride(&self) -> Option<usize> {
        self.props.iter().try_fold(0usize, |acc, p| match p.kind {
            PropKind::Scalar(s) => Some(acc + s.size()),
            PropKind::List { .. } => None,
        })
    }

    pub(crate) fn prop(&self, name: &str) -> Option<usize> {
        self.props.iter().position(|p| p.name == name)
    }

    /// Byte offset of property `i` inside a fixed-size record.
    pub(crate) fn offset(&self, i: usize) -> usize {
        self.props[..i]
            .iter()
            .map(|p| match p.kind {
                PropKind::Scalar(s) => s.size(),
                PropKind::List { .. } => 0,
            })
            .sum()
    }
}

#[derive(Clone, Debug)]
pub(crate) struct Header {
    pub(crate) encoding: Encoding,
    pub(crate) version: String,
    pub(crate) elements: Vec<Element>,
    /// Bytes up to and including the `end_header` line.
    pub(crate) len: usize,
}

impl Header {
    /// `"binary_little_endian 1.0"`.
    pub(crate) fn format(&self) -> String {
        format!("{} {}", self.encoding.name(), self.version)
    }

    pub(crate) fn element(&self, name: &str) -> Option<usize> {
        self.elements.iter().position(|e| e.name == name)
    }

    /// Total data bytes when every element has fixed-size records (binary only).
    pub(crate) fn fixed_data_len(&self) -> Option<u128> {
        self.elements.iter().try_fold(0u128, |acc, e| {
            e.stride().map(|s| acc + s as u128 * e.count as u128)
        })
    }
}

/// Parses the header at the start of `bytes` (which need not hold the whole file).
pub(crate) fn parse_header(path: &Path, bytes: &[u8], at_eof: bool) -> Result<Header, Error> {
    let mut start = 0usize;
    let mut line_no = 0usize;
    let mut encoding: Option<(Encoding, String)> = None;
    let mut elements: Vec<Element> = Vec::new();
    loop {
        let Some(nl) = bytes[start..].iter().position(|&b| b == b'\n') else {
            let msg = if at_eof && bytes.len() < MAX_HEADER {
                "the header has no `end_header` line (file cut short?)".to_string()
            } else {
                format!("no `end_header` in the first {} bytes", bytes.len())
            };
            return Err(Error::truncated(path, Position::Line(line_no + 1), msg));
        };
        line_no += 1;
        let raw = &bytes[start..start + nl];
        start += nl + 1;
        let Ok(text) = std::str::from_utf8(raw) else {
            return Err(Error::parse(
                path,
                Position::Line(line_no),
                "the header line is not text",
            ));
        };
        let text = text.trim_end_matches('\r');
        let toks: Vec<&str> = text.split_whitespace().collect();
        let bad = |msg: String| Error::parse(path, Position::Line(line_no), msg);
        if line_no == 1 {
            if text.trim() != "ply" {
                return Err(Error::unknown(path, "the first line is not `ply`"));
            }
            continue;
        }
        match toks.first().copied() {
            None => {}
            Some("comment") | Some("obj_info") => {}
            Some("format") => {
                if toks.len() != 3 {
                    return Err(bad(format!(
                        "expected `format <encoding> 1.0`, found `{text}`"
                    )));
                }
                let enc = match toks[1] {
                    "ascii" => Encoding::Ascii,
                    "binary_little_endian" => Encoding::BinaryLe,
                    "binary_big_endian" => Encoding::BinaryBe,
                    other => {
                        return Err(bad(format!(
                            "unknown encoding `{other}` (ascii, binary_little_endian, binary_big_endian)"
                        )))
                    }
                };
                encoding = Some((enc, toks[2].to_string()));
            }
            Some("element") => {
                if toks.len() != 3 {
                    return Err(bad(format!(
                        "expected `element <name> <count>`, found `{text}`"
                    )));
                }
                let count: usize = toks[2].parse().map_err(|_| {
                    bad(format!(
                        "element count `{}` is not a non-negative integer",
                        toks[2]
                    ))
                })?;
                if let Some(prev) = elements.iter().find(|e| e.name == toks[1]) {
                    return Err(bad(format!(
                        "a second `{}` element (the first is on line {}); which one holds the data?",
                        toks[1], prev.line
                    )));
                }
                check_has_props(path, elements.last())?;
                elements.push(Element {
                    name: toks[1].to_string(),
                    count,
                    props: Vec::new(),
                    line: line_no,
                });
            }
            Some("property") => {
                let Some(elem) = elements.last_mut() else {
                    return Err(bad("`property` before any `element`".to_string()));
                };
                let ty = |s: &str| {
                    Scalar::parse(s).ok_or_else(|| bad(format!("unknown property type `{s}`")))
                };
                let prop = match toks.as_slice() {
                    ["property", "list", ct, it, name] => {
                        let count = ty(ct)?;
                        if !count.is_integer() {
                            return Err(bad(format!("list count type `{ct}` is not an integer")));
                        }
                        Property {
                            name: name.to_string(),
                            kind: PropKind::List {
                                count,
                                item: ty(it)?,
                            },
                        }
                    }
                    ["property", t, name] => Property {
                        name: name.to_string(),
                        kind: PropKind::Scalar(ty(t)?),
                    },
                    _ => {
                        return Err(bad(format!(
                            "expected `property <type> <name>` or `property list <type> <type> <name>`, found `{text}`"
                        )))
                    }
                };
                if elem.props.iter().any(|p| p.name == prop.name) {
                    return Err(bad(format!(
                        "property `{}` of `{}` is declared twice",
                        prop.name, elem.name
                    )));
                }
                elem.props.push(prop);
            }
            Some("end_header") => {
                let Some((encoding, version)) = encoding else {
                    return Err(bad("`end_header` without a `format` line".to_string()));
                };
                check_has_props(path, elements.last())?;
                return Ok(Header {
                    encoding,
                    version,
                    elements,
                    len: start,
                });
            }
            Some(other) => return Err(bad(format!("unknown header keyword `{other}`"))),
        }
        if start >= MAX_HEADER {
            return Err(Error::parse(
                path,
                Position::Line(line_no),
                format!("no `end_header` in the first {MAX_HEADER} bytes"),
            ));
        }
    }
}

/// An element with records but no properties has no data to read (and a walk over its
/// `2^64 - 1` empty records would never end).
fn check_has_props(path: &Path, elem: Option<&Element>) -> Result<(), Error> {
    match elem {
        Some(e) if e.props.is_empty() && e.count > 0 => Err(Error::parse(
            path,
            Position::Line(e.line),
            format!(
                "element `{}` has {} records but no properties",
                e.name, e.count
            ),
        )),
        _ => Ok(()),
    }
}
