//! LIMAP `.npy` line files: an `N x 2 x 3` float array (f32 or f64, either byte order,
//! C or Fortran order). `N x 6` is read too, as it is the same numbers.

use std::path::Path;

use crate::geom::Segment;

use super::error::{Error, Position};
use super::format::{Detect, LineFormat, LineWriter, Origin, Parsed};
use super::limap::refuse_pickled_npy;
use super::write::write_atomic;

pub(crate) const MAGIC: &[u8] = b"\x93NUMPY";

pub(crate) static FORMAT: LineFormat = LineFormat {
    id: "npy",
    name: "NumPy .npy",
    extensions: &["npy"],
    summary: "LIMAP `.npy`: a float array N×2×3 (f32 or f64, either byte order); LIMAP's \
              pickled `.npy` (dicts of tracks) is refused with the line of Python that saves \
              a float array instead",
    help: None,
    hint: Some(".npy (N x 2 x 3 float)"),
    rank: 1,
    detect: Detect::Bytes(|p| p.bytes.starts_with(MAGIC)),
    parse: |path, bytes, _| {
        refuse_pickled_npy(path, bytes)?;
        let mut p = Parsed::new(Origin::Records("row"));
        p.segments = parse(path, bytes)?;
        Ok(p)
    },
    read_folder: None,
};

pub(crate) static WRITER: LineWriter = LineWriter {
    format: &FORMAT,
    ext: "npy",
    help: "`.npy`",
    write: |path, lines| {
        let bytes = encode(lines);
        write_atomic(path, |w| std::io::Write::write_all(w, &bytes))
    },
};

