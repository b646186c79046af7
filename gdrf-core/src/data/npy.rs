//! A small, strict reader for the one `.npy` case the CARLA layout needs: a float32 or
//! float64 camera-to-world matrix of shape (4, 4) or (3, 4). Anything else is an error
//! that says what was found.
use crate::{Error, Result};
use std::path::Path;

/// The top three rows of a camera-to-world matrix, row-major.
pub type Matrix3x4 = [[f64; 4]; 3];

pub fn read_matrix(path: &Path) -> Result<Matrix3x4> {
    let bytes = std::fs::read(path).map_err(|source| Error::Io { path: path.to_path_buf(), err: source })?;
    parse_matrix(&bytes).map_err(|reason| Error::Data { path: path.to_path_buf(), reason })
}

pub fn parse_matrix(bytes: &[u8]) -> std::result::Result<Matrix3x4, String> {
    if bytes.is_empty() {
        return Err("empty file (0 bytes)".into());
    }
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err("not a .npy file (missing the \\x93NUMPY magic)".into());
    }
    let (header_len, start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 if bytes.len() >= 12 => (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12),
        v => return Err(format!(".npy format version {v} is not supported")),
    };
    let header = bytes.get(start..start + header_len).ok_or("truncated .npy header")?;
    let header = std::str::from_utf8(header).map_err(|_| "the .npy header is not text")?;
    let descr = dict_value(header, "descr").ok_or("the .npy header has no 'descr'")?;
    let fortran = dict_value(header, "fortran_order").ok_or("the .npy header has no 'fortran_order'")?;
    let shape = dict_value(header, "shape").ok_or("the .npy header has no 'shape'")?;
    let (little, width) = match descr.trim_matches(|c| c == '\'' || c == '"') {
        "<f4" => (true, 4),
        ">f4" => (false, 4),
        "<f8" => (true, 8),
        ">f8" => (false, 8),
        d => return Err(format!("dtype {d} is not supported, expected float32 or float64")),
    };
    let fortran = match fortran {
        "False" => false,
        "True" => true,
        f => return Err(format!("fortran_order {f} is not a boolean")),
    };
    let dims: Vec<usize> = shape
        .trim_matches(|c| c == '(' || c == ')')
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>().map_err(|_| format!("bad shape {shape}")))
        .collect::<std::result::Result<_, _>>()?;
    let rows = match dims[..] {
        [4, 4] => 4,
        [3, 4] => 3,
        _ => return Err(format!("shape {shape} is not a camera-to-world matrix, expected (4, 4) or (3, 4)")),
    };
    let data = &bytes[start + header_len..];
    if data.len() != rows * 4 * width {
        return Err(format!(
            "data is {} bytes, expected {} for shape {shape} (truncated?)",
            data.len(),
            rows * 4 * width
        ));
    }
    let value = |k: usize| -> f64 {
        let b = &data[k * width..(k + 1) * width];
        match (width, little) {
            (4, true) => f32::from_le_bytes(b.try_into().unwrap()) as f64,
            (4, false) => f32::from_be_bytes(b.try_into().unwrap()) as f64,
            (_, true) => f64::from_le_bytes(b.try_into().unwrap()),
            (_, false) => f64::from_be_bytes(b.try_into().unwrap()),
        }
    };
    let mut m = [[0.0; 4]; 3];
    for (r, row) in m.iter_mut().enumerate() {
        for (c, x) in row.iter_mut().enumerate() {
            *x = value(if fortran { c * rows + r } else { r * 4 + c });
        }
    }
    if m.iter().flatten().any(|x| !x.is_finite()) {
        return Err("matrix has non-finite entries".into());
    }
    Ok(m)
}

/// The raw text of `key`'s value in numpy's header dict (`{'descr': '<f4', ...}`).
fn dict_value<'a>(header: &'a str, key: &str) -> Option<&'a str> {
    let at = header.find(&format!("'{key}'"))? + key.len() + 2;
    let rest = header[at..].trim_start().strip_prefix(':')?.trim_start();
    let end = if rest.starts_with('(') { rest.find(')')? + 1 } else { rest.find([',', '}'])? };
    Some(rest[..end].trim())
}

/// Writes a float64 (4, 4) `.npy` (tests and tools that make CARLA-style pose files).
pub fn encode_matrix_f64(m: &[[f64; 4]; 4]) -> Vec<u8> {
    let mut header = "{'descr': '<f8', 'fortran_order': False, 'shape': (4, 4), }".to_string();
    // Pad so that magic + length + header + newline is a multiple of 64, as numpy does.
    while !(10 + header.len() + 1).is_multiple_of(64) {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for x in m.iter().flatten() {
        out.extend_from_slice(&x.to_le_bytes());
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn m() -> [[f64; 4]; 4] {
        [[1.0, 2.0, 3.0, 4.0], [5.0, 6.0, 7.0, 8.0], [9.0, 10.0, 11.0, 12.0], [0.0, 0.0, 0.0, 1.0]]
    }

    #[test]
    fn round_trips_and_reads_float32_and_fortran_order() {
        let got = parse_matrix(&encode_matrix_f64(&m())).unwrap();
        assert_eq!(got[1], [5.0, 6.0, 7.0, 8.0]);
        // float32, Fortran order, (3, 4): columns stored first.
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        let h = "{'descr': '<f4', 'fortran_order': True, 'shape': (3, 4), }\n";
        b.extend_from_slice(&(h.len() as u16).to_le_bytes());
        b.extend_from_slice(h.as_bytes());
        for c in 0..4 {
            for r in 0..3 {
                b.extend_from_slice(&(m()[r][c] as f32).to_le_bytes());
            }
        }
        assert_eq!(parse_matrix(&b).unwrap()[2], [9.0, 10.0, 11.0, 12.0]);
    }

    #[test]
    fn rejects_what_it_cannot_read() {
        let good = encode_matrix_f64(&m());
        assert!(parse_matrix(&[]).unwrap_err().contains("empty"));
        assert!(parse_matrix(b"hello world").unwrap_err().contains("magic"));
        assert!(parse_matrix(&good[..good.len() - 8]).unwrap_err().contains("truncated"));
        let edit = |from: &str, to: &str| {
            let at = good.windows(from.len()).position(|w| w == from.as_bytes()).unwrap();
            [&good[..at], to.as_bytes(), &good[at + from.len()..]].concat()
        };
        assert!(parse_matrix(&edit("<f8", "<i8")).unwrap_err().contains("dtype"));
        assert!(parse_matrix(&edit("(4, 4)", "(16,)  ")).unwrap_err().contains("shape"));
    }
}
