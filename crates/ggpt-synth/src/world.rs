//! Procedural scene layouts (indoor room, object-centric) and camera placement.
//!
//! World frame: metres, OpenCV-like with **y down** (the floor / ground is the plane `y = 0`,
//! "up" is `-y`). Cameras are OpenCV `cam_from_world` (x right, y down, z forward).

use nalgebra::{Matrix3, Matrix3x4, Point3, Rotation3, Vector3};

use crate::geometry::{Hit, Primitive, Shape};
use crate::regime::Regime;
use crate::rng::{SynthRng, Tag, chance, normal, stream, uniform};
use crate::texture::{Material, Rgb, TextureFamily, fbm, random_material};

/// The two scene families.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SceneKind {
    /// Indoor room: floor, walls, optional ceiling, furniture-like boxes, cylinders, spheres.
    Room,
    /// Object-centric: a cluster of primitives on a finite ground disc, cameras orbiting.
    Object,
}

impl std::fmt::Display for SceneKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            SceneKind::Room => "room",
            SceneKind::Object => "object",
        })
    }
}

impl SceneKind {
    /// Parses `room` or `object` (the [`std::fmt::Display`] names).
    pub fn parse(s: &str) -> Result<Self, crate::SynthError> {
        match s {
            "room" => Ok(SceneKind::Room),
            "object" => Ok(SceneKind::Object),
            other => Err(crate::SynthError::Config(format!(
                "unknown scene kind {other:?} (room, object)"
            ))),
        }
    }
}

/// Light of the scene (shading only; view independent).
#[derive(Debug, Clone, PartialEq)]
pub enum Light {
    /// Point light at a world position (rooms).
    Point(Point3<f64>),
    /// Directional light; the vector points from the scene towards the light (unit).
    Directional(Vector3<f64>),
}

/// A procedural world: primitives, materials, light, and the point the cameras look at.
#[derive(Debug, Clone, PartialEq)]
pub struct World {
    /// Scene kind.
    pub kind: SceneKind,
    /// All primitives (metres, world frame).
    pub prims: Vec<Primitive>,
    /// Materials referenced by `Primitive::material`.
    pub materials: Vec<Material>,
    /// Light used for shading.
    pub light: Light,
    /// Point of interest (world, metres) the cameras aim at.
    pub target: Point3<f64>,
    /// Seed of the sky's cloud noise.
    pub sky_seed: u64,
    /// Whether the room has a ceiling (rooms only).
    pub ceiling: bool,
}

impl World {
    /// Period (metres) of the repeating texture of primitive `prim` (checker, stripes), `None`
    /// for aperiodic textures or an unknown index.
    pub fn texture_period_m(&self, prim: usize) -> Option<f64> {
        let m = self.prims.get(prim)?.material;
        self.materials.get(m)?.period_m()
    }

    /// Nearest hit of the ray `o + t d` (world frame) over all primitives: `(hit, primitive index)`.
    pub fn cast(&self, o: &Point3<f64>, d: &Vector3<f64>) -> Option<(Hit, usize)> {
        let mut best: Option<(Hit, usize)> = None;
        for (i, p) in self.prims.iter().enumerate() {
            if let Some(h) = p.intersect(o, d)
                && best.is_none_or(|(b, _)| h.t < b.t)
            {
                best = Some((h, i));
            }
        }
        best
    }

    /// True when any primitive is hit with `T_MIN < t < t_max` (shadow rays).
    fn occluded(&self, o: &Point3<f64>, d: &Vector3<f64>, t_max: f64) -> bool {
        self.prims
            .iter()
            .any(|p| p.intersect(o, d).is_some_and(|h| h.t < t_max))
    }

