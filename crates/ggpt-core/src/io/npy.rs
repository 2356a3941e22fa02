//! NumPy `.npy` / `.npz` (`formats.md` §1.1).
//!
//! Reading: format versions 1.0, 2.0 and 3.0; descriptors `<f4 <f8 <i4 <i8 |u1 |b1 <u2` (`=` as
//! byte order is accepted as little-endian, big-endian `>` is rejected); `fortran_order: True`
//! arrays are transposed to C order. The data length must match the shape exactly; bool bytes
//! must be 0 or 1. Writing: version 1.0 (2.0 only if the header exceeds 65535 bytes), C order,
//! header padded to a multiple of 64. `.npz`: zip archive of `<key>.npy` members, stored or
//! deflated (both read; the writer deflates unless asked to store).

use std::collections::BTreeMap;
use std::io::{Cursor, Read, Write};
use std::path::Path;

use crate::io::atomic::write_bytes_atomic;
use crate::{CoreError, Result};

/// `.npy` magic bytes.
const MAGIC: &[u8; 6] = b"\x93NUMPY";
/// Alignment of the data start written by NumPy ≥ 1.14.
const HEADER_ALIGN: usize = 64;

/// Typed array values (always C order after reading).
#[derive(Debug, Clone, PartialEq)]
pub enum NpyData {
    /// `<f4`
    F32(Vec<f32>),
    /// `<f8`
    F64(Vec<f64>),
    /// `<i4`
    I32(Vec<i32>),
    /// `<i8`
    I64(Vec<i64>),
    /// `|u1`
    U8(Vec<u8>),
    /// `<u2`
    U16(Vec<u16>),
    /// `|b1`
    Bool(Vec<bool>),
}

/// An n-dimensional array: shape (outermost first; empty for a scalar) and C-order values.
#[derive(Debug, Clone, PartialEq)]
pub struct NpyArray {
    /// Extents, outermost first.
    pub shape: Vec<usize>,
    /// Values in row-major (C) order; `len` equals the product of `shape`.
    pub data: NpyData,
}

impl NpyData {
    /// Number of values.
    pub fn len(&self) -> usize {
        match self {
            NpyData::F32(v) => v.len(),
            NpyData::F64(v) => v.len(),
            NpyData::I32(v) => v.len(),
            NpyData::I64(v) => v.len(),
            NpyData::U8(v) => v.len(),
            NpyData::U16(v) => v.len(),
            NpyData::Bool(v) => v.len(),
        }
    }

    /// True when there is no value.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// NumPy descriptor string (`<f4`, ...).
    pub fn descr(&self) -> &'static str {
        match self {
            NpyData::F32(_) => "<f4",
            NpyData::F64(_) => "<f8",
            NpyData::I32(_) => "<i4",
            NpyData::I64(_) => "<i8",
            NpyData::U8(_) => "|u1",
            NpyData::U16(_) => "<u2",
            NpyData::Bool(_) => "|b1",
        }
    }
}

impl NpyArray {
    /// Creates an array, checking that `data` holds `shape.product()` values.
    pub fn new(shape: Vec<usize>, data: NpyData) -> Result<Self> {
        let want: usize = shape.iter().product();
        if data.len() != want {
            return Err(CoreError::Invalid(format!(
                "npy array: {} values for shape {shape:?} ({want} expected)",
                data.len()
            )));
        }
        Ok(Self { shape, data })
    }

    /// Values as f32 when the array is `<f4` (exact) or `<f8` (rounded); `None` otherwise.
    pub fn to_f32(&self) -> Option<Vec<f32>> {
        match &self.data {
            NpyData::F32(v) => Some(v.clone()),
            NpyData::F64(v) => Some(v.iter().map(|&x| x as f32).collect()),
            _ => None,
        }
    }

    /// [`NpyArray::to_f32`] without a copy of `<f4` values (the array is consumed); `Err`
    /// gives the array back when it holds no floats.
    pub fn into_f32(self) -> std::result::Result<Vec<f32>, Self> {
        match self.data {
            NpyData::F32(v) => Ok(v),
            NpyData::F64(v) => Ok(v.iter().map(|&x| x as f32).collect()),
            _ => Err(self),
        }
    }

