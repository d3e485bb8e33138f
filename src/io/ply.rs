//! PLY: the header, a record walker shared by every element and encoding, and the
//! Gaussian reader with its fast path for 3DGS `point_cloud.ply` files (docs/formats.md).

use std::io::{self, BufRead, BufReader, Read};
use std::path::Path;

use super::chunked::{Chunked, CHUNK};
use super::error::{Error, Position};
use super::input::{open_input, Input};

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
    fn offset(&self, i: usize) -> usize {
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
    fn fixed_data_len(&self) -> Option<u128> {
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

impl Element {
    /// The fewest bytes one record can take: binary, its scalars and list counts (a list
    /// may be empty); ASCII, one character and one separator per value.
    fn min_record_len(&self, encoding: Encoding) -> u64 {
        self.props
            .iter()
            .map(|p| match (encoding, p.kind) {
                (Encoding::Ascii, _) => 2,
                (_, PropKind::Scalar(s)) => s.size() as u64,
                (_, PropKind::List { count, .. }) => count.size() as u64,
            })
            .sum()
    }
}

impl Element {
    /// The most records of this element that `data_len` bytes can hold: what a reader may
    /// reserve, so a count of 2^64 - 1 costs nothing until the data runs out (and the walk
    /// then stops with a truncation error naming the record).
    pub(crate) fn max_records(&self, encoding: Encoding, data_len: u64) -> usize {
        // +1: the last ASCII value needs no separator after it.
        let most = (data_len + 1) / self.min_record_len(encoding).max(1);
        self.count.min(most.try_into().unwrap_or(usize::MAX))
    }
}

/// Where a record is, in the terms its encoding can name.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Loc {
    pub(crate) index: usize,
    pub(crate) byte: Option<u64>,
    pub(crate) line: Option<usize>,
}

impl Loc {
    pub(crate) fn position(&self, element: &str) -> Position {
        match self.line {
            Some(l) => Position::Line(l),
            None => Position::record(element, self.index, self.byte),
        }
    }
}

/// ASCII body, one record per line. The PLY spec only asks for whitespace between
/// values, but every writer puts one record on a line, and holding each record to its line
/// is what catches a header that drops a property (the values would shift silently).
pub(crate) struct Rows<R> {
    inner: R,
    line: String,
    line_no: usize,
}

impl<R: BufRead> Rows<R> {
    fn new(inner: R, first_line: usize) -> Self {
        Rows {
            inner,
            line: String::new(),
            line_no: first_line - 1,
        }
    }

    /// Reads the next line that is not blank into `self.line`; `Ok(false)` at the end.
    fn next(&mut self) -> io::Result<bool> {
        loop {
            self.line.clear();
            if self.inner.read_line(&mut self.line)? == 0 {
                return Ok(false);
            }
            self.line_no += 1;
            if !self.line.trim_ascii().is_empty() {
                return Ok(true);
            }
        }
    }
}

/// The data section of a PLY file, in either encoding.
pub(crate) enum Body<R: Read> {
    Binary { ch: Chunked<R>, big: bool },
    Ascii(Rows<BufReader<io::Chain<io::Cursor<Vec<u8>>, R>>>),
}

impl<R: Read> Body<R> {
    /// `ch` positioned just after the header.
    pub(crate) fn new(ch: Chunked<R>, header: &Header, header_lines: usize) -> Self {
        match header.encoding {
            Encoding::BinaryLe => Body::Binary { ch, big: false },
            Encoding::BinaryBe => Body::Binary { ch, big: true },
            Encoding::Ascii => Body::Ascii(Rows::new(
                BufReader::with_capacity(1 << 16, ch.into_rest()),
                header_lines + 1,
            )),
        }
    }

    /// Walks every record of `elem`, handing `f` the values of the properties `wanted`
    /// (scalar properties, by index) as f64.
    pub(crate) fn for_each(
        &mut self,
        path: &Path,
        elem: &Element,
        wanted: &[usize],
        mut f: impl FnMut(Loc, &[f64]) -> Result<(), Error>,
    ) -> Result<(), Error> {
        let mut vals = vec![0.0f64; wanted.len()];
        // For each property: the slot in `vals` it fills, if wanted.
        let mut slot = vec![None; elem.props.len()];
        for (k, &w) in wanted.iter().enumerate() {
            slot[w] = Some(k);
        }
        let read_err = |e: io::Error| Error::io(path, "read", e);
        match self {
            Body::Binary { ch, big } => {
                let big = *big;
                if let Some(stride) = elem.stride().filter(|&s| s > 0) {
                    let offs: Vec<(usize, Scalar)> = wanted
                        .iter()
                        .map(|&w| match elem.props[w].kind {
                            PropKind::Scalar(s) => (elem.offset(w), s),
                            // Unreachable: a fixed stride means the element has no lists.
                            PropKind::List { .. } => (0, Scalar::U8),
                        })
                        .collect();
                    let mut index = 0usize;
                    while index < elem.count {
                        let avail = ch.available().len() / stride;
                        if avail == 0 {
                            if !ch.ensure(stride).map_err(read_err)? {
                                return Err(short_record(path, elem, index, ch.offset()));
                            }
                            continue;
                        }
                        let n = avail.min(elem.count - index);
                        let base = ch.offset();
                        for (k, rec) in ch.available()[..n * stride]
                            .chunks_exact(stride)
                            .enumerate()
                        {
                            for (v, &(o, s)) in vals.iter_mut().zip(&offs) {
                                *v = s.decode(&rec[o..], big);
                            }
                            let loc = Loc {
                                index: index + k,
                                byte: Some(base + (k * stride) as u64),
                                line: None,
                            };
                            f(loc, &vals)?;
                        }
                        ch.consume(n * stride);
                        index += n;
                    }
                    return Ok(());
                }
                for index in 0..elem.count {
                    let loc = Loc {
                        index,
                        byte: Some(ch.offset()),
                        line: None,
                    };
                    for (p, s) in elem.props.iter().zip(&slot) {
                        match p.kind {
                            PropKind::Scalar(t) => {
                                if !ch.ensure(t.size()).map_err(read_err)? {
                                    return Err(short_record(path, elem, index, ch.offset()));
                                }
                                if let Some(k) = s {
                                    vals[*k] = t.decode(ch.available(), big);
                                }
                                ch.consume(t.size());
                            }
                            PropKind::List { count, item } => {
                                if !ch.ensure(count.size()).map_err(read_err)? {
                                    return Err(short_record(path, elem, index, ch.offset()));
                                }
                                let n = count.decode(ch.available(), big);
                                if n < 0.0 {
                                    return Err(Error::parse(
                                        path,
                                        Position::record(&elem.name, index, Some(ch.offset())),
                                        format!("list `{}` has negative length {n}", p.name),
                                    ));
                                }
                                ch.consume(count.size());
                                let bytes = n as u64 * item.size() as u64;
                                if ch.skip(bytes).map_err(read_err)? < bytes {
                                    return Err(short_record(path, elem, index, ch.offset()));
                                }
                            }
                        }
                    }
                    f(loc, &vals)?;
                }
                Ok(())
            }
            Body::Ascii(rows) => {
                for index in 0..elem.count {
                    let more = rows.next().map_err(|e| {
                        ascii_read_error(path, rows, &format!("{} {index}: ", elem.name), e)
                    })?;
                    let line = rows.line_no;
                    if !more {
                        return Err(Error::truncated(
                            path,
                            Position::Line(line + 1),
                            format!(
                                "the header promises {} `{}` records but the data ends after {index}",
                                elem.count, elem.name
                            ),
                        ));
                    }
                    let row = Row {
                        path,
                        elem,
                        index,
                        line,
                        text: &rows.line,
                    };
                    let mut toks = rows.line.split_ascii_whitespace();
                    let mut used = 0usize;
                    for (p, s) in elem.props.iter().zip(&slot) {
                        match p.kind {
                            PropKind::Scalar(_) => {
                                let tok = row.next(&mut toks, &mut used, "property", p)?;
                                if let Some(k) = s {
                                    vals[*k] = row.number(tok, "property", p)?;
                                }
                            }
                            PropKind::List { .. } => {
                                let label = "the length of list";
                                let tok = row.next(&mut toks, &mut used, label, p)?;
                                let n = row.number(tok, label, p)?;
                                if n < 0.0 || n.fract() != 0.0 {
                                    return Err(Error::parse(
                                        path,
                                        Position::LineValue { line, value: used },
                                        format!(
                                            "{} {index}: list `{}` has length {n}",
                                            elem.name, p.name
                                        ),
                                    ));
                                }
                                // Bounded by the values on the line: a missing one stops it.
                                for _ in 0..n as u64 {
                                    row.next(&mut toks, &mut used, "an item of list", p)?;
                                }
                            }
                        }
                    }
                    if toks.next().is_some() {
                        return Err(
                            row.mismatch(format!("the header's properties take {used} values"))
                        );
                    }
                    let loc = Loc {
                        index,
                        byte: None,
                        line: Some(line),
                    };
                    f(loc, &vals)?;
                }
                Ok(())
            }
        }
    }

    /// After the last element: the data must end here. Bytes or rows left over mean the
    /// header's counts (or its layout) do not match the data.
    pub(crate) fn finish(&mut self, path: &Path, total: Option<u64>) -> Result<(), Error> {
        match self {
            Body::Binary { ch, .. } => {
                if ch.ensure(1).map_err(|e| Error::io(path, "read", e))? {
                    let at = ch.offset();
                    let extra = match total {
                        Some(t) => format!("{} bytes", t.saturating_sub(at)),
                        None => "data".to_string(),
                    };
                    return Err(Error::parse(
                        path,
                        Position::Byte(at),
                        format!(
                            "{extra} after the last element the header declares (a wrong count in the header, or a property missing from it)"
                        ),
                    ));
                }
            }
            Body::Ascii(rows) => {
                if rows
                    .next()
                    .map_err(|e| ascii_read_error(path, rows, "", e))?
                {
                    return Err(Error::parse(
                        path,
                        Position::Line(rows.line_no),
                        "a row after the last element the header declares (a count in the header is smaller than the data)",
                    ));
                }
            }
        }
        Ok(())
    }

    /// Skips every record of `elem` (an element we do not need, before the one we do).
    pub(crate) fn skip(&mut self, path: &Path, elem: &Element) -> Result<(), Error> {
        if elem.props.is_empty() {
            return Ok(());
        }
        if let (Body::Binary { ch, .. }, Some(stride)) = (&mut *self, elem.stride()) {
            let bytes = (stride as u64).saturating_mul(elem.count as u64);
            let start = ch.offset();
            let done = ch.skip(bytes).map_err(|e| Error::io(path, "read", e))?;
            if done < bytes {
                let index = (done / stride as u64) as usize;
                return Err(short_record(
                    path,
                    elem,
                    index,
                    start + index as u64 * stride as u64,
                ));
            }
            return Ok(());
        }
        self.for_each(path, elem, &[], |_, _| Ok(()))
    }
}

fn short_record(path: &Path, elem: &Element, index: usize, byte: u64) -> Error {
    Error::truncated(
        path,
        Position::record(&elem.name, index, Some(byte)),
        format!(
            "the header promises {} {} records but the data stops inside {} {index}",
            elem.count, elem.name, elem.name
        ),
    )
}

/// One ASCII record (a line), for reading its values and naming them in messages.
struct Row<'a> {
    path: &'a Path,
    elem: &'a Element,
    index: usize,
    line: usize,
    text: &'a str,
}