    /// Shaded colour of a surface point `p` (world) hit by a ray with direction `d` on primitive
    /// `prim` with outward normal `n`. Lambert + ambient + hard shadows; view independent except
    /// for which side of a two-sided plane is seen.
    pub fn shade(&self, p: &Point3<f64>, d: &Vector3<f64>, n: &Vector3<f64>, prim: usize) -> Rgb {
        let albedo = self
            .prims
            .get(prim)
            .and_then(|q| self.materials.get(q.material))
            .map_or(Rgb::repeat(0.5), |m| m.albedo(p));
        let n = if n.dot(d) > 0.0 { -n } else { *n };
        let origin = p + n * 1e-6;
        let (to_light, t_max, falloff) = match &self.light {
            Light::Point(l) => {
                let v = l - origin;
                let dist = v.norm();
                (v, 1.0, 1.0 / (1.0 + 0.04 * dist * dist))
            }
            Light::Directional(l) => (*l, f64::INFINITY, 1.0),
        };
        let cos = n.dot(&to_light.normalize()).max(0.0);
        let lit = if cos > 0.0 && !self.occluded(&origin, &to_light, t_max) {
            cos * falloff
        } else {
            0.0
        };
        (albedo * (0.35 + 0.75 * lit)).map(|c| c.clamp(0.0, 1.0))
    }

    /// Sky colour seen along the world direction `d` (a function of the direction only).
    pub fn sky(&self, d: &Vector3<f64>) -> Rgb {
        let u = d.normalize();
        let elev = (-u.y).clamp(-1.0, 1.0); // up is -y
        let horizon = Rgb::new(0.78, 0.85, 0.93);
        let zenith = Rgb::new(0.32, 0.52, 0.85);
        let base = horizon.lerp(&zenith, elev.max(0.0).sqrt());
        let cloud = fbm(self.sky_seed, &(u * 4.0), 4);
        base.lerp(&Rgb::repeat(0.97), ((cloud - 0.55) * 3.0).clamp(0.0, 0.8))
    }
}

fn rect(
    origin: Point3<f64>,
    x: Vector3<f64>,
    z: Vector3<f64>,
    hx: f64,
    hy: f64,
    material: usize,
) -> Primitive {
    Primitive::with_axes(origin, x, z, Shape::Rect { hx, hy }, material)
}

/// Footprint circles used to keep furniture apart: (x, z, radius).
fn place(
    rng: &mut SynthRng,
    taken: &mut Vec<(f64, f64, f64)>,
    radius: f64,
    spread: f64,
    centre: (f64, f64),
) -> Option<(f64, f64)> {
    for _ in 0..60 {
        let a = uniform(rng, 0.0, std::f64::consts::TAU);
        let r = spread * uniform(rng, 0.0, 1.0).sqrt();
        let (x, z) = (centre.0 + r * a.cos(), centre.1 + r * a.sin());
        if taken
            .iter()
            .all(|&(tx, tz, tr)| (tx - x).hypot(tz - z) > tr + radius + 0.05)
        {
            taken.push((x, z, radius));
            return Some((x, z));
        }
    }
    None
}

