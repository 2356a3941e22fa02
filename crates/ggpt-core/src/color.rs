//! Colour conversion of the official export (`formats.md`, PLY and images) and of the error maps.

/// Colour conversion of the official export: `floor(255 · clamp(v, 0, 1))` in `f32`.
pub fn color_u8(v: f32) -> u8 {
    let c = if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
    (255.0f32 * c).floor() as u8
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colour_conversion_truncates() {
        assert_eq!(color_u8(0.0), 0);
        assert_eq!(color_u8(1.0), 255);
        assert_eq!(color_u8(1.5), 255);
        assert_eq!(color_u8(-0.2), 0);
        assert_eq!(color_u8(0.5), 127); // 127.5 -> 127
        assert_eq!(color_u8(0.999), 254); // 254.745 -> 254
        assert_eq!(color_u8(f32::NAN), 0);
    }
}