impl<'a> Row<'a> {
    fn mismatch(&self, what: String) -> Error {
        let found = self.text.split_ascii_whitespace().count();
        Error::parse(
            self.path,
            Position::Line(self.line),
            format!(
                "{} {}: {what}, but the row has {found} values (the header's properties and the rows disagree)",
                self.elem.name, self.index
            ),
        )
    }

    fn next<'t>(
        &self,
        toks: &mut impl Iterator<Item = &'t str>,
        used: &mut usize,
        label: &str,
        p: &Property,
    ) -> Result<&'t str, Error> {
        *used += 1;
        toks.next()
            .ok_or_else(|| self.mismatch(format!("{label} `{}` is value {used}", p.name)))
    }

    fn number(&self, tok: &str, label: &str, p: &Property) -> Result<f64, Error> {
        tok.parse::<f64>().map_err(|_| {
            Error::parse(
                self.path,
                Position::Line(self.line),
                format!(
                    "{} {}, {label} `{}`: `{tok}` is not a number",
                    self.elem.name, self.index, p.name
                ),
            )
        })
    }
}

/// `read_line` refuses bytes that are not UTF-8: binary data in an ASCII body.
/// `record` names the record being read (`"vertex 0: "`), or is empty.
fn ascii_read_error<R>(path: &Path, rows: &Rows<R>, record: &str, err: io::Error) -> Error {
    if err.kind() == io::ErrorKind::InvalidData {
        Error::parse(
            path,
            Position::Line(rows.line_no + 1),
            format!("{record}the ASCII PLY body holds bytes that are not text (binary data with an `ascii` header?)"),
        )
    } else {
        Error::io(path, "read", err)
    }
}