/// Adds one random furniture-like item (or object) resting on the floor at `(x, z)` with the
/// footprint radius `fr`; `scale` multiplies all sizes.
#[allow(clippy::too_many_arguments)]
fn add_item(
    rng: &mut SynthRng,
    w: &mut World,
    x: f64,
    z: f64,
    fr: f64,
    scale: f64,
    kinds: &[u32],
    plain: PlainOdds,
) {
    let kind = kinds[(uniform(rng, 0.0, kinds.len() as f64) as usize).min(kinds.len() - 1)];
    let family = plain.family(rng, TextureFamily::Any, plain.items);
    w.materials.push(random_material(rng, family));
    let m = w.materials.len() - 1;
    let yaw = if chance(rng, 0.3) {
        0.0
    } else {
        uniform(rng, 0.0, std::f64::consts::FRAC_PI_2)
    };
    match kind {
        // Box (yawed or not).
        0 => {
            let half = Vector3::new(
                fr * uniform(rng, 0.55, 0.7),
                scale * uniform(rng, 0.15, 0.6),
                fr * uniform(rng, 0.45, 0.7),
            );
            w.prims.push(Primitive::yawed(
                Point3::new(x, -half.y, z),
                yaw,
                Shape::Cuboid { half },
                m,
            ));
            // Sometimes a sphere or a smaller box on top.
            if chance(rng, 0.35) {
                let r = half.x.min(half.z) * uniform(rng, 0.5, 0.9);
                let m2 = w.materials.len();
                w.materials.push(random_material(rng, TextureFamily::Any));
                w.prims.push(Primitive::yawed(
                    Point3::new(x, -2.0 * half.y - r, z),
                    0.0,
                    Shape::Sphere { r },
                    m2,
                ));
            }
        }
        // Table: top + four legs.
        1 => {
            let height = scale * uniform(rng, 0.6, 0.8);
            let top = Vector3::new(fr * 0.68, 0.03 * scale, fr * uniform(rng, 0.4, 0.68));
            w.prims.push(Primitive::yawed(
                Point3::new(x, -height + top.y, z),
                yaw,
                Shape::Cuboid { half: top },
                m,
            ));
            let rot = Rotation3::from_axis_angle(&Vector3::y_axis(), yaw);
            let leg = Vector3::new(0.03 * scale, (height - 2.0 * top.y) / 2.0, 0.03 * scale);
            for (sx, sz) in [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)] {
                let off = rot
                    * Vector3::new(
                        sx * (top.x - 0.06 * scale),
                        0.0,
                        sz * (top.z - 0.06 * scale),
                    );
                w.prims.push(Primitive::yawed(
                    Point3::new(x + off.x, -leg.y, z + off.z),
                    yaw,
                    Shape::Cuboid { half: leg },
                    m,
                ));
            }
        }
        // Vertical cylinder.
        2 => {
            let r = fr * uniform(rng, 0.6, 0.95);
            let hh = scale * uniform(rng, 0.2, 0.6);
            w.prims.push(Primitive::with_axes(
                Point3::new(x, -hh, z),
                Vector3::x(),
                -Vector3::y(),
                Shape::Cylinder { r, hh },
                m,
            ));
        }
        // Sphere, resting or floating.
        3 => {
            let r = fr * uniform(rng, 0.6, 0.95);
            let lift = if chance(rng, 0.5) {
                0.0
            } else {
                scale * uniform(rng, 0.2, 0.7)
            };
            w.prims.push(Primitive::yawed(
                Point3::new(x, -r - lift, z),
                0.0,
                Shape::Sphere { r },
                m,
            ));
        }
        // Lying cylinder (axis horizontal).
        _ => {
            let r = fr * uniform(rng, 0.25, 0.45);
            let hh = fr * uniform(rng, 0.6, 0.9);
            let axis = Vector3::new(yaw.cos(), 0.0, yaw.sin());
            w.prims.push(Primitive::with_axes(
                Point3::new(x, -r, z),
                Vector3::y(),
                axis,
                Shape::Cylinder { r, hh },
                m,
            ));
        }
    }
}

/// Camera placement limits of a room (cameras stay inside this radius around the target).
const ROOM_CAM_RADIUS: (f64, f64) = (3.0, 4.0);

/// Probabilities that a surface gets a low-texture ([`TextureFamily::Plain`]) material
/// [project, calibrated with `cargo bench -p ggpt-sfm --bench regime`, `docs/synthetic.md`]:
/// real rooms have painted walls and ceilings and often plain floors, on which dense matchers
/// lose their certainty (the paper's SfM covers 8.5-76 % of the pixels, supplementary Table 5).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlainOdds {
    /// Room floors.
    pub floor: f64,
    /// The ground disc of object scenes: plain with this probability, else weakly textured
    /// ([`TextureFamily::Weak`]); textured only in the easy regime.
    pub ground: f64,
    /// Room walls, the side panel.
    pub wall: f64,
    /// Room ceilings.
    pub ceiling: f64,
    /// Furniture and objects.
    pub items: f64,
}

