//! The record walker shared by every PLY element and encoding: binary records read in
//! chunks, ASCII records one per line, each located (byte or line) for its errors.

use std::io::{self, BufRead, BufReader, Read};
use std::path::Path;

use super::super::chunked::Chunked;
use super::super::error::{Error, Position};
use super::header::*;

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

pub(crate) fn short_record(path: &Path, elem: &Element, index: usize, byte: u64) -> Error {
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