/// Options for [`read_gaussians`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlyOptions {
    /// Keep only Gaussians with `sigmoid(opacity) >= min_opacity` (3DGS stores the logit).
    pub min_opacity: Option<f64>,
    /// Make a NaN or infinite center an error instead of a counted, skipped Gaussian.
    pub strict: bool,
}

/// The Gaussian centers of a PLY model and what was dropped on the way.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GaussianCloud {
    pub centers: Vec<[f32; 3]>,
    /// The header's format line without `format`, e.g. `"binary_little_endian 1.0"`.
    pub format: String,
    /// Records in the `vertex` element, before anything was dropped.
    pub vertex_count: usize,
    /// Property names of the `vertex` element, in file order.
    pub properties: Vec<String>,
    pub skipped_nonfinite: usize,
    pub dropped_low_opacity: usize,
    /// One line each, naming the file (the NaN-center warning of docs/formats.md, trailing data).
    pub warnings: Vec<String>,
}

/// Collects centers and the counts of what was dropped; one per read.
struct Collect<'a> {
    path: &'a Path,
    centers: Vec<[f32; 3]>,
    min_opacity: Option<OpacityCut>,
    strict: bool,
    nonfinite: usize,
    first_nonfinite: Option<Position>,
    low: usize,
}

impl Collect<'_> {
    /// Takes one Gaussian; `loc` is only turned into a position on the rare bad record.
    #[inline(always)]
    fn push(
        &mut self,
        c: [f32; 3],
        opacity: f32,
        loc: impl FnOnce() -> Position,
    ) -> Result<(), Error> {
        if !(c[0].is_finite() && c[1].is_finite() && c[2].is_finite()) {
            let pos = loc();
            if self.strict {
                return Err(Error::strict_center(self.path, pos, c));
            }
            self.nonfinite += 1;
            self.first_nonfinite.get_or_insert(pos);
            return Ok(());
        }
        if let Some(cut) = &self.min_opacity {
            if !cut.keeps(opacity) {
                self.low += 1;
                return Ok(());
            }
        }
        self.centers.push(c);
        Ok(())
    }
}