    /// Values as f64 when the array is `<f4` or `<f8`; `None` otherwise.
    pub fn to_f64(&self) -> Option<Vec<f64>> {
        match &self.data {
            NpyData::F32(v) => Some(v.iter().map(|&x| f64::from(x)).collect()),
            NpyData::F64(v) => Some(v.clone()),
            _ => None,
        }
    }
}

/// Reads a `.npy` file.
pub fn read_npy(path: &Path) -> Result<NpyArray> {
    let bytes = std::fs::read(path).map_err(|e| CoreError::io(path, e))?;
    parse_npy(path, "", &bytes)
}

/// Writes a `.npy` file (version 1.0, C order, atomic).
pub fn write_npy(path: &Path, array: &NpyArray) -> Result<()> {
    let bytes = encode_npy(array)?;
    write_bytes_atomic(path, &bytes)
}

/// Parses `.npy` bytes; errors name `path` and `key` (the npz member, empty for a file).
pub fn parse_npy(path: &Path, key: &str, bytes: &[u8]) -> Result<NpyArray> {
    let err = |m: String| CoreError::format(path, key, m);
    if bytes.len() < 10 || bytes.get(..6) != Some(&MAGIC[..]) {
        return Err(err("not a .npy file (bad magic or truncated header)".into()));
    }
    let (major, minor) = (bytes[6], bytes[7]);
    let (hlen, hstart) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            let b = bytes
                .get(8..12)
                .ok_or_else(|| err("truncated header length".into()))?;
            (u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize, 12)
        }
        _ => return Err(err(format!("unsupported .npy version {major}.{minor}"))),
    };
    let header = bytes
        .get(hstart..hstart + hlen)
        .ok_or_else(|| err("truncated header".into()))?;
    let header = std::str::from_utf8(header).map_err(|_| err("header is not text".into()))?;
    if major < 3 && !header.is_ascii() {
        return Err(err("header is not ASCII".into()));
    }
    let h = parse_header(header)
        .map_err(|m| err(format!("bad header {:?}: {m}", header.trim_end())))?;
    let payload = bytes.get(hstart + hlen..).unwrap_or_default();
    let numel = h
        .shape
        .iter()
        .try_fold(1usize, |a, &d| a.checked_mul(d))
        .ok_or_else(|| err("shape overflows".into()))?;
    let item = item_size(&h.descr)
        .ok_or_else(|| err(format!("unsupported dtype descriptor '{}'", h.descr)))?;
    let want = numel
        .checked_mul(item)
        .ok_or_else(|| err("shape overflows".into()))?;
    if payload.len() != want {
        let what = if payload.len() < want {
            "truncated"
        } else {
            "trailing bytes"
        };
        return Err(err(format!(
            "{what}: data has {} bytes, shape {:?} x {} needs {want}",
            payload.len(),
            h.shape,
            h.descr
        )));
    }
    let data = decode(&h.descr, payload).map_err(&err)?;
    let data = if h.fortran_order {
        fortran_to_c(&h.shape, data)
    } else {
        data
    };
    Ok(NpyArray {
        shape: h.shape,
        data,
    })
}

/// Parsed `.npy` header dict.
struct Header {
    descr: String,
    fortran_order: bool,
    shape: Vec<usize>,
}