impl PlainOdds {
    /// The odds of a regime: none in [`Regime::Easy`] (which then draws no extra random number,
    /// so its scenes stay bit-identical to the first generator's).
    pub fn of(regime: Regime) -> Self {
        match regime {
            Regime::Benchmark => PlainOdds {
                floor: 0.5,
                ground: 0.1,
                wall: 0.85,
                ceiling: 0.9,
                items: 0.25,
            },
            Regime::Easy => PlainOdds {
                floor: 0.0,
                ground: 0.0,
                wall: 0.0,
                ceiling: 0.0,
                items: 0.0,
            },
        }
    }

    /// `family`, or [`TextureFamily::Plain`] with probability `p` (no draw when `p == 0`).
    fn family(self, rng: &mut SynthRng, family: TextureFamily, p: f64) -> TextureFamily {
        if p > 0.0 && chance(rng, p) {
            TextureFamily::Plain
        } else {
            family
        }
    }
}

/// Builds a random indoor room. `ceiling`: `None` draws it at random (50 %); `regime` decides
/// how many surfaces are low-texture ([`PlainOdds`]).
pub fn build_room(seed: u64, ceiling: Option<bool>, regime: Regime) -> World {
    let plain = PlainOdds::of(regime);
    let mut rng = stream(seed, Tag::Layout, 0, 0);
    let ceiling = ceiling.unwrap_or_else(|| chance(&mut rng, 0.5));
    let hx = uniform(&mut rng, 3.8, 5.0);
    let back = uniform(&mut rng, 2.5, 3.8);
    let front = -(ROOM_CAM_RADIUS.1 + uniform(&mut rng, 1.0, 1.8));
    // Without a ceiling the walls are lower so that some views see sky above them.
    let height = if ceiling {
        uniform(&mut rng, 2.3, 2.9)
    } else {
        uniform(&mut rng, 1.5, 2.3)
    };
    let mid_z = 0.5 * (back + front);
    let half_d = 0.5 * (back - front) + 0.01;
    let mut w = World {
        kind: SceneKind::Room,
        prims: Vec::new(),
        materials: Vec::new(),
        light: Light::Point(Point3::new(
            uniform(&mut rng, -1.0, 1.0),
            -height + 0.3,
            uniform(&mut rng, -1.5, 1.0),
        )),
        target: Point3::new(0.0, -0.6, 0.0),
        sky_seed: rng_seed(&mut rng),
        ceiling,
    };
    let up = -Vector3::y();
    let family = plain.family(&mut rng, TextureFamily::Floor, plain.floor);
    let floor_m = push_mat(&mut w, &mut rng, family);
    w.prims.push(rect(
        Point3::new(0.0, 0.0, mid_z),
        Vector3::x(),
        up,
        hx + 0.01,
        half_d,
        floor_m,
    ));
    let walls = [
        (
            Point3::new(0.0, -height / 2.0, back),
            Vector3::x(),
            -Vector3::z(),
            hx + 0.01,
        ),
        (
            Point3::new(0.0, -height / 2.0, front),
            Vector3::x(),
            Vector3::z(),
            hx + 0.01,
        ),
        (
            Point3::new(-hx, -height / 2.0, mid_z),
            Vector3::z(),
            Vector3::x(),
            half_d,
        ),
        (
            Point3::new(hx, -height / 2.0, mid_z),
            Vector3::z(),
            -Vector3::x(),
            half_d,
        ),
    ];
    for (o, x, n, half_w) in walls {
        let family = plain.family(&mut rng, TextureFamily::Wall, plain.wall);
        let m = push_mat(&mut w, &mut rng, family);
        w.prims.push(rect(o, x, n, half_w, height / 2.0 + 0.01, m));
    }
    if ceiling {
        let family = plain.family(&mut rng, TextureFamily::Wall, plain.ceiling);
        let m = push_mat(&mut w, &mut rng, family);
        w.prims.push(rect(
            Point3::new(0.0, -height, mid_z),
            Vector3::x(),
            Vector3::y(),
            hx + 0.01,
            half_d,
            m,
        ));
    }
    // A shelf / cabinet against the back wall and a low panel on the right.
    let m = push_mat(&mut w, &mut rng, TextureFamily::Any);
    let shelf = Vector3::new(
        uniform(&mut rng, 0.5, 1.0),
        uniform(&mut rng, 0.5, 0.9),
        uniform(&mut rng, 0.15, 0.3),
    );
    w.prims.push(Primitive::yawed(
        Point3::new(
            uniform(&mut rng, -1.5, 1.5),
            -shelf.y,
            back - shelf.z - 0.02,
        ),
        0.0,
        Shape::Cuboid { half: shelf },
        m,
    ));
    let family = plain.family(&mut rng, TextureFamily::Wall, plain.wall);
    let m = push_mat(&mut w, &mut rng, family);
    let panel_h = uniform(&mut rng, 0.4, 0.9);
    w.prims.push(rect(
        Point3::new(hx - 0.6, -panel_h / 2.0, mid_z + 1.0),
        Vector3::z(),
        -Vector3::x(),
        1.2,
        panel_h / 2.0,
        m,
    ));
    // Furniture cluster around the target.
    let mut taken = vec![];
    let count = 4 + (uniform(&mut rng, 0.0, 4.0) as usize).min(3);
    for _ in 0..count {
        let fr = uniform(&mut rng, 0.3, 0.65);
        if let Some((x, z)) = place(&mut rng, &mut taken, fr, 2.0, (0.0, 0.4)) {
            add_item(&mut rng, &mut w, x, z, fr, 1.0, &[0, 0, 1, 2, 3, 4], plain);
        }
    }
    w
}

