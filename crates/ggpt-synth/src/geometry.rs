//! Analytic primitives and exact ray intersection in `f64`.
//!
//! Every primitive lives in its own local frame (`x_local = local_from_world * (x_world - origin)`);
//! shapes are defined in that frame. Rays are `o + t d` in the GT world frame (metres); `d` need
//! not be unit length, and the returned `t` is in units of `d` (the renderer passes
//! `d = R^T K^-1 (x, y, 1)`, so `t` is directly the camera z-depth).

use nalgebra::{Matrix3, Point3, Rotation3, Vector3};

/// Smallest accepted ray parameter (avoids self-hits at the origin).
pub const T_MIN: f64 = 1e-6;

/// A shape in its local frame.
#[derive(Debug, Clone, PartialEq)]
pub enum Shape {
    /// Rectangle in the local `z = 0` plane, `|x| <= hx`, `|y| <= hy` (two-sided).
    Rect {
        /// Half-width along local `x` (m).
        hx: f64,
        /// Half-height along local `y` (m).
        hy: f64,
    },
    /// Disc in the local `z = 0` plane, radius `r`.
    Disc {
        /// Radius (m).
        r: f64,
    },
    /// Axis-aligned box `|x_i| <= half_i`.
    Cuboid {
        /// Half-extents along the local axes (m).
        half: Vector3<f64>,
    },
    /// Capped cylinder around the local `z` axis, `x^2 + y^2 <= r^2`, `|z| <= hh`.
    Cylinder {
        /// Radius (m).
        r: f64,
        /// Half-height along local `z` (m).
        hh: f64,
    },
    /// Sphere of radius `r` centred at the local origin.
    Sphere {
        /// Radius (m).
        r: f64,
    },
}

/// Surface hit: ray parameter and the outward unit normal (world frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Ray parameter (units of the ray direction).
    pub t: f64,
    /// Outward surface normal, unit length, world frame.
    pub normal: Vector3<f64>,
}

/// A placed primitive with its material index.
#[derive(Debug, Clone, PartialEq)]
pub struct Primitive {
    /// Origin of the local frame in the world (metres).
    pub origin: Point3<f64>,
    /// Rotation `local_from_world`.
    pub local_from_world: Matrix3<f64>,
    /// Shape in the local frame.
    pub shape: Shape,
    /// Index into the world's material list.
    pub material: usize,
    /// Radius of a sphere around `origin` that contains the shape (cheap rejection test).
    pub bound: f64,
}

/// Radius of a sphere around the local origin that contains `shape`.
pub fn bounding_radius(shape: &Shape) -> f64 {
    match shape {
        Shape::Rect { hx, hy } => hx.hypot(*hy),
        Shape::Disc { r } | Shape::Sphere { r } => *r,
        Shape::Cuboid { half } => half.norm(),
        Shape::Cylinder { r, hh } => r.hypot(*hh),
    }
}

impl Primitive {
    /// A primitive with the local axes given in world coordinates (`x_axis`, `z_axis`; the `y`
    /// axis completes a right-handed frame). `z_axis` is the normal of planar shapes and the axis
    /// of cylinders.
    pub fn with_axes(
        origin: Point3<f64>,
        x_axis: Vector3<f64>,
        z_axis: Vector3<f64>,
        shape: Shape,
        material: usize,
    ) -> Self {
        let z = z_axis.normalize();
        let x = (x_axis - z * z.dot(&x_axis)).normalize();
        let y = z.cross(&x);
        let local_from_world = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
        let bound = bounding_radius(&shape) * (1.0 + 1e-9) + 1e-9;
        Primitive {
            origin,
            local_from_world,
            shape,
            material,
            bound,
        }
    }

    /// An axis-aligned primitive rotated by `yaw` (radians) about the world vertical (`y`) axis.
    pub fn yawed(origin: Point3<f64>, yaw: f64, shape: Shape, material: usize) -> Self {
        let world_from_local = Rotation3::from_axis_angle(&Vector3::y_axis(), yaw);
        let bound = bounding_radius(&shape) * (1.0 + 1e-9) + 1e-9;
        Primitive {
            origin,
            local_from_world: world_from_local.matrix().transpose(),
            shape,
            material,
            bound,
        }
    }