/// Parses the Python dict literal `{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }`.
fn parse_header(s: &str) -> std::result::Result<Header, String> {
    let body = s
        .trim()
        .strip_prefix('{')
        .and_then(|b| b.trim_end().strip_suffix('}'))
        .ok_or("not a dict literal")?;
    let mut descr = None;
    let mut fortran = None;
    let mut shape = None;
    let mut rest = body.trim_start();
    while !rest.is_empty() {
        let (key, r) = take_string(rest)?;
        let r = r
            .trim_start()
            .strip_prefix(':')
            .ok_or("expected ':'")?
            .trim_start();
        let r = match key.as_str() {
            "descr" => {
                let (v, r) = take_string(r)?;
                descr = Some(v);
                r
            }
            "fortran_order" => {
                let (v, r) = if let Some(r) = r.strip_prefix("True") {
                    (true, r)
                } else {
                    (
                        false,
                        r.strip_prefix("False")
                            .ok_or("fortran_order must be True or False")?,
                    )
                };
                fortran = Some(v);
                r
            }
            "shape" => {
                let r = r.strip_prefix('(').ok_or("shape must be a tuple")?;
                let end = r.find(')').ok_or("unterminated shape tuple")?;
                let dims = r[..end]
                    .split(',')
                    .map(str::trim)
                    .filter(|t| !t.is_empty())
                    .map(|t| {
                        t.trim_end_matches('L')
                            .parse::<usize>()
                            .map_err(|_| format!("bad dimension '{t}'"))
                    })
                    .collect::<std::result::Result<Vec<_>, _>>()?;
                shape = Some(dims);
                &r[end + 1..]
            }
            other => return Err(format!("unknown key '{other}'")),
        };
        let r = r.trim_start();
        rest = r.strip_prefix(',').unwrap_or(r).trim_start();
    }
    Ok(Header {
        descr: descr.ok_or("missing 'descr'")?,
        fortran_order: fortran.ok_or("missing 'fortran_order'")?,
        shape: shape.ok_or("missing 'shape'")?,
    })
}

/// Takes a single- or double-quoted string literal from the front of `s`.
fn take_string(s: &str) -> std::result::Result<(String, &str), String> {
    let q = s.chars().next().ok_or("unexpected end of header")?;
    if q != '\'' && q != '"' {
        return Err(format!(
            "expected a quoted string at '{}'",
            s.chars().take(12).collect::<String>()
        ));
    }
    let inner = &s[1..];
    let end = inner.find(q).ok_or("unterminated string")?;
    Ok((inner[..end].to_string(), &inner[end + 1..]))
}

/// Normalises the byte-order character: `<`, `=` and `|` are accepted (little-endian host).
fn canonical(descr: &str) -> Option<&str> {
    let (bo, t) = descr.split_at_checked(1)?;
    match (bo, t) {
        ("<" | "=", "f4" | "f8" | "i4" | "i8" | "u2") => Some(t),
        ("|" | "<" | "=", "u1" | "b1") => Some(t),
        _ => None,
    }
}

fn item_size(descr: &str) -> Option<usize> {
    match canonical(descr)? {
        "f8" | "i8" => Some(8),
        "f4" | "i4" => Some(4),
        "u2" => Some(2),
        _ => Some(1),
    }
}

fn decode(descr: &str, b: &[u8]) -> std::result::Result<NpyData, String> {
    let a4 = |c: &[u8]| [c[0], c[1], c[2], c[3]];
    let a8 = |c: &[u8]| [c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]];
    Ok(
        match canonical(descr).ok_or_else(|| format!("unsupported dtype descriptor '{descr}'"))? {
            "f4" => NpyData::F32(
                b.chunks_exact(4)
                    .map(|c| f32::from_le_bytes(a4(c)))
                    .collect(),
            ),
            "f8" => NpyData::F64(
                b.chunks_exact(8)
                    .map(|c| f64::from_le_bytes(a8(c)))
                    .collect(),
            ),
            "i4" => NpyData::I32(
                b.chunks_exact(4)
                    .map(|c| i32::from_le_bytes(a4(c)))
                    .collect(),
            ),
            "i8" => NpyData::I64(
                b.chunks_exact(8)
                    .map(|c| i64::from_le_bytes(a8(c)))
                    .collect(),
            ),
            "u2" => NpyData::U16(
                b.chunks_exact(2)
                    .map(|c| u16::from_le_bytes([c[0], c[1]]))
                    .collect(),
            ),
            "u1" => NpyData::U8(b.to_vec()),
            _ => NpyData::Bool(
                b.iter()
                    .enumerate()
                    .map(|(i, &x)| match x {
                        0 => Ok(false),
                        1 => Ok(true),
                        _ => Err(format!("bool byte {x} at flat index {i} (must be 0 or 1)")),
                    })
                    .collect::<std::result::Result<_, _>>()?,
            ),
        },
    )
}

