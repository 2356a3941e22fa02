//! Minimal `torch.save` zip-pickle writer for tests (protocol 2, the opcodes torch emits), so
//! that malformed official files (wrong dtype / shape, NaN, strided views) can be produced.

use std::io::Write;
use std::path::Path;

/// One value of the top-level dict.
pub enum Value {
    /// A tensor view of its own storage: storage type (`FloatStorage`, ...), storage bytes,
    /// storage numel, offset, size, stride.
    Tensor { storage: &'static str, bytes: Vec<u8>, numel: usize, offset: usize, size: Vec<usize>, stride: Vec<usize> },
    /// A Python bool.
    Bool(bool),
}

/// Contiguous f32 tensor.
pub fn f32_tensor(v: &[f32], size: &[usize]) -> Value {
    let stride = contiguous(size);
    Value::Tensor { storage: "FloatStorage", bytes: v.iter().flat_map(|x| x.to_le_bytes()).collect(), numel: v.len(), offset: 0, size: size.to_vec(), stride }
}

/// Contiguous bool tensor.
pub fn bool_tensor(v: &[bool], size: &[usize]) -> Value {
    Value::Tensor { storage: "BoolStorage", bytes: v.iter().map(|&b| u8::from(b)).collect(), numel: v.len(), offset: 0, size: size.to_vec(), stride: contiguous(size) }
}

/// Row-major strides of `size`.
pub fn contiguous(size: &[usize]) -> Vec<usize> {
    let mut s = vec![1; size.len()];
    for d in (0..size.len().saturating_sub(1)).rev() {
        s[d] = s[d + 1] * size[d + 1];
    }
    s
}

fn unicode(p: &mut Vec<u8>, s: &str) {
    p.push(b'X');
    p.extend_from_slice(&(s.len() as u32).to_le_bytes());
    p.extend_from_slice(s.as_bytes());
}

fn int(p: &mut Vec<u8>, v: usize) {
    p.push(b'J');
    p.extend_from_slice(&(v as i32).to_le_bytes());
}

fn tuple(p: &mut Vec<u8>, v: &[usize]) {
    p.push(b'(');
    for &x in v {
        int(p, x);
    }
    p.push(b't');
}

/// Writes `<stem>.bin`-style torch zip with the given entries (in order).
pub fn write_torch(path: &Path, entries: &[(&str, Value)]) {
    let stem = path.file_stem().unwrap().to_string_lossy().into_owned();
    let mut p = vec![0x80, 2, b'}', b'('];
    let mut storages = Vec::new();
    for (key, v) in entries {
        unicode(&mut p, key);
        match v {
            Value::Bool(b) => p.push(if *b { 0x88 } else { 0x89 }),
            Value::Tensor { storage, bytes, numel, offset, size, stride } => {
                let id = storages.len();
                storages.push(bytes.clone());
                p.extend_from_slice(b"ctorch._utils\n_rebuild_tensor_v2\n(");
                p.push(b'(');
                unicode(&mut p, "storage");
                p.extend_from_slice(format!("ctorch\n{storage}\n").as_bytes());
                unicode(&mut p, &id.to_string());
                unicode(&mut p, "cpu");
                int(&mut p, *numel);
                p.extend_from_slice(b"tQ");
                int(&mut p, *offset);
                tuple(&mut p, size);
                tuple(&mut p, stride);
                p.push(0x89);
                p.extend_from_slice(b"ccollections\nOrderedDict\n)R");
                p.extend_from_slice(b"tR");
            }
        }
    }
    p.extend_from_slice(b"u.");
    let mut zw = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    zw.start_file(format!("{stem}/data.pkl"), opts).unwrap();
    zw.write_all(&p).unwrap();
    zw.start_file(format!("{stem}/byteorder"), opts).unwrap();
    zw.write_all(b"little").unwrap();
    for (i, s) in storages.iter().enumerate() {
        zw.start_file(format!("{stem}/data/{i}"), opts).unwrap();
        zw.write_all(s).unwrap();
    }
    zw.start_file(format!("{stem}/version"), opts).unwrap();
    zw.write_all(b"3\n").unwrap();
    std::fs::write(path, zw.finish().unwrap().into_inner()).unwrap();
}