/// Parses a whole `.npy` file into segments (validity is checked by the caller).
pub(crate) fn parse(path: &Path, bytes: &[u8]) -> Result<Vec<Segment>, Error> {
    if bytes.len() < 10 || !bytes.starts_with(MAGIC) {
        return Err(Error::truncated(
            path,
            Position::Byte(bytes.len() as u64),
            "the .npy preamble (magic, version, header length) is incomplete",
        ));
    }
    let major = bytes[6];
    let (hlen, hstart) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err(Error::truncated(
                    path,
                    Position::Byte(bytes.len() as u64),
                    "the .npy preamble is incomplete",
                ));
            }
            (
                u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
                12,
            )
        }
        v => {
            return Err(Error::parse(
                path,
                Position::Byte(6),
                format!(".npy format version {v} is not supported (1, 2 or 3)"),
            ))
        }
    };
    let data_start = hstart + hlen;
    if bytes.len() < data_start {
        return Err(Error::truncated(
            path,
            Position::Byte(bytes.len() as u64),
            format!("the .npy header needs {hlen} bytes from byte {hstart}"),
        ));
    }
    let raw = &bytes[hstart..data_start];
    // The format ends the header with a newline after the padding: a length field that is
    // off by even one byte would otherwise shift every value (coordinates near 1e38).
    if raw.last() != Some(&b'\n') {
        return Err(Error::parse(
            path,
            Position::Byte(8),
            format!(
                "the header length field says {hlen} bytes, but byte {} is not the newline that ends a .npy header (corrupt header length?)",
                data_start.saturating_sub(1)
            ),
        ));
    }
    let header = String::from_utf8_lossy(raw);
    let bad = |msg: String| Error::parse(path, Position::Byte(hstart as u64), msg);
    let dict = header.trim_end_matches([' ', '\n', '\x00']);
    if !(dict.trim_start().starts_with('{') && dict.ends_with('}')) {
        return Err(bad(format!(
            "the header `{}` is not a Python dict literal {{...}} padded with spaces",
            header.trim().chars().take(80).collect::<String>()
        )));
    }
    let descr = dict_value(&header, "descr")
        .map(|v| v.trim_matches(|c| c == '\'' || c == '"').to_string())
        .ok_or_else(|| bad(format!("the header `{}` has no 'descr'", header.trim())))?;
    let (big, size) = match descr.as_str() {
        "<f4" => (false, 4),
        "<f8" => (false, 8),
        ">f4" => (true, 4),
        ">f8" => (true, 8),
        "=f4" | "f4" => (cfg!(target_endian = "big"), 4),
        "=f8" | "f8" => (cfg!(target_endian = "big"), 8),
        other => {
            return Err(bad(format!(
                "dtype '{other}' is not a float array (expected '<f4' or '<f8')"
            )))
        }
    };
    let fortran = match dict_value(&header, "fortran_order").map(str::trim) {
        Some("True") => true,
        Some("False") | None => false,
        Some(other) => return Err(bad(format!("fortran_order `{other}` is not True/False"))),
    };
    let shape_text = dict_value(&header, "shape")
        .ok_or_else(|| bad(format!("the header `{}` has no 'shape'", header.trim())))?;
    let shape: Vec<usize> = shape_text
        .trim_matches(|c| c == '(' || c == ')')
        .split(',')
        .map(|t| t.trim().trim_end_matches('L'))
        .filter(|t| !t.is_empty())
        .map(|t| t.parse::<usize>())
        .collect::<Result<_, _>>()
        .map_err(|_| bad(format!("shape {shape_text} is not a tuple of integers")))?;
    let n = match shape.as_slice() {
        [n, 2, 3] | [n, 6] => *n,
        _ => {
            return Err(bad(format!(
                "shape {shape_text} is not N x 2 x 3 (segments x endpoints x xyz)"
            )))
        }
    };
    if n == 0 {
        return Err(Error::no_data(
            path,
            "the array has no segments (shape 0 x 2 x 3)",
        ));
    }
    let need = n as u128 * 6 * size as u128;
    let have = (bytes.len() - data_start) as u128;
    if have < need {
        // In C order the first missing value names the row the data stops in.
        let first_missing = (have / size as u128) as usize;
        let pos = if fortran {
            Position::Byte(bytes.len() as u64)
        } else {
            Position::RowValue {
                row: first_missing / 6,
                value: first_missing % 6,
            }
        };
        return Err(Error::truncated(
            path,
            pos,
            format!(
                "shape {shape_text} of {descr} needs {need} data bytes from byte {data_start}, the file has {have}"
            ),
        ));
    }
    if have > need {
        return Err(Error::parse(
            path,
            Position::Byte(data_start as u64 + need as u64),
            format!(
                "shape {shape_text} of {descr} needs {need} data bytes from byte {data_start}, but the file has {have} (wrong shape in the header?)"
            ),
        ));
    }
    let data = &bytes[data_start..];
    let three_d = shape.len() == 3;
    // Flat index of value k (= 3 j + c: endpoint j, axis c) of segment `row`. Fortran order
    // stores the first axis fastest: (i, j, c) of N x 2 x 3 sits at i + N (j + 2 c).
    let flat = |row: usize, k: usize| match (fortran, three_d) {
        (false, _) => row * 6 + k,
        (true, false) => row + n * k,
        (true, true) => row + n * (k / 3 + 2 * (k % 3)),
    };
    let mut segs = Vec::with_capacity(n);
    let mut v = [0.0f64; 6];
    for row in 0..n {
        for (k, slot) in v.iter_mut().enumerate() {
            let i = flat(row, k);
            let b = &data[i * size..(i + 1) * size];
            let x = match (size, big) {
                (4, false) => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
                (4, true) => f32::from_be_bytes([b[0], b[1], b[2], b[3]]) as f64,
                (_, false) => f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]),
                (_, true) => f64::from_be_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]),
            };
            if !x.is_finite() {
                return Err(Error::non_finite(
                    path,
                    Position::RowValue { row, value: k },
                    "line coordinate",
                    x,
                ));
            }
            *slot = x;
        }
        segs.push(Segment::from_arrays([v[0], v[1], v[2]], [v[3], v[4], v[5]]));
    }
    Ok(segs)
}