#[inline(always)]
fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

/// `sigmoid(x) >= t` without an `exp` per Gaussian (it halved the read speed): sigmoid is
/// increasing, so `x` is compared with `logit(t)`, and only a logit within rounding
/// distance of the threshold takes the exact test, so the answer is the same.
#[derive(Clone, Copy, Debug)]
struct OpacityCut {
    t: f64,
    /// NaN where `logit(t)` is too ill-conditioned to trust (t near 0 or 1).
    logit: f64,
}

impl OpacityCut {
    fn new(t: f64) -> Self {
        let logit = if t > 1e-6 && t < 1.0 - 1e-6 {
            (t / (1.0 - t)).ln()
        } else {
            f64::NAN
        };
        OpacityCut { t, logit }
    }

    #[inline(always)]
    fn keeps(&self, x: f32) -> bool {
        let x = x as f64;
        let d = x - self.logit;
        // NaN (either side) fails this and takes the exact test, where NaN opacity is dropped.
        if d.abs() > 1e-9 * (1.0 + self.logit.abs()) {
            d > 0.0
        } else {
            sigmoid(x) >= self.t
        }
    }
}

#[inline(always)]
fn f32_le(rec: &[u8], o: usize) -> f32 {
    f32::from_le_bytes([rec[o], rec[o + 1], rec[o + 2], rec[o + 3]])
}

