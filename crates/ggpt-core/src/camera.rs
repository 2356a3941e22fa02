//! Pinhole cameras with `cam_from_world` extrinsics (OpenCV axes: x right, y down, z forward).
//!
//! Intrinsics use the pixel-centre convention: the centre of the top-left pixel is `(0, 0)`, so
//! the principal point of an `h x w` image is `((w - 1) / 2, (h - 1) / 2)`.

use nalgebra::{Matrix3, Matrix3x4, Matrix4, Point3, Vector2, Vector3};

/// The cameras of `N` views.
#[derive(Debug, Clone, PartialEq)]
pub struct Cameras {
    /// `cam_from_world = [R | t]` per view: `X_cam = R X_world + t` (world units).
    pub cam_from_world: Vec<Matrix3x4<f64>>,
    /// `K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]` per view, pixel-centre convention (pixels).
    pub intrinsics: Vec<Matrix3<f64>>,
}

impl Cameras {
    /// Number of views.
    pub fn len(&self) -> usize {
        self.cam_from_world.len()
    }

    /// True when there is no view.
    pub fn is_empty(&self) -> bool {
        self.cam_from_world.is_empty()
    }

    /// Rotation part `R` of view `i`'s `cam_from_world`.
    pub fn rotation(&self, i: usize) -> Matrix3<f64> {
        self.cam_from_world[i].fixed_view::<3, 3>(0, 0).into_owned()
    }

    /// Translation part `t` of view `i`'s `cam_from_world`.
    pub fn translation(&self, i: usize) -> Vector3<f64> {
        self.cam_from_world[i].column(3).into_owned()
    }

    /// Camera centre `C = -R^T t` of view `i` (world frame).
    pub fn center(&self, i: usize) -> Point3<f64> {
        Point3::from(-(self.rotation(i).transpose() * self.translation(i)))
    }

    /// 4x4 homogeneous `cam_from_world` of view `i`.
    pub fn cam_from_world_4x4(&self, i: usize) -> Matrix4<f64> {
        to_4x4(&self.cam_from_world[i])
    }

    /// Projection of a world point into view `i` (ff pixels, pixel-centre convention).
    /// Returns `None` when the point has depth `z <= 0` in that camera.
    pub fn project(&self, i: usize, x_world: &Point3<f64>) -> Option<Vector2<f64>> {
        let x_cam = self.rotation(i) * x_world.coords + self.translation(i);
        if x_cam.z <= 0.0 {
            return None;
        }
        let k = &self.intrinsics[i];
        Some(Vector2::new(
            k[(0, 0)] * x_cam.x / x_cam.z + k[(0, 2)],
            k[(1, 1)] * x_cam.y / x_cam.z + k[(1, 2)],
        ))
    }

    /// True when every entry of every matrix is finite.
    pub fn is_finite(&self) -> bool {
        self.cam_from_world
            .iter()
            .all(|m| m.iter().all(|v| v.is_finite()))
            && self
                .intrinsics
                .iter()
                .all(|m| m.iter().all(|v| v.is_finite()))
    }
}

/// Extends a 3x4 `[R | t]` to 4x4 with last row `0 0 0 1`.
pub fn to_4x4(m: &Matrix3x4<f64>) -> Matrix4<f64> {
    let mut out = Matrix4::identity();
    out.fixed_view_mut::<3, 4>(0, 0).copy_from(m);
    out
}

/// Principal point `((w - 1) / 2, (h - 1) / 2)` of an `h x w` image (pixel-centre convention).
pub fn centred_principal_point(h: usize, w: usize) -> (f64, f64) {
    ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0)
}