    /// Nearest intersection of the ray `o + t d` (world frame) with `t > T_MIN`.
    pub fn intersect(&self, o: &Point3<f64>, d: &Vector3<f64>) -> Option<Hit> {
        // Bounding-sphere rejection: distance from the origin to the ray line (or, behind the
        // ray start, to the start point) larger than the bound means no hit with t > 0.
        let oc = self.origin - o;
        let dd = d.norm_squared();
        let along = oc.dot(d);
        let r2 = self.bound * self.bound;
        if along < 0.0 {
            if oc.norm_squared() > r2 {
                return None;
            }
        } else if oc.norm_squared() - along * along / dd > r2 {
            return None;
        }
        let ol = self.local_from_world * (o - self.origin);
        let dl = self.local_from_world * d;
        let (t, nl) = match &self.shape {
            Shape::Rect { hx, hy } => {
                let t = plane_t(&ol, &dl)?;
                let p = ol + dl * t;
                if p.x.abs() > *hx || p.y.abs() > *hy {
                    return None;
                }
                (t, Vector3::z())
            }
            Shape::Disc { r } => {
                let t = plane_t(&ol, &dl)?;
                let p = ol + dl * t;
                if p.x * p.x + p.y * p.y > r * r {
                    return None;
                }
                (t, Vector3::z())
            }
            Shape::Cuboid { half } => cuboid(&ol, &dl, half)?,
            Shape::Cylinder { r, hh } => cylinder(&ol, &dl, *r, *hh)?,
            Shape::Sphere { r } => {
                let a = dl.norm_squared();
                let b = ol.dot(&dl);
                let c = ol.norm_squared() - r * r;
                let disc = b * b - a * c;
                if disc < 0.0 || a <= 0.0 {
                    return None;
                }
                let sq = disc.sqrt();
                let t0 = (-b - sq) / a;
                let t1 = (-b + sq) / a;
                let t = if t0 > T_MIN {
                    t0
                } else if t1 > T_MIN {
                    t1
                } else {
                    return None;
                };
                (t, (ol + dl * t) / *r)
            }
        };
        let normal = (self.local_from_world.transpose() * nl).normalize();
        Some(Hit { t, normal })
    }

    /// True when the world point lies inside the solid (cuboid, cylinder, sphere), with a margin
    /// `margin` (metres). Planar shapes contain nothing.
    pub fn contains(&self, p: &Point3<f64>, margin: f64) -> bool {
        let l = self.local_from_world * (p - self.origin);
        match &self.shape {
            Shape::Rect { .. } | Shape::Disc { .. } => false,
            Shape::Cuboid { half } => (0..3).all(|i| l[i].abs() <= half[i] + margin),
            Shape::Cylinder { r, hh } => l.z.abs() <= hh + margin && l.x.hypot(l.y) <= r + margin,
            Shape::Sphere { r } => l.norm() <= r + margin,
        }
    }
}

fn plane_t(ol: &Vector3<f64>, dl: &Vector3<f64>) -> Option<f64> {
    if dl.z.abs() < 1e-15 {
        return None;
    }
    let t = -ol.z / dl.z;
    (t > T_MIN).then_some(t)
}

fn cuboid(
    ol: &Vector3<f64>,
    dl: &Vector3<f64>,
    half: &Vector3<f64>,
) -> Option<(f64, Vector3<f64>)> {
    let mut t_near = f64::NEG_INFINITY;
    let mut t_far = f64::INFINITY;
    let mut axis_near = 0usize;
    let mut axis_far = 0usize;
    for i in 0..3 {
        if dl[i].abs() < 1e-15 {
            if ol[i].abs() > half[i] {
                return None;
            }
            continue;
        }
        let t1 = (-half[i] - ol[i]) / dl[i];
        let t2 = (half[i] - ol[i]) / dl[i];
        let (lo, hi) = if t1 < t2 { (t1, t2) } else { (t2, t1) };
        if lo > t_near {
            t_near = lo;
            axis_near = i;
        }
        if hi < t_far {
            t_far = hi;
            axis_far = i;
        }
    }
    if t_near > t_far || t_far <= T_MIN {
        return None;
    }
    let (t, axis) = if t_near > T_MIN {
        (t_near, axis_near)
    } else {
        (t_far, axis_far)
    };
    let p = ol + dl * t;
    let mut n = Vector3::zeros();
    n[axis] = p[axis].signum();
    Some((t, n))
}

