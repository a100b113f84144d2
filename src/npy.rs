//! Minimal NumPy `.npy` reading and writing for `f32` arrays (and writing of `f64` ones; C
//! order, little-endian), so the CLI can exchange motions and noise with Python without a NumPy
//! dependency.

use std::path::Path;

use crate::error::{invalid_arg, Error, Result};

/// Encodes `data` with `shape` as a version 1.0 `.npy` file.
pub fn encode_f32(shape: &[usize], data: &[f32]) -> Vec<u8> {
    assert_eq!(
        shape.iter().product::<usize>(),
        data.len(),
        "shape does not match data"
    );
    let mut out = header("<f4", shape);
    out.reserve(data.len() * 4);
    for v in data {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// Encodes `data` with `shape` as a version 1.0 `.npy` file of `<f8`, after checking that the
/// shape holds `data.len()` values.
pub fn encode_f64(shape: &[usize], data: &[f64]) -> Result<Vec<u8>> {
    let count = shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
    if count != Some(data.len()) {
        return Err(invalid_arg!(
            ".npy shape {shape:?} does not hold {} values",
            data.len()
        ));
    }
    let mut out = header("<f8", shape);
    out.reserve(data.len() * 8);
    for v in data {
        out.extend_from_slice(&v.to_le_bytes());
    }
    Ok(out)
}

/// The magic, version (1.0), header length and header of a `.npy` file holding a C-order array
/// of NumPy dtype `descr` (`<f4`, `<f8`, `<U7`, ...) and `shape` (`[]` for a 0-d array), padded
/// with spaces so the data that follows starts on a 64-byte boundary, as NumPy's `np.save`
/// writes it (numpy/lib/format.py, `_wrap_header`). Version 1.0 keeps the header under 64 KiB,
/// which any dtype name and shape of a few dimensions fits.
pub fn header(descr: &str, shape: &[usize]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let shape_txt = match dims.len() {
        1 => format!("({},)", dims[0]),
        _ => format!("({})", dims.join(", ")),
    };
    let mut header =
        format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape_txt}, }}");
    // Pad so the data starts on a 64-byte boundary, header ends in '\n'.
    let unpadded = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len());
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out
}

/// Writes an `f32` array to `path`.
pub fn write_f32(path: &Path, shape: &[usize], data: &[f32]) -> Result<()> {
    std::fs::write(path, encode_f32(shape, data)).map_err(|source| Error::Write {
        path: path.display().to_string(),
        source,
    })
}

/// Reads an array of `<f4` or `<f8` values (C order) from `path`, as `f32`.
pub fn read_f32(path: &Path) -> Result<(Vec<usize>, Vec<f32>)> {
    let bytes = std::fs::read(path).map_err(|source| Error::Io {
        path: path.display().to_string(),
        source,
    })?;
    decode_f32(&bytes).map_err(|e| match e {
        Error::InvalidArgument(m) => invalid_arg!("{}: {m}", path.display()),
        other => other,
    })
}