/// The raw text of `key`'s value in a Python dict literal (`{'descr': '<f8', ...}`).
fn dict_value<'a>(header: &'a str, key: &str) -> Option<&'a str> {
    let k = header
        .find(&format!("'{key}'"))
        .or_else(|| header.find(&format!("\"{key}\"")))?;
    let rest = &header[k + key.len() + 2..];
    let rest = rest.trim_start().strip_prefix(':')?.trim_start();
    let end = if rest.starts_with('(') {
        rest.find(')')? + 1
    } else if let Some(q) = rest.strip_prefix('\'') {
        q.find('\'')? + 2
    } else {
        rest.find([',', '}']).unwrap_or(rest.len())
    };
    Some(&rest[..end])
}

/// An `N x 2 x 3` little-endian f64 `.npy` (format 1.0), as `numpy.save` writes it.
pub(crate) fn encode(segments: &[Segment]) -> Vec<u8> {
    let dict = format!(
        "{{'descr': '<f8', 'fortran_order': False, 'shape': ({}, 2, 3), }}",
        segments.len()
    );
    // numpy pads the header with spaces so the data starts on a 64-byte boundary.
    let unpadded = MAGIC.len() + 4 + dict.len() + 1;
    let pad = (64 - unpadded % 64) % 64;
    let hlen = dict.len() + pad + 1;
    let mut out = Vec::with_capacity(10 + hlen + segments.len() * 48);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&[1, 0]);
    out.extend_from_slice(&(hlen as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    out.extend(std::iter::repeat_n(b' ', pad));
    out.push(b'\n');
    for s in segments {
        for v in s.p1.to_array().into_iter().chain(s.p2.to_array()) {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(dict: &str) -> Vec<u8> {
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&[1, 0]);
        out.extend_from_slice(&(dict.len() as u16 + 1).to_le_bytes());
        out.extend_from_slice(dict.as_bytes());
        out.push(b'\n');
        out
    }

    #[test]
    fn written_header_is_aligned_and_reads_back() {
        let segs = vec![
            Segment::from_arrays([1.0, 2.0, 3.0], [4.0, 5.0, 6.5]),
            Segment::from_arrays([-1e-3, 0.25, 1e6], [7.0, 8.0, 9.0]),
        ];
        let bytes = encode(&segs);
        let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        assert_eq!((10 + hlen) % 64, 0);
        assert_eq!(bytes.len(), 10 + hlen + 2 * 48);
        assert_eq!(parse(Path::new("a.npy"), &bytes).unwrap(), segs);
    }

    #[test]
    fn f32_big_endian_and_fortran_order() {
        // Two segments, values 0..12, stored big-endian f32 in Fortran order of a 2x2x3
        // array: element (i, j, c) at i + 2 (j + 2 c).
        let mut bytes = header("{'descr': '>f4', 'fortran_order': True, 'shape': (2, 2, 3), }");
        let mut data = [0f32; 12];
        for i in 0..2 {
            for j in 0..2 {
                for c in 0..3 {
                    data[i + 2 * (j + 2 * c)] = (i * 6 + j * 3 + c) as f32;
                }
            }
        }
        for v in data {
            bytes.extend_from_slice(&v.to_be_bytes());
        }
        let segs = parse(Path::new("f.npy"), &bytes).unwrap();
        assert_eq!(
            segs[0],
            Segment::from_arrays([0.0, 1.0, 2.0], [3.0, 4.0, 5.0])
        );
        assert_eq!(
            segs[1],
            Segment::from_arrays([6.0, 7.0, 8.0], [9.0, 10.0, 11.0])
        );
    }

    #[test]
    fn wrong_shape_and_dtype_are_errors() {
        let p = Path::new("x.npy");
        let e = parse(
            p,
            &header("{'descr': '<f8', 'fortran_order': False, 'shape': (4, 3), }"),
        )
        .unwrap_err();
        assert!(e.to_string().contains("is not N x 2 x 3"), "{e}");
        let e = parse(
            p,
            &header("{'descr': '<i4', 'fortran_order': False, 'shape': (4, 2, 3), }"),
        )
        .unwrap_err();
        assert!(e.to_string().contains("'<i4' is not a float array"), "{e}");
    }
}