/// Builds a random object-centric scene: primitives clustered on a finite ground disc;
/// `regime` decides how many surfaces are low-texture ([`PlainOdds`]).
pub fn build_object(seed: u64, regime: Regime) -> World {
    let plain = PlainOdds::of(regime);
    let mut rng = stream(seed, Tag::Layout, 1, 0);
    let sun = Vector3::new(
        uniform(&mut rng, -0.6, 0.6),
        -1.0,
        uniform(&mut rng, -0.6, 0.6),
    )
    .normalize();
    let mut w = World {
        kind: SceneKind::Object,
        prims: Vec::new(),
        materials: Vec::new(),
        light: Light::Directional(sun),
        target: Point3::new(0.0, -0.25, 0.0),
        sky_seed: rng_seed(&mut rng),
        ceiling: false,
    };
    let family = match regime {
        Regime::Easy => TextureFamily::Floor,
        Regime::Benchmark => plain.family(&mut rng, TextureFamily::Weak, plain.ground),
    };
    let m = push_mat(&mut w, &mut rng, family);
    let ground_r = uniform(&mut rng, 4.0, 6.0);
    w.prims.push(Primitive::with_axes(
        Point3::origin(),
        Vector3::x(),
        -Vector3::y(),
        Shape::Disc { r: ground_r },
        m,
    ));
    let mut taken = vec![];
    let count = 3 + (uniform(&mut rng, 0.0, 5.0) as usize).min(4);
    for _ in 0..count {
        let fr = uniform(&mut rng, 0.12, 0.35);
        if let Some((x, z)) = place(&mut rng, &mut taken, fr, 0.8, (0.0, 0.0)) {
            add_item(&mut rng, &mut w, x, z, fr, 0.55, &[0, 0, 2, 3, 4], plain);
        }
    }
    w
}

fn rng_seed(rng: &mut SynthRng) -> u64 {
    use rand::Rng;
    rng.random()
}

fn push_mat(w: &mut World, rng: &mut SynthRng, family: TextureFamily) -> usize {
    w.materials.push(random_material(rng, family));
    w.materials.len() - 1
}

/// `cam_from_world` of a camera at `centre` looking at `look_at` (world y down), rolled by `roll`
/// radians about its optical axis. OpenCV axes.
pub fn look_at(centre: &Point3<f64>, look_at: &Point3<f64>, roll: f64) -> Matrix3x4<f64> {
    let z = (look_at - centre).normalize();
    let down = Vector3::y();
    let x0 = down.cross(&z).normalize();
    let y0 = z.cross(&x0);
    let (s, c) = roll.sin_cos();
    let x = x0 * c + y0 * s;
    let y = z.cross(&x);
    let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
    let t = -(r * centre.coords);
    let mut m = Matrix3x4::zeros();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    m.set_column(3, &t);
    m
}