/// Reads the Gaussian centers (`vertex` x, y, z) of a PLY file.
///
/// Memory stays at the 12 bytes per kept center plus one 1 MiB read buffer: records are
/// decoded straight out of the buffer. NaN/Inf centers are skipped and counted with one
/// warning (an error with `strict`); a file with no usable Gaussian is an error.
pub fn read_gaussians(path: &Path, opts: &PlyOptions) -> Result<GaussianCloud, Error> {
    match open_input(path)? {
        Input::File { file, len } => gaussians_from(path, file.take(len), len, opts),
        Input::Bytes(b) => gaussians_from(path, &b[..], b.len() as u64, opts),
    }
}

/// [`read_gaussians`] on bytes already in memory; `path` names them in messages.
pub fn parse_gaussians(
    path: &Path,
    bytes: &[u8],
    opts: &PlyOptions,
) -> Result<GaussianCloud, Error> {
    gaussians_from(path, bytes, bytes.len() as u64, opts)
}

/// The Gaussian reader over a stream of exactly `file_len` bytes.
fn gaussians_from<R: Read>(
    path: &Path,
    input: R,
    file_len: u64,
    opts: &PlyOptions,
) -> Result<GaussianCloud, Error> {
    if file_len == 0 {
        return Err(Error::Empty {
            path: path.to_path_buf(),
        });
    }
    let mut ch = Chunked::new(input, CHUNK.min(file_len as usize + 1), 0);
    ch.fill().map_err(|e| Error::io(path, "read", e))?;
    // A byte-order mark from a Windows editor: skipped here as in the line reader, so
    // `info` and `eval` agree about such a file.
    let bom = if ch.available().starts_with(BOM) {
        ch.consume(BOM.len());
        BOM.len()
    } else {
        0
    };
    let head = ch.available();
    if !head.starts_with(b"ply") {
        return Err(Error::unknown(
            path,
            "Gaussians are read from PLY files, and this file does not start with `ply`",
        ));
    }
    let header = parse_header(path, head, (bom + head.len()) as u64 == file_len)?;
    let header_lines = head[..header.len].iter().filter(|&&b| b == b'\n').count();
    ch.consume(header.len);

    let Some(vi) = header.element("vertex") else {
        return Err(Error::missing(
            path,
            "the PLY has no `vertex` element, so it holds no Gaussians",
        ));
    };
    let vertex = &header.elements[vi];
    let scalar_prop = |name: &str| -> Result<(usize, Scalar), Error> {
        match vertex.prop(name).map(|i| (i, vertex.props[i].kind)) {
            Some((i, PropKind::Scalar(s))) => Ok((i, s)),
            Some(_) => Err(Error::parse(
                path,
                Position::Line(vertex.line),
                format!("vertex property `{name}` is a list, expected a number"),
            )),
            None => Err(Error::missing(
                path,
                format!(
                    "the `vertex` element has no `{name}` property (it has: {})",
                    vertex
                        .props
                        .iter()
                        .map(|p| p.name.as_str())
                        .collect::<Vec<_>>()
                        .join(" ")
                ),
            )),
        }
    };
    let x = scalar_prop("x")?;
    let y = scalar_prop("y")?;
    let z = scalar_prop("z")?;
    let opacity = match opts.min_opacity {
        Some(_) => Some(scalar_prop("opacity").map_err(|_| {
            Error::missing(
                path,
                "--min-opacity needs an `opacity` property on `vertex` (3DGS models have one; this file has none)",
            )
        })?),
        None => None,
    };
    if vertex.count == 0 {
        return Err(Error::no_data(
            path,
            "the model has no Gaussians (`element vertex 0`)",
        ));
    }

    let mut warnings = Vec::new();
    let data_start = (bom + header.len) as u64;
    let have = file_len.saturating_sub(data_start);
    let binary = header.encoding != Encoding::Ascii;
    // A lying header is caught before anything is allocated for it.
    if binary {
        if let Some(data_len) = header.fixed_data_len() {
            if (have as u128) < data_len {
                return Err(short_file(path, &header, data_start, file_len));
            }
            if have as u128 > data_len {
                return Err(Error::parse(
                    path,
                    Position::Byte(data_start + data_len as u64),
                    format!(
                        "{} bytes after the last element: the header's elements take {data_len} bytes, the file has {have} after the header (a property or a count missing from the header?)",
                        have as u128 - data_len
                    ),
                ));
            }
        }
    }
    let capacity = vertex.max_records(header.encoding, have);
    let mut col = Collect {
        path,
        centers: Vec::with_capacity(capacity),
        min_opacity: opts.min_opacity.map(OpacityCut::new),
        strict: opts.strict,
        nonfinite: 0,
        first_nonfinite: None,
        low: 0,
    };

    let fast = header.encoding == Encoding::BinaryLe
        && vertex.stride().is_some()
        && [Some(x), Some(y), Some(z), opacity]
            .iter()
            .flatten()
            .all(|p| p.1 == Scalar::F32);
    let mut body = Body::new(ch, &header, header_lines);
    for elem in &header.elements[..vi] {
        body.skip(path, elem)?;
    }
    match (&mut body, fast) {
        (Body::Binary { ch, .. }, true) => {
            let stride = vertex.stride().unwrap_or(0);
            let offs = [x.0, y.0, z.0].map(|i| vertex.offset(i));
            let oo = opacity.map(|o| vertex.offset(o.0));
            read_fast_le(path, ch, vertex, stride, offs, oo, &mut col)?;
        }
        _ => {
            let mut wanted = vec![x.0, y.0, z.0];
            wanted.extend(opacity.map(|o| o.0));
            body.for_each(path, vertex, &wanted, |loc, v| {
                let op = v.get(3).copied().unwrap_or(0.0) as f32;
                col.push([v[0] as f32, v[1] as f32, v[2] as f32], op, || {
                    loc.position("vertex")
                })
            })?;
        }
    }
    for elem in &header.elements[vi + 1..] {
        body.skip(path, elem)?;
    }
    body.finish(path, Some(file_len))?;

    if col.nonfinite > 0 {
        warnings.push(super::error::skipped_centers_warning(
            path,
            col.nonfinite,
            col.first_nonfinite.as_ref(),
        ));
    }
    if col.centers.is_empty() {
        return Err(Error::none_usable(
            path,
            vertex.count,
            col.nonfinite,
            col.low,
            opts.min_opacity,
        ));
    }
    col.centers.shrink_to_fit();
    Ok(GaussianCloud {
        centers: col.centers,
        format: header.format(),
        vertex_count: vertex.count,
        properties: vertex.props.iter().map(|p| p.name.clone()).collect(),
        skipped_nonfinite: col.nonfinite,
        dropped_low_opacity: col.low,
        warnings,
    })
}