/// Decodes `.npy` bytes holding `<f4` or `<f8` values in C order.
pub fn decode_f32(bytes: &[u8]) -> Result<(Vec<usize>, Vec<f32>)> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(invalid_arg!("not a .npy file"));
    }
    let (header_len, start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 if bytes.len() >= 12 => (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        ),
        v => return Err(invalid_arg!("unsupported .npy version {v}")),
    };
    let header = bytes
        .get(start..start + header_len)
        .and_then(|h| std::str::from_utf8(h).ok())
        .ok_or_else(|| invalid_arg!(".npy header is truncated or not text"))?;
    let field = |key: &str| -> Option<&str> {
        let i = header.find(&format!("'{key}'"))? + key.len() + 2;
        let rest = header[i..].trim_start().strip_prefix(':')?.trim_start();
        Some(rest)
    };
    let descr = field("descr").ok_or_else(|| invalid_arg!(".npy header has no descr"))?;
    let width = if descr.starts_with("'<f4'") {
        4
    } else if descr.starts_with("'<f8'") {
        8
    } else {
        return Err(invalid_arg!(
            ".npy dtype must be little-endian float32 or float64"
        ));
    };
    if field("fortran_order").is_some_and(|v| v.starts_with("True")) {
        return Err(invalid_arg!(".npy array must be in C order"));
    }
    let shape_txt = field("shape").ok_or_else(|| invalid_arg!(".npy header has no shape"))?;
    let dims = shape_txt
        .strip_prefix('(')
        .and_then(|s| s.split_once(')'))
        .map(|(dims, _)| dims)
        .ok_or_else(|| invalid_arg!(".npy shape is malformed"))?;
    let shape: Vec<usize> = dims
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<usize>()
                .map_err(|_| invalid_arg!(".npy shape is malformed"))
        })
        .collect::<Result<_>>()?;
    let needed = shape
        .iter()
        .try_fold(width, |a: usize, &d| a.checked_mul(d))
        .ok_or_else(|| invalid_arg!(".npy shape is too large"))?;
    let data = &bytes[start + header_len..];
    if data.len() != needed {
        return Err(invalid_arg!(
            ".npy holds {} data bytes, its shape needs {needed}",
            data.len(),
        ));
    }
    let values = if width == 4 {
        data.chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect()
    } else {
        data.chunks_exact(8)
            .map(|b| f64::from_le_bytes(b.try_into().expect("8 bytes")) as f32)
            .collect()
    };
    Ok((shape, values))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_alignment() {
        let data: Vec<f32> = (0..6).map(|i| i as f32 * 0.5).collect();
        let bytes = encode_f32(&[2, 3], &data);
        assert_eq!(&bytes[..8], b"\x93NUMPY\x01\x00");
        let header_len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        assert_eq!((10 + header_len) % 64, 0);
        let (shape, back) = decode_f32(&bytes).unwrap();
        assert_eq!(shape, vec![2, 3]);
        assert_eq!(back, data);
        let (shape, _) = decode_f32(&encode_f32(&[4], &[0.0; 4])).unwrap();
        assert_eq!(shape, vec![4]);
    }

    #[test]
    fn reads_a_numpy_written_float64_file() {
        // np.save of np.array([[1.5, -2.0]]) (float64), header as NumPy 1.x/2.x writes it.
        let mut bytes = b"\x93NUMPY\x01\x00v\x00".to_vec();
        let mut h = "{'descr': '<f8', 'fortran_order': False, 'shape': (1, 2), }".to_string();
        h.push_str(&" ".repeat(118 - h.len() - 1));
        h.push('\n');
        bytes.extend_from_slice(h.as_bytes());
        bytes.extend_from_slice(&1.5f64.to_le_bytes());
        bytes.extend_from_slice(&(-2.0f64).to_le_bytes());
        assert_eq!(decode_f32(&bytes).unwrap(), (vec![1, 2], vec![1.5, -2.0]));
    }

    #[test]
    fn rejects_bad_files() {
        assert!(decode_f32(b"hello").is_err());
        let mut b = encode_f32(&[2], &[1.0, 2.0]);
        b.pop();
        assert!(decode_f32(&b)
            .unwrap_err()
            .to_string()
            .contains("data bytes"));
    }

    /// A v1.0 file with `header` (padded to a 64-byte boundary) and `data`.
    fn with_header(header: &str, data: &[u8]) -> Vec<u8> {
        let mut h = header.to_string();
        h.push_str(&" ".repeat((64 - (10 + h.len() + 1) % 64) % 64));
        h.push('\n');
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        b.extend_from_slice(&(h.len() as u16).to_le_bytes());
        b.extend_from_slice(h.as_bytes());
        b.extend_from_slice(data);
        b
    }

    /// Found by fuzzing: a shape whose `)` comes before any `(` sliced the header backwards.
    #[test]
    fn rejects_a_shape_without_its_parenthesis() {
        for shape in ["),(", ")", "2,)", "(2,"] {
            let b = with_header(
                &format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}}}"),
                &[0; 8],
            );
            let e = decode_f32(&b).unwrap_err().to_string();
            assert!(e.contains("shape is malformed"), "{shape}: {e}");
        }
    }

    /// Found by fuzzing: an element count that fits `usize` but whose byte size does not
    /// overflowed while the error message was being written.
    #[test]
    fn rejects_a_shape_whose_byte_size_overflows() {
        let huge = usize::MAX / 4 + 1;
        let b = with_header(
            &format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({huge},)}}"),
            &[],
        );
        assert!(decode_f32(&b)
            .unwrap_err()
            .to_string()
            .contains("too large"));
        let b = with_header("{'descr': '<f8', 'shape': (3, 0), }", &[]);
        assert_eq!(decode_f32(&b).unwrap(), (vec![3, 0], vec![]));
    }
}