/// Places `n` cameras on an arc (rooms) or orbit (objects) around the world's target, all
/// looking at (a jittered) target. Returns `cam_from_world` (metres) and the focal length in
/// pixels for an image of width `width` (horizontal field of view drawn in 55..70 deg).
pub fn place_cameras(
    world: &World,
    seed: u64,
    n: usize,
    width: usize,
) -> (Vec<Matrix3x4<f64>>, f64) {
    let mut rng = stream(seed, Tag::Cameras, 0, 0);
    let fov = uniform(&mut rng, 55.0, 70.0).to_radians();
    let focal = (width as f64 / 2.0) / (fov / 2.0).tan();
    // Angular step between neighbouring views (deg) and the total span of the arc / orbit.
    let gaps = (n.max(2) - 1) as f64;
    let (span, radius, height) = match world.kind {
        SceneKind::Room => (
            (uniform(&mut rng, 6.0, 12.0) * gaps).min(90.0),
            ROOM_CAM_RADIUS,
            (1.3, 1.8),
        ),
        SceneKind::Object => (
            (uniform(&mut rng, 15.0, 26.0) * gaps).min(300.0),
            (1.6, 2.3),
            (0.7, 1.5),
        ),
    };
    let phi0 = match world.kind {
        SceneKind::Room => 0.0,
        SceneKind::Object => uniform(&mut rng, 0.0, 360.0),
    };
    let mut cams = Vec::with_capacity(n);
    let foot = Point3::new(world.target.x, 0.0, world.target.z);
    let h_mid = uniform(&mut rng, height.0, height.1);
    for i in 0..n {
        let frac = if n > 1 {
            i as f64 / (n - 1) as f64 - 0.5
        } else {
            0.0
        };
        let step = if n > 1 { span / (n - 1) as f64 } else { 0.0 };
        let phi =
            (phi0 + span * frac + 0.2 * step * normal(&mut rng).clamp(-2.0, 2.0)).to_radians();
        let r = uniform(&mut rng, radius.0, radius.1);
        let h = (h_mid + 0.12 * normal(&mut rng)).clamp(height.0, height.1);
        let centre = Point3::new(foot.x + r * phi.sin(), -h, foot.z - r * phi.cos());
        let aim = world.target
            + Vector3::new(
                0.25 * normal(&mut rng),
                0.1 * normal(&mut rng),
                0.25 * normal(&mut rng),
            );
        let roll = 2f64.to_radians() * normal(&mut rng).clamp(-2.0, 2.0);
        cams.push(look_at(&centre, &aim, roll));
    }
    (cams, focal)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn look_at_is_opencv() {
        let c = Point3::new(0.0, -1.5, -4.0);
        let m = look_at(&c, &Point3::new(0.0, -1.5, 0.0), 0.0);
        let r = m.fixed_view::<3, 3>(0, 0).into_owned();
        assert!((r - Matrix3::identity()).norm() < 1e-12);
        let p = r * Vector3::new(0.0, -1.5, 0.0) + m.column(3);
        assert!((p - Vector3::new(0.0, 0.0, 4.0)).norm() < 1e-12);
    }

    #[test]
    fn cameras_are_outside_solids() {
        for seed in 0..6 {
            for w in [
                build_room(seed, None, Regime::Easy),
                build_object(seed, Regime::Easy),
                build_room(seed, None, Regime::Benchmark),
                build_object(seed, Regime::Benchmark),
            ] {
                let (cams, f) = place_cameras(&w, seed, 8, 518);
                assert!(f > 300.0 && f < 520.0);
                for m in &cams {
                    let r = m.fixed_view::<3, 3>(0, 0).into_owned();
                    let c = Point3::from(-(r.transpose() * m.column(3)));
                    assert!(
                        w.prims.iter().all(|p| !p.contains(&c, 0.05)),
                        "camera inside a solid, seed {seed}"
                    );
                }
            }
        }
    }
}
