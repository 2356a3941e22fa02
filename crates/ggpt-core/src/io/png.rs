//! PNG output of RGB8 images: the one encoder behind scene previews, error maps and training
//! curves. Writes are atomic ([`crate::io::atomic`]).

use std::path::Path;

use image::ImageEncoder;
use image::codecs::png::PngEncoder;

use crate::{CoreError, Result};

/// Encodes `rgb` (`[height, width, 3]` row-major, RGB8) as PNG bytes; `path` names the image
/// in errors.
pub fn encode_rgb8(path: &Path, width: usize, height: usize, rgb: &[u8]) -> Result<Vec<u8>> {
    let (Ok(w), Ok(h)) = (u32::try_from(width), u32::try_from(height)) else {
        return Err(CoreError::format(
            path,
            "",
            format!("image {width}x{height} too large for PNG"),
        ));
    };
    if rgb.len() != 3 * width * height {
        return Err(CoreError::format(
            path,
            "",
            format!(
                "image buffer of {} bytes, expected {width} x {height} x 3",
                rgb.len()
            ),
        ));
    }
    let mut bytes = Vec::new();
    PngEncoder::new(&mut bytes)
        .write_image(rgb, w, h, image::ExtendedColorType::Rgb8)
        .map_err(|e| CoreError::format(path, "", format!("PNG encoding failed: {e}")))?;
    Ok(bytes)
}

/// Writes `rgb` (`[height, width, 3]`, RGB8) to `path` as PNG, atomically.
pub fn write_rgb8(path: &Path, width: usize, height: usize, rgb: &[u8]) -> Result<()> {
    let bytes = encode_rgb8(path, width, height, rgb)?;
    crate::io::atomic::write_bytes_atomic(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_and_refuses_a_wrong_size() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.png");
        let rgb: Vec<u8> = (0..2 * 3 * 3).map(|i| (i * 13) as u8).collect();
        write_rgb8(&p, 3, 2, &rgb).unwrap();
        let back = image::open(&p).unwrap().to_rgb8();
        assert_eq!((back.width(), back.height()), (3, 2));
        assert_eq!(back.into_raw(), rgb);
        let e = write_rgb8(&p, 4, 2, &rgb).unwrap_err().to_string();
        assert!(
            e.contains("a.png") && e.contains("expected 4 x 2 x 3"),
            "{e}"
        );
    }
}