/// Reorders column-major values into row-major order.
fn fortran_to_c(shape: &[usize], data: NpyData) -> NpyData {
    fn perm<T: Copy>(shape: &[usize], v: Vec<T>) -> Vec<T> {
        let numel = v.len();
        if shape.len() < 2 || numel == 0 {
            return v;
        }
        // Fortran strides (in elements).
        let mut fstride = vec![1usize; shape.len()];
        for d in 1..shape.len() {
            fstride[d] = fstride[d - 1] * shape[d - 1];
        }
        let mut idx = vec![0usize; shape.len()];
        let mut out = Vec::with_capacity(numel);
        for _ in 0..numel {
            let off: usize = idx.iter().zip(&fstride).map(|(i, s)| i * s).sum();
            if let Some(&x) = v.get(off) {
                out.push(x);
            }
            for d in (0..shape.len()).rev() {
                idx[d] += 1;
                if idx[d] < shape[d] {
                    break;
                }
                idx[d] = 0;
            }
        }
        out
    }
    match data {
        NpyData::F32(v) => NpyData::F32(perm(shape, v)),
        NpyData::F64(v) => NpyData::F64(perm(shape, v)),
        NpyData::I32(v) => NpyData::I32(perm(shape, v)),
        NpyData::I64(v) => NpyData::I64(perm(shape, v)),
        NpyData::U8(v) => NpyData::U8(perm(shape, v)),
        NpyData::U16(v) => NpyData::U16(perm(shape, v)),
        NpyData::Bool(v) => NpyData::Bool(perm(shape, v)),
    }
}