/// The 3DGS hot loop: fixed stride, little-endian f32 x/y/z (and opacity) at offsets
/// computed once; each chunk is walked with `chunks_exact`, nothing is allocated.
fn read_fast_le<R: Read>(
    path: &Path,
    ch: &mut Chunked<R>,
    vertex: &Element,
    stride: usize,
    [ox, oy, oz]: [usize; 3],
    oo: Option<usize>,
    col: &mut Collect,
) -> Result<(), Error> {
    let mut index = 0usize;
    while index < vertex.count {
        let avail = ch.available().len() / stride;
        if avail == 0 {
            if !ch.ensure(stride).map_err(|e| Error::io(path, "read", e))? {
                return Err(short_record(path, vertex, index, ch.offset()));
            }
            continue;
        }
        let n = avail.min(vertex.count - index);
        let base = ch.offset();
        let bytes = &ch.available()[..n * stride];
        for (k, rec) in bytes.chunks_exact(stride).enumerate() {
            let c = [f32_le(rec, ox), f32_le(rec, oy), f32_le(rec, oz)];
            let op = match oo {
                Some(o) => f32_le(rec, o),
                None => 0.0,
            };
            col.push(c, op, || {
                Position::record("vertex", index + k, Some(base + (k * stride) as u64))
            })?;
        }
        ch.consume(n * stride);
        index += n;
    }
    Ok(())
}

