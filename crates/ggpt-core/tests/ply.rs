//! PLY writer / reader.
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

use ggpt_core::io::ply::{PlyCloud, read_ply, write_ply};

fn cloud(conf: bool) -> PlyCloud {
    PlyCloud {
        points: vec![[1.0, -2.0, 3.5], [0.0, f32::MIN_POSITIVE, -1e6]],
        colors: vec![[0, 128, 255], [1, 2, 3]],
        confidence: conf.then(|| vec![0.25, 7.0]),
    }
}

#[test]
fn binary_roundtrip_and_exact_layout() {
    let dir = tempfile::tempdir().unwrap();
    for conf in [true, false] {
        let p = dir.path().join("a.ply");
        write_ply(&p, &cloud(conf)).unwrap();
        assert_eq!(read_ply(&p).unwrap(), cloud(conf));
        let b = std::fs::read(&p).unwrap();
        let text = String::from_utf8_lossy(&b);
        assert!(text.starts_with("ply\nformat binary_little_endian 1.0\ncomment ggpt-rs "));
        let end = text.find("end_header\n").unwrap() + "end_header\n".len();
        assert_eq!(b.len() - end, 2 * if conf { 19 } else { 15 });
        assert_eq!(&b[end..end + 4], &1.0f32.to_le_bytes());
        assert_eq!(&b[end + 12..end + 15], &[0, 128, 255]);
    }
}

#[test]
fn ascii_any_order_extra_properties_and_other_elements() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("b.ply");
    let s = "ply\r\nformat ascii 1.0\ncomment demo\nelement vertex 2\nproperty uchar blue\nproperty double z\nproperty float nx\n\
             property float x\nproperty uchar green\nproperty float y\nproperty uchar red\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n\
             255 3.5 0 1 128 -2 0\n3 -1e6 9 0 2 0 1\n3 0 1 1\n";
    std::fs::write(&p, s).unwrap();
    let c = read_ply(&p).unwrap();
    assert_eq!(c.points, vec![[1.0, -2.0, 3.5], [0.0, 0.0, -1e6]]);
    assert_eq!(c.colors, vec![[0, 128, 255], [1, 2, 3]]);
    assert!(c.confidence.is_none());
}

#[test]
fn binary_with_face_element_first() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("c.ply");
    let mut b = b"ply\nformat binary_little_endian 1.0\nelement face 1\nproperty list uchar int idx\nelement vertex 1\nproperty double x\nproperty double y\nproperty double z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nproperty float confidence\nend_header\n".to_vec();
    b.push(2);
    b.extend_from_slice(&5i32.to_le_bytes());
    b.extend_from_slice(&6i32.to_le_bytes());
    for v in [1.5f64, 2.5, 3.5] {
        b.extend_from_slice(&v.to_le_bytes());
    }
    b.extend_from_slice(&[9, 8, 7]);
    b.extend_from_slice(&0.5f32.to_le_bytes());
    std::fs::write(&p, &b).unwrap();
    let c = read_ply(&p).unwrap();
    assert_eq!(c.points, vec![[1.5, 2.5, 3.5]]);
    assert_eq!(c.colors, vec![[9, 8, 7]]);
    assert_eq!(c.confidence, Some(vec![0.5]));
}

#[test]
fn rejects_bad_files() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("bad.ply");
    write_ply(&p, &cloud(true)).unwrap();
    let b = std::fs::read(&p).unwrap();
    std::fs::write(&p, &b[..b.len() - 3]).unwrap();
    let e = read_ply(&p).unwrap_err().to_string();
    assert!(
        e.contains("bad.ply") && e.contains("truncated") && e.contains("[confidence]"),
        "{e}"
    );
    std::fs::write(&p, &b[..40]).unwrap();
    assert!(read_ply(&p).unwrap_err().to_string().contains("[header]"));
    let s = "ply\nformat binary_big_endian 1.0\nelement vertex 0\nend_header\n";
    std::fs::write(&p, s).unwrap();
    assert!(
        read_ply(&p)
            .unwrap_err()
            .to_string()
            .contains("binary_big_endian")
    );
    let s = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nend_header\n1 2 3 4 5\n";
    std::fs::write(&p, s).unwrap();
    let e = read_ply(&p).unwrap_err().to_string();
    assert!(e.contains("[blue]") && e.contains("missing"), "{e}");
    let s = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nproperty int red\nproperty uchar green\nproperty uchar blue\nend_header\n1 2 3 300 5 6\n";
    std::fs::write(&p, s).unwrap();
    let e = read_ply(&p).unwrap_err().to_string();
    assert!(e.contains("[red]") && e.contains("300"), "{e}");
    let s = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n1 2 three 4 5 6\n";
    std::fs::write(&p, s).unwrap();
    let e = read_ply(&p).unwrap_err().to_string();
    assert!(e.contains("[z]") && e.contains("three"), "{e}");
    // Writer rejects inconsistent lengths.
    let mut c = cloud(true);
    c.colors.pop();
    assert!(write_ply(&p, &c).is_err());
}