fn cylinder(ol: &Vector3<f64>, dl: &Vector3<f64>, r: f64, hh: f64) -> Option<(f64, Vector3<f64>)> {
    let mut best: Option<(f64, Vector3<f64>)> = None;
    let mut consider = |t: f64, n: Vector3<f64>| {
        if t > T_MIN && best.is_none_or(|(bt, _)| t < bt) {
            best = Some((t, n));
        }
    };
    let a = dl.x * dl.x + dl.y * dl.y;
    if a > 1e-30 {
        let b = ol.x * dl.x + ol.y * dl.y;
        let c = ol.x * ol.x + ol.y * ol.y - r * r;
        let disc = b * b - a * c;
        if disc >= 0.0 {
            let sq = disc.sqrt();
            for t in [(-b - sq) / a, (-b + sq) / a] {
                let p = ol + dl * t;
                if p.z.abs() <= hh {
                    consider(t, Vector3::new(p.x / r, p.y / r, 0.0));
                }
            }
        }
    }
    if dl.z.abs() > 1e-15 {
        for (z, nz) in [(hh, 1.0), (-hh, -1.0)] {
            let t = (z - ol.z) / dl.z;
            let p = ol + dl * t;
            if p.x * p.x + p.y * p.y <= r * r {
                consider(t, Vector3::new(0.0, 0.0, nz));
            }
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ray_hits(p: &Primitive, o: Point3<f64>, d: Vector3<f64>) -> Option<f64> {
        p.intersect(&o, &d).map(|h| h.t)
    }

    #[test]
    fn sphere_and_cuboid_distances() {
        let s = Primitive::yawed(Point3::new(0.0, 0.0, 5.0), 0.0, Shape::Sphere { r: 1.0 }, 0);
        let t = ray_hits(&s, Point3::origin(), Vector3::new(0.0, 0.0, 2.0)).unwrap_or(f64::NAN);
        assert!((t - 2.0).abs() < 1e-12, "{t}");
        let b = Primitive::yawed(
            Point3::new(0.0, 0.0, 5.0),
            0.3,
            Shape::Cuboid {
                half: Vector3::new(1.0, 1.0, 1.0),
            },
            0,
        );
        let h = b.intersect(&Point3::origin(), &Vector3::new(0.0, 0.0, 1.0));
        let h = h.unwrap_or(Hit {
            t: f64::NAN,
            normal: Vector3::zeros(),
        });
        // Face at local z = -1 of a box yawed by 0.3 rad: the ray along z hits it at 5 - 1/cos(0.3).
        assert!((h.t - (5.0 - 1.0 / 0.3f64.cos())).abs() < 1e-12, "{}", h.t);
        assert!(h.normal.z < 0.0);
        assert!(ray_hits(&b, Point3::origin(), Vector3::new(0.0, 1.0, 0.0)).is_none());
    }

    #[test]
    fn cylinder_side_and_cap() {
        let c = Primitive::with_axes(
            Point3::new(0.0, 0.0, 4.0),
            Vector3::x(),
            -Vector3::y(),
            Shape::Cylinder { r: 0.5, hh: 1.0 },
            0,
        );
        let t = ray_hits(&c, Point3::origin(), Vector3::z()).unwrap_or(f64::NAN);
        assert!((t - 3.5).abs() < 1e-12);
        // From above (y down world: above = negative y), hitting the top cap at y = -1.
        let h = c.intersect(&Point3::new(0.0, -3.0, 4.0), &Vector3::y());
        let h = h.unwrap_or(Hit {
            t: f64::NAN,
            normal: Vector3::zeros(),
        });
        assert!((h.t - 2.0).abs() < 1e-12);
        assert!((h.normal - (-Vector3::y())).norm() < 1e-12);
    }

    #[test]
    fn rect_bounds() {
        let floor = Primitive::with_axes(
            Point3::origin(),
            Vector3::x(),
            -Vector3::y(),
            Shape::Rect { hx: 1.0, hy: 1.0 },
            0,
        );
        assert!(ray_hits(&floor, Point3::new(0.5, -1.0, 0.5), Vector3::y()).is_some());
        assert!(ray_hits(&floor, Point3::new(1.5, -1.0, 0.5), Vector3::y()).is_none());
        assert!(
            floor
                .intersect(&Point3::new(0.5, -1.0, 0.5), &-Vector3::y())
                .is_none()
        );
    }
}