/// The truncation error for a binary file shorter than its header's fixed-size elements
/// (whose data starts at byte `data_start`).
fn short_file(path: &Path, header: &Header, data_start: u64, file_len: u64) -> Error {
    let mut at = data_start;
    for e in &header.elements {
        let stride = e.stride().unwrap_or(0) as u64;
        let len = stride.saturating_mul(e.count as u64);
        if at.saturating_add(len) > file_len {
            let index = ((file_len.saturating_sub(at)) / stride.max(1)) as usize;
            return Error::truncated(
                path,
                Position::record(&e.name, index, Some(at + index as u64 * stride)),
                format!(
                    "the header promises {} {} records of {stride} bytes ({} bytes from byte {at}) but the file has {file_len} bytes, so it stops inside {} {index} (cut-short download or copy, or a wrong count in the header)",
                    e.count, e.name, len, e.name
                ),
            );
        }
        at += len;
    }
    Error::truncated(
        path,
        Position::Byte(file_len),
        "the data is shorter than the header says",
    )
}

/// Opens a PLY file for the line reader (small files; the whole file is in memory).
pub(crate) fn open_in_memory<'a>(
    path: &Path,
    bytes: &'a [u8],
) -> Result<(Header, Body<&'a [u8]>), Error> {
    let header = parse_header(path, bytes, true)?;
    let header_lines = bytes[..header.len].iter().filter(|&&b| b == b'\n').count();
    let have = (bytes.len() - header.len) as u64;
    if header.encoding != Encoding::Ascii {
        if let Some(data_len) = header.fixed_data_len() {
            if (have as u128) < data_len {
                return Err(short_file(
                    path,
                    &header,
                    header.len as u64,
                    bytes.len() as u64,
                ));
            }
        }
    }
    let rest = &bytes[header.len..];
    let ch = Chunked::new(rest, rest.len().clamp(1, CHUNK), header.len as u64);
    let body = Body::new(ch, &header, header_lines);
    Ok((header, body))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_with_lists_and_comments() {
        let text = b"ply\r\nformat binary_big_endian 1.0\r\ncomment made by hand\r\nelement face 2\r\nproperty list uchar int vertex_indices\r\nelement vertex 3\r\nproperty double x\r\nproperty float32 y\r\nproperty uint8 red\r\nend_header\r\nDATA";
        let h = parse_header(Path::new("h.ply"), text, true).unwrap();
        assert_eq!(h.encoding, Encoding::BinaryBe);
        assert_eq!(h.format(), "binary_big_endian 1.0");
        assert_eq!(h.len, text.len() - 4);
        assert_eq!(h.elements[0].stride(), None);
        let v = &h.elements[1];
        assert_eq!((v.name.as_str(), v.count, v.line), ("vertex", 3, 6));
        assert_eq!(v.stride(), Some(13));
        assert_eq!(v.offset(2), 12);
        assert_eq!(v.props[1].kind, PropKind::Scalar(Scalar::F32));
    }

    #[test]
    fn header_errors_name_the_line() {
        let p = Path::new("bad.ply");
        let e = parse_header(
            p,
            b"ply\nformat ascii 1.0\nelement vertex -3\nend_header\n",
            true,
        )
        .unwrap_err();
        assert_eq!(e.position(), Some(&Position::Line(3)));
        let e = parse_header(
            p,
            b"ply\nformat ascii 1.0\nelement vertex 3\nproperty half x\n",
            true,
        )
        .unwrap_err();
        assert!(
            e.to_string()
                .starts_with("bad.ply: line 4: unknown property type `half`"),
            "{e}"
        );
        let e = parse_header(p, b"ply\nformat ascii 1.0\nelement vertex 3\n", true).unwrap_err();
        assert!(
            matches!(
                e,
                Error::Truncated {
                    pos: Position::Line(4),
                    ..
                }
            ),
            "{e}"
        );
        let e = parse_header(p, b"ply\nelement vertex 3\nend_header\n", true).unwrap_err();
        assert!(e.to_string().contains("without a `format`"), "{e}");
    }

    #[test]
    fn scalar_decoding_both_endians() {
        assert_eq!(Scalar::I16.decode(&[0xff, 0xfe], false), -257.0);
        assert_eq!(Scalar::I16.decode(&[0xff, 0xfe], true), -2.0);
        assert_eq!(Scalar::U32.decode(&7u32.to_be_bytes(), true), 7.0);
        assert_eq!(Scalar::F64.decode(&1.5f64.to_le_bytes(), false), 1.5);
        assert_eq!(Scalar::I8.decode(&[0x80], false), -128.0);
    }

    #[test]
    fn sigmoid_threshold_is_on_the_probability() {
        assert_eq!(sigmoid(0.0), 0.5);
        assert!((sigmoid(2.0) - 0.880797).abs() < 1e-6);
    }

    #[test]
    fn the_logit_cut_agrees_with_the_sigmoid_everywhere() {
        // Thresholds that are exactly sigmoid of an f32 put Gaussians right on the boundary.
        let thresholds = [
            0.5,
            sigmoid(2.0),
            sigmoid(-3.25),
            0.1,
            0.999,
            1e-7,
            1.0 - 1e-9,
            0.0,
            1.0,
        ];
        for t in thresholds {
            let cut = OpacityCut::new(t);
            let l = (t / (1.0 - t)).ln() as f32;
            let mut xs = vec![
                f32::NAN,
                f32::INFINITY,
                f32::NEG_INFINITY,
                0.0,
                -0.0,
                40.0,
                -40.0,
            ];
            for k in -3i32..=3 {
                if l.is_finite() {
                    xs.push(f32::from_bits((l.to_bits() as i32 + k) as u32));
                }
            }
            xs.extend((-200..=200).map(|i| i as f32 * 0.05));
            for x in xs {
                assert_eq!(cut.keeps(x), sigmoid(x as f64) >= t, "t {t}, x {x}");
            }
        }
    }
}