/// Encodes an array as `.npy` bytes (version 1.0 unless the header needs 2.0).
pub fn encode_npy(a: &NpyArray) -> Result<Vec<u8>> {
    let numel: usize = a.shape.iter().product();
    if a.data.len() != numel {
        return Err(CoreError::Invalid(format!(
            "npy array: {} values for shape {:?}",
            a.data.len(),
            a.shape
        )));
    }
    let shape = match a.shape.len() {
        1 => format!("({},)", a.shape[0]),
        _ => format!(
            "({})",
            a.shape
                .iter()
                .map(|d| d.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let dict = format!(
        "{{'descr': '{}', 'fortran_order': False, 'shape': {shape}, }}",
        a.data.descr()
    );
    let v1 = dict.len() + 1 + 10 <= u16::MAX as usize;
    let pre = if v1 { 10 } else { 12 };
    let total = (pre + dict.len() + 1).div_ceil(HEADER_ALIGN) * HEADER_ALIGN;
    let hlen = total - pre;
    let mut out = Vec::with_capacity(total + numel * 8);
    out.extend_from_slice(MAGIC);
    if v1 {
        out.extend_from_slice(&[1, 0]);
        out.extend_from_slice(&(hlen as u16).to_le_bytes());
    } else {
        out.extend_from_slice(&[2, 0]);
        out.extend_from_slice(&(hlen as u32).to_le_bytes());
    }
    out.extend_from_slice(dict.as_bytes());
    out.resize(total - 1, b' ');
    out.push(b'\n');
    match &a.data {
        NpyData::F32(v) => v
            .iter()
            .for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
        NpyData::F64(v) => v
            .iter()
            .for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
        NpyData::I32(v) => v
            .iter()
            .for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
        NpyData::I64(v) => v
            .iter()
            .for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
        NpyData::U16(v) => v
            .iter()
            .for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
        NpyData::U8(v) => out.extend_from_slice(v),
        NpyData::Bool(v) => out.extend(v.iter().map(|&b| u8::from(b))),
    }
    Ok(out)
}

/// Largest expansion of deflate (1032:1): bounds what a member's compressed bytes can decode to.
const MAX_DEFLATE_RATIO: u64 = 1032;
/// Largest buffer reserved up front for one member (it grows past this when the data does).
const MAX_NPZ_PREALLOC: u64 = 64 << 20;

/// Reads every `<key>.npy` member of a `.npz` archive (stored or deflated), keyed by `<key>`.
/// Members not ending in `.npy` are ignored.
pub fn read_npz(path: &Path) -> Result<BTreeMap<String, NpyArray>> {
    let bytes = std::fs::read(path).map_err(|e| CoreError::io(path, e))?;
    let zerr = |key: &str, e: zip::result::ZipError| {
        CoreError::format(path, key, format!("corrupt or truncated npz archive: {e}"))
    };
    let mut zip = zip::ZipArchive::new(Cursor::new(bytes)).map_err(|e| zerr("", e))?;
    let mut out = BTreeMap::new();
    for i in 0..zip.len() {
        let mut f = zip.by_index(i).map_err(|e| zerr("", e))?;
        let name = f.name().map_err(|e| zerr("", e))?.into_owned();
        let Some(key) = name.strip_suffix(".npy") else {
            continue;
        };
        let key = key.to_string();
        // The declared size is only a hint: it is capped by what the compressed bytes can
        // expand to, and reading stops one byte past it (a member larger than declared is an
        // error, not an unbounded buffer).
        let declared = f.size();
        let hint = declared
            .min(
                f.compressed_size()
                    .saturating_mul(MAX_DEFLATE_RATIO)
                    .saturating_add(1024),
            )
            .min(MAX_NPZ_PREALLOC);
        let mut buf = Vec::with_capacity(usize::try_from(hint).unwrap_or(0));
        (&mut f)
            .take(declared.saturating_add(1))
            .read_to_end(&mut buf)
            .map_err(|e| CoreError::format(path, &key, format!("cannot decompress member: {e}")))?;
        if buf.len() as u64 > declared {
            return Err(CoreError::format(
                path,
                &key,
                format!("member is larger than its declared {declared} bytes"),
            ));
        }
        let arr = parse_npy(path, &key, &buf)?;
        if out.insert(key.clone(), arr).is_some() {
            return Err(CoreError::format(path, &key, "duplicate member"));
        }
    }
    Ok(out)
}

/// Writes a `.npz` archive of `<key>.npy` members (deflated unless `store` is true; zip64 when
/// a member is ≥ 4 GiB). Atomic.
pub fn write_npz(path: &Path, arrays: &[(&str, &NpyArray)], store: bool) -> Result<()> {
    let zerr =
        |key: &str, e: String| CoreError::format(path, key, format!("cannot write npz: {e}"));
    let method = if store {
        zip::CompressionMethod::Stored
    } else {
        zip::CompressionMethod::Deflated
    };
    let mut zw = zip::ZipWriter::new(Cursor::new(Vec::new()));
    for (key, a) in arrays {
        let npy = encode_npy(a).map_err(|e| zerr(key, e.to_string()))?;
        let opts = zip::write::SimpleFileOptions::default()
            .compression_method(method)
            .large_file(npy.len() as u64 >= u32::MAX as u64);
        zw.start_file(format!("{key}.npy"), opts)
            .map_err(|e| zerr(key, e.to_string()))?;
        zw.write_all(&npy).map_err(|e| zerr(key, e.to_string()))?;
    }
    let bytes = zw
        .finish()
        .map_err(|e| zerr("", e.to_string()))?
        .into_inner();
    write_bytes_atomic(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_parser_accepts_numpy_variants() {
        let h =
            parse_header("{'descr': '<f8', 'fortran_order': True, 'shape': (3,), }   \n").unwrap();
        assert_eq!(
            (h.descr.as_str(), h.fortran_order, h.shape),
            ("<f8", true, vec![3])
        );
        let h = parse_header("{\"descr\":\"|b1\",\"fortran_order\":False,\"shape\":()}").unwrap();
        assert!(h.shape.is_empty());
        assert!(parse_header("{'descr': '<f4', 'shape': (1,), }").is_err());
    }

    #[test]
    fn fortran_reorders() {
        // 2x3 array [[0,1,2],[3,4,5]] stored column-major: 0,3,1,4,2,5.
        let d = fortran_to_c(&[2, 3], NpyData::I32(vec![0, 3, 1, 4, 2, 5]));
        assert_eq!(d, NpyData::I32(vec![0, 1, 2, 3, 4, 5]));
    }
}
