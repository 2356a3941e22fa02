//! PLY point clouds (`formats.md` §6.1).
//!
//! Writer: binary little-endian, `comment ggpt-rs <version>`, one `vertex` element with
//! `float x, y, z`, `uchar red, green, blue` and optionally `float confidence` (15 / 19 bytes per
//! record). Coordinates are written as given (the pipeline passes SfM-frame scene units).
//!
//! Reader: ASCII or binary little-endian (big-endian is rejected), any number of elements (only
//! `vertex` is kept; other elements, including list properties, are parsed and skipped),
//! vertex properties in any order, extra properties ignored. `x, y, z` and `red, green, blue` are
//! required (any numeric type; colours must be integers in `0..=255`); `confidence` is optional.

use std::path::Path;

use crate::io::atomic::write_atomic;
use crate::{CoreError, Result};

/// A coloured point cloud.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PlyCloud {
    /// Point coordinates (frame and units as chosen by the caller; SfM frame in the pipeline).
    pub points: Vec<[f32; 3]>,
    /// RGB colour per point.
    pub colors: Vec<[u8; 3]>,
    /// Optional per-point confidence.
    pub confidence: Option<Vec<f32>>,
}

/// Writes `cloud` as binary little-endian PLY (atomic). Lengths must agree.
pub fn write_ply(path: &Path, cloud: &PlyCloud) -> Result<()> {
    let n = cloud.points.len();
    if cloud.colors.len() != n || cloud.confidence.as_ref().is_some_and(|c| c.len() != n) {
        return Err(CoreError::format(
            path,
            "",
            "points, colors and confidence must have the same length",
        ));
    }
    let mut header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment ggpt-rs {}\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n",
        env!("CARGO_PKG_VERSION")
    );
    if cloud.confidence.is_some() {
        header.push_str("property float confidence\n");
    }
    header.push_str("end_header\n");
    write_atomic(path, |w| {
        w.write_all(header.as_bytes())?;
        let mut rec = Vec::with_capacity(19 * 4096);
        for i in 0..n {
            for c in cloud.points[i] {
                rec.extend_from_slice(&c.to_le_bytes());
            }
            rec.extend_from_slice(&cloud.colors[i]);
            if let Some(c) = &cloud.confidence {
                rec.extend_from_slice(&c[i].to_le_bytes());
            }
            if rec.len() >= 19 * 4096 {
                w.write_all(&rec)?;
                rec.clear();
            }
        }
        w.write_all(&rec)
    })
}

/// Scalar property types of PLY.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Scalar {
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
    fn parse(s: &str) -> Option<Self> {
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
    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }
    fn is_int(self) -> bool {
        !matches!(self, Scalar::F32 | Scalar::F64)
    }
    /// Decodes one little-endian value (caller guarantees `b.len() == size`).
    fn decode(self, b: &[u8]) -> f64 {
        let a = |n: usize| -> [u8; 8] {
            let mut x = [0u8; 8];
            x[..n].copy_from_slice(&b[..n]);
            x
        };
        match self {
            Scalar::I8 => f64::from(b[0] as i8),
            Scalar::U8 => f64::from(b[0]),
            Scalar::I16 => f64::from(i16::from_le_bytes([b[0], b[1]])),
            Scalar::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
            Scalar::I32 => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Scalar::U32 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Scalar::F32 => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Scalar::F64 => f64::from_le_bytes(a(8)),
        }
    }
}

/// One property: scalar, or list (count type, item type).
#[derive(Debug, Clone)]
struct Property {
    name: String,
    kind: Scalar,
    list_count: Option<Scalar>,
}

#[derive(Debug, Clone)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Property>,
}

#[derive(Debug, PartialEq)]
enum Encoding {
    Ascii,
    BinaryLe,
}

/// Parses the header; returns encoding, elements and the byte offset of the body.
fn parse_header(path: &Path, bytes: &[u8]) -> Result<(Encoding, Vec<Element>, usize)> {
    let err = |m: String| CoreError::format(path, "header", m);
    let mut pos = 0;
    let mut lines = Vec::new();
    loop {
        let rest = bytes.get(pos..).unwrap_or_default();
        let nl = rest
            .iter()
            .position(|&b| b == b'\n')
            .ok_or_else(|| err("truncated header (no end_header line)".into()))?;
        let line = String::from_utf8_lossy(&rest[..nl]).trim().to_string();
        pos += nl + 1;
        if line == "end_header" {
            break;
        }
        lines.push(line);
        if lines.len() > 100_000 {
            return Err(err("header too long".into()));
        }
    }
    if lines.first().map(String::as_str) != Some("ply") {
        return Err(err("missing 'ply' magic line".into()));
    }
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    for line in lines.iter().skip(1) {
        let t: Vec<&str> = line.split_whitespace().collect();
        match t.as_slice() {
            [] | ["comment", ..] | ["obj_info", ..] => {}
            ["format", "ascii", _] => encoding = Some(Encoding::Ascii),
            ["format", "binary_little_endian", _] => encoding = Some(Encoding::BinaryLe),
            ["format", other, ..] => {
                return Err(err(format!(
                    "unsupported format '{other}' (ascii or binary_little_endian only)"
                )));
            }
            ["element", name, count] => {
                let count = count
                    .parse()
                    .map_err(|_| err(format!("bad element count '{count}'")))?;
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    props: Vec::new(),
                });
            }
            ["property", "list", ct, it, name] => {
                let (ct, it) = (Scalar::parse(ct), Scalar::parse(it));
                let (Some(ct), Some(it)) = (ct, it) else {
                    return Err(err(format!("bad list property '{line}'")));
                };
                let el = elements
                    .last_mut()
                    .ok_or_else(|| err("property before any element".into()))?;
                el.props.push(Property {
                    name: name.to_string(),
                    kind: it,
                    list_count: Some(ct),
                });
            }
            ["property", ty, name] => {
                let kind = Scalar::parse(ty)
                    .ok_or_else(|| err(format!("unknown property type '{ty}'")))?;
                let el = elements
                    .last_mut()
                    .ok_or_else(|| err("property before any element".into()))?;
                el.props.push(Property {
                    name: name.to_string(),
                    kind,
                    list_count: None,
                });
            }
            _ => return Err(err(format!("unrecognised header line '{line}'"))),
        }
    }
    let encoding = encoding.ok_or_else(|| err("missing format line".into()))?;
    Ok((encoding, elements, pos))
}

/// Reads the body value by value (ASCII tokens or little-endian binary).
struct Body<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    pos: usize,
    ascii: bool,
}

impl Body<'_> {
    fn next(&mut self, kind: Scalar, what: &str) -> Result<f64> {
        if self.ascii {
            let rest = self.bytes.get(self.pos..).unwrap_or_default();
            let start = rest
                .iter()
                .position(|b| !b.is_ascii_whitespace())
                .ok_or_else(|| self.trunc(what))?;
            let len = rest[start..]
                .iter()
                .position(|b| b.is_ascii_whitespace())
                .unwrap_or(rest.len() - start);
            let tok = String::from_utf8_lossy(&rest[start..start + len]);
            self.pos += start + len;
            tok.parse::<f64>()
                .map_err(|_| CoreError::format(self.path, what, format!("bad ASCII value '{tok}'")))
        } else {
            let b = self
                .bytes
                .get(self.pos..self.pos + kind.size())
                .ok_or_else(|| self.trunc(what))?;
            self.pos += kind.size();
            Ok(kind.decode(b))
        }
    }
    fn trunc(&self, what: &str) -> CoreError {
        CoreError::format(
            self.path,
            what,
            "truncated body (fewer records than the header declares)",
        )
    }
}

/// Reads an ASCII or binary little-endian PLY (see the module docs).
pub fn read_ply(path: &Path) -> Result<PlyCloud> {
    let bytes = std::fs::read(path).map_err(|e| CoreError::io(path, e))?;
    let (enc, elements, start) = parse_header(path, &bytes)?;
    let vertex = elements
        .iter()
        .find(|e| e.name == "vertex")
        .ok_or_else(|| CoreError::format(path, "vertex", "no vertex element"))?;
    let find = |name: &str| {
        vertex
            .props
            .iter()
            .position(|p| p.name == name && p.list_count.is_none())
    };
    let need = |name: &str| {
        find(name).ok_or_else(|| CoreError::format(path, name, "missing vertex property"))
    };
    let (ix, iy, iz) = (need("x")?, need("y")?, need("z")?);
    let (ir, ig, ib) = (need("red")?, need("green")?, need("blue")?);
    for i in [ir, ig, ib] {
        if !vertex.props[i].kind.is_int() {
            return Err(CoreError::format(
                path,
                &vertex.props[i].name,
                "colour property must be an integer type",
            ));
        }
    }
    let ic = find("confidence");
    // Sanity bound before allocating: every record needs at least one byte.
    if vertex.count > bytes.len() {
        return Err(CoreError::format(
            path,
            "vertex",
            format!(
                "header declares {} vertices, the file has only {} bytes",
                vertex.count,
                bytes.len()
            ),
        ));
    }
    let mut body = Body {
        path,
        bytes: &bytes,
        pos: start,
        ascii: enc == Encoding::Ascii,
    };
    let mut cloud = PlyCloud {
        points: Vec::with_capacity(vertex.count),
        colors: Vec::with_capacity(vertex.count),
        confidence: ic.map(|_| Vec::with_capacity(vertex.count)),
    };
    let mut vals = Vec::new();
    for el in &elements {
        for _ in 0..el.count {
            vals.clear();
            for p in &el.props {
                match p.list_count {
                    None => vals.push(body.next(p.kind, &p.name)?),
                    Some(ct) => {
                        let k = body.next(ct, &p.name)?;
                        if !(0.0..=1e9).contains(&k) || k.fract() != 0.0 {
                            return Err(CoreError::format(
                                path,
                                &p.name,
                                format!("bad list length {k}"),
                            ));
                        }
                        for _ in 0..k as usize {
                            body.next(p.kind, &p.name)?;
                        }
                        vals.push(0.0);
                    }
                }
            }
            if el.name == "vertex" {
                push_vertex(
                    path,
                    &mut cloud,
                    &vals,
                    [ix, iy, iz],
                    [ir, ig, ib],
                    ic,
                    &vertex.props,
                )?;
            }
        }
    }
    Ok(cloud)
}

fn push_vertex(
    path: &Path,
    cloud: &mut PlyCloud,
    v: &[f64],
    xyz: [usize; 3],
    rgb: [usize; 3],
    ic: Option<usize>,
    props: &[Property],
) -> Result<()> {
    let get = |i: usize| v.get(i).copied().unwrap_or(0.0);
    cloud
        .points
        .push([get(xyz[0]) as f32, get(xyz[1]) as f32, get(xyz[2]) as f32]);
    let mut c = [0u8; 3];
    for (k, &i) in rgb.iter().enumerate() {
        let x = get(i);
        if !(0.0..=255.0).contains(&x) {
            return Err(CoreError::format(
                path,
                &props[i].name,
                format!("colour {x} outside 0..=255 (vertex {})", cloud.colors.len()),
            ));
        }
        c[k] = x as u8;
    }
    cloud.colors.push(c);
    if let (Some(i), Some(conf)) = (ic, cloud.confidence.as_mut()) {
        conf.push(get(i) as f32);
    }
    Ok(())
}
