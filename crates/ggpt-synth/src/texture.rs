//! Solid (3D) procedural textures.
//!
//! A texture maps a **world point** (metres, GT world frame) to an RGB colour in `[0, 1]`. Because
//! the colour is a function of the 3D point and not of the view, a surface point has the same
//! albedo in every view, so dense correspondences are well defined.

use nalgebra::{Point3, Vector3};

use crate::rng::{SynthRng, normal, splitmix64, uniform, unit_vector};

/// RGB colour, components in `[0, 1]`.
pub type Rgb = Vector3<f64>;

/// Integer lattice hash of a 3D cell, mapped to `[0, 1)`.
fn lattice(seed: u64, x: i64, y: i64, z: i64) -> f64 {
    let h = splitmix64(
        seed ^ (x as u64).wrapping_mul(0x8CB9_2BA7_2F3D_8DD7)
            ^ (y as u64).wrapping_mul(0xD1B5_4A32_D192_ED03)
            ^ (z as u64).wrapping_mul(0xABC9_8388_FB8F_AC03),
    );
    (h >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

fn quintic(t: f64) -> f64 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

/// Smooth 3D value noise in `[0, 1]` (trilinear blend of lattice values with quintic fade).
pub fn value_noise(seed: u64, p: &Vector3<f64>) -> f64 {
    let fx = p.x.floor();
    let fy = p.y.floor();
    let fz = p.z.floor();
    let (ix, iy, iz) = (fx as i64, fy as i64, fz as i64);
    let (tx, ty, tz) = (quintic(p.x - fx), quintic(p.y - fy), quintic(p.z - fz));
    let mut acc = 0.0;
    for dz in 0..2i64 {
        let wz = if dz == 0 { 1.0 - tz } else { tz };
        for dy in 0..2i64 {
            let wy = if dy == 0 { 1.0 - ty } else { ty };
            for dx in 0..2i64 {
                let wx = if dx == 0 { 1.0 - tx } else { tx };
                acc += wx * wy * wz * lattice(seed, ix + dx, iy + dy, iz + dz);
            }
        }
    }
    acc
}

/// Fractal Brownian motion: `octaves` octaves of value noise (lacunarity 2, gain 0.5), in `[0, 1]`.
pub fn fbm(seed: u64, p: &Vector3<f64>, octaves: u32) -> f64 {
    let mut amp = 0.5;
    let mut freq = 1.0;
    let mut sum = 0.0;
    let mut norm = 0.0;
    for o in 0..octaves {
        sum += amp * value_noise(seed.wrapping_add(o as u64 * 0x51), &(p * freq));
        norm += amp;
        amp *= 0.5;
        freq *= 2.03;
    }
    if norm > 0.0 { sum / norm } else { 0.5 }
}

/// Piecewise-linear palette lookup, `t` clamped to `[0, 1]`.
fn palette(colours: &[Rgb; 3], t: f64) -> Rgb {
    let t = t.clamp(0.0, 1.0) * 2.0;
    if t < 1.0 {
        colours[0].lerp(&colours[1], t)
    } else {
        colours[1].lerp(&colours[2], t - 1.0)
    }
}

/// A procedural solid texture. Frequencies are in cycles per metre.
#[derive(Debug, Clone, PartialEq)]
pub enum Texture {
    /// 3D checkerboard of cell size `cell` (m).
    Checker {
        /// Cell size (m).
        cell: f64,
        /// First colour.
        a: Rgb,
        /// Second colour.
        b: Rgb,
    },
    /// Parallel stripes along `axis` with period `period` (m), edges warped by noise.
    Stripes {
        /// Direction across the stripes (unit).
        axis: Vector3<f64>,
        /// Period (m).
        period: f64,
        /// Noise warp of the edges (m).
        warp: f64,
        /// First colour.
        a: Rgb,
        /// Second colour.
        b: Rgb,
    },
    /// Multi-octave value noise through a 3-colour palette ("photo-like" mottling).
    Noise {
        /// Base frequency (cycles per metre).
        freq: f64,
        /// Octaves.
        octaves: u32,
        /// Palette.
        colours: [Rgb; 3],
    },
    /// Linear gradient along `axis` over `length` (m), plus noise.
    Gradient {
        /// Direction of the gradient (unit).
        axis: Vector3<f64>,
        /// Length over which `a` turns into `b` (m).
        length: f64,
        /// Start colour.
        a: Rgb,
        /// End colour.
        b: Rgb,
    },
    /// Wood: concentric rings around an axis through `centre`, perturbed by turbulence.
    Wood {
        /// A point on the ring axis (world frame, m).
        centre: Point3<f64>,
        /// Ring axis (unit).
        axis: Vector3<f64>,
        /// Rings per metre.
        ring_freq: f64,
        /// Turbulence amplitude.
        turbulence: f64,
        /// Light wood colour.
        light: Rgb,
        /// Dark ring colour.
        dark: Rgb,
    },
    /// Marble: `sin` bands along `dir` perturbed by strong turbulence.
    Marble {
        /// Band direction (unit).
        dir: Vector3<f64>,
        /// Bands per metre.
        freq: f64,
        /// Turbulence amplitude.
        turbulence: f64,
        /// Palette.
        colours: [Rgb; 3],
    },
    /// Random blobs of palette colours on a base colour.
    Blobs {
        /// Blob frequency (cycles per metre).
        freq: f64,
        /// Noise level above which a blob is drawn.
        threshold: f64,
        /// Base colour.
        base: Rgb,
        /// Blob palette.
        colours: [Rgb; 3],
    },
}

/// A texture with its noise seed and a fine-detail amount (every surface gets some fine grain, as
/// real surfaces do; it is what makes dense matching possible).
#[derive(Debug, Clone, PartialEq)]
pub struct Material {
    /// The pattern.
    pub texture: Texture,
    /// Seed of the texture's noise lattice.
    pub seed: u64,
    /// Amplitude of the fine multiplicative grain (0..0.3).
    pub grain: f64,
    /// Frequency of the fine grain (cycles per metre).
    pub grain_freq: f64,
}

impl Material {
    /// Albedo of the world point `p` (metres, GT world frame), RGB in `[0, 1]`.
    pub fn albedo(&self, p: &Point3<f64>) -> Rgb {
        let v = p.coords;
        let s = self.seed;
        let base = match &self.texture {
            Texture::Checker { cell, a, b } => {
                let q = v / *cell;
                let parity =
                    (q.x.floor() as i64 + q.y.floor() as i64 + q.z.floor() as i64).rem_euclid(2);
                if parity == 0 { *a } else { *b }
            }
            Texture::Stripes {
                axis,
                period,
                warp,
                a,
                b,
            } => {
                let u = axis.dot(&v) / *period + warp * (fbm(s, &(v * 3.0), 3) - 0.5);
                let t = 0.5 + 0.5 * (std::f64::consts::TAU * u).sin();
                a.lerp(b, smoothstep(0.35, 0.65, t))
            }
            Texture::Noise {
                freq,
                octaves,
                colours,
            } => palette(colours, 1.6 * (fbm(s, &(v * *freq), *octaves) - 0.5) + 0.5),
            Texture::Gradient { axis, length, a, b } => {
                let t = axis.dot(&v) / *length + 0.5 + 0.25 * (fbm(s, &(v * 2.0), 3) - 0.5);
                a.lerp(b, t.clamp(0.0, 1.0))
            }
            Texture::Wood {
                centre,
                axis,
                ring_freq,
                turbulence,
                light,
                dark,
            } => {
                let d = v - centre.coords;
                let radial = (d - axis * axis.dot(&d)).norm();
                let r = radial * ring_freq + turbulence * fbm(s, &(v * 4.0), 4);
                let ring = r - r.floor();
                light.lerp(dark, smoothstep(0.0, 0.8, ring).powf(1.5))
            }
            Texture::Marble {
                dir,
                freq,
                turbulence,
                colours,
            } => {
                let u = dir.dot(&v) * freq + turbulence * fbm(s, &(v * 2.5), 5);
                palette(colours, 0.5 + 0.5 * (std::f64::consts::TAU * u).sin())
            }
            Texture::Blobs {
                freq,
                threshold,
                base,
                colours,
            } => {
                let n = fbm(s, &(v * *freq), 3);
                let pick = value_noise(s ^ 0x77, &(v * (*freq * 0.5)));
                let blob = palette(colours, pick);
                base.lerp(&blob, smoothstep(*threshold, threshold + 0.04, n))
            }
        };
        let g = 1.0 + self.grain * 2.0 * (fbm(s ^ 0xFEED, &(v * self.grain_freq), 3) - 0.5);
        (base * g).map(|c| c.clamp(0.0, 1.0))
    }
}

fn smoothstep(e0: f64, e1: f64, x: f64) -> f64 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Random colour: hue uniform, saturation and value in the given ranges (HSV -> RGB).
pub fn random_colour(rng: &mut SynthRng, sat: (f64, f64), val: (f64, f64)) -> Rgb {
    let h = uniform(rng, 0.0, 6.0);
    let s = uniform(rng, sat.0, sat.1);
    let v = uniform(rng, val.0, val.1);
    let c = v * s;
    let x = c * (1.0 - ((h % 2.0) - 1.0).abs());
    let (r, g, b) = match h as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    Rgb::new(r + m, g + m, b + m)
}

fn palette3(rng: &mut SynthRng) -> [Rgb; 3] {
    [
        random_colour(rng, (0.2, 0.8), (0.15, 0.45)),
        random_colour(rng, (0.1, 0.7), (0.4, 0.75)),
        random_colour(rng, (0.0, 0.5), (0.7, 0.98)),
    ]
}

/// Which family of textures to draw from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TextureFamily {
    /// Any texture.
    Any,
    /// Floors: wood, checker (tiles), marble, noise.
    Floor,
    /// Walls: noise, stripes, gradients, blobs.
    Wall,
    /// Low-texture paint / plaster: a faint gradient of one colour with a very weak grain, the
    /// surfaces on which real dense matchers lose their certainty ([`crate::Regime::Benchmark`]).
    Plain,
    /// Weak texture (worn concrete, asphalt, short carpet): like [`TextureFamily::Plain`] with a
    /// stronger grain ([`WEAK_GRAIN`]), on which matchers are partly certain and noisy.
    Weak,
}

/// Draws a random material of the given family.
pub fn random_material(rng: &mut SynthRng, family: TextureFamily) -> Material {
    let kind = match family {
        TextureFamily::Any => (uniform(rng, 0.0, 7.0) as u32).min(6),
        TextureFamily::Floor => [0u32, 3, 4, 5][(uniform(rng, 0.0, 4.0) as usize).min(3)],
        TextureFamily::Wall => [1u32, 2, 3, 6][(uniform(rng, 0.0, 4.0) as usize).min(3)],
        TextureFamily::Plain => return plain_material(rng, PLAIN_GRAIN),
        TextureFamily::Weak => return plain_material(rng, WEAK_GRAIN),
    };
    let texture = match kind {
        0 => Texture::Checker {
            cell: uniform(rng, 0.15, 0.6),
            a: random_colour(rng, (0.0, 0.6), (0.2, 0.5)),
            b: random_colour(rng, (0.0, 0.6), (0.6, 0.95)),
        },
        1 => Texture::Stripes {
            axis: unit_vector(rng),
            period: uniform(rng, 0.08, 0.5),
            warp: uniform(rng, 0.0, 0.8),
            a: random_colour(rng, (0.1, 0.8), (0.2, 0.6)),
            b: random_colour(rng, (0.1, 0.8), (0.5, 0.95)),
        },
        2 => Texture::Noise {
            freq: uniform(rng, 1.5, 8.0),
            octaves: 5,
            colours: palette3(rng),
        },
        3 => Texture::Gradient {
            axis: unit_vector(rng),
            length: uniform(rng, 0.5, 4.0),
            a: random_colour(rng, (0.1, 0.9), (0.2, 0.9)),
            b: random_colour(rng, (0.1, 0.9), (0.2, 0.9)),
        },
        4 => {
            let light = random_colour(rng, (0.3, 0.6), (0.55, 0.85));
            Texture::Wood {
                centre: Point3::new(
                    uniform(rng, -5.0, 5.0),
                    uniform(rng, -5.0, 5.0),
                    uniform(rng, -5.0, 5.0),
                ),
                axis: unit_vector(rng),
                ring_freq: uniform(rng, 6.0, 20.0),
                turbulence: uniform(rng, 0.5, 2.5),
                light,
                dark: light * uniform(rng, 0.45, 0.7),
            }
        }
        5 => Texture::Marble {
            dir: unit_vector(rng),
            freq: uniform(rng, 0.8, 3.0),
            turbulence: uniform(rng, 1.0, 4.0),
            colours: palette3(rng),
        },
        _ => Texture::Blobs {
            freq: uniform(rng, 2.0, 10.0),
            threshold: uniform(rng, 0.5, 0.62),
            base: random_colour(rng, (0.0, 0.5), (0.4, 0.9)),
            colours: palette3(rng),
        },
    };
    let seed = splitmix64((normal(rng).to_bits()) ^ 0x5EED);
    Material {
        texture,
        seed,
        grain: uniform(rng, 0.12, 0.3),
        grain_freq: uniform(rng, 15.0, 40.0),
    }
}

/// Grain amplitude range of [`TextureFamily::Plain`] materials (textured ones: 0.12-0.3).
pub const PLAIN_GRAIN: (f64, f64) = (0.004, 0.02);
/// Grain amplitude range of [`TextureFamily::Weak`] materials.
pub const WEAK_GRAIN: (f64, f64) = (0.1, 0.22);

/// A low-texture material: one colour with a faint gradient over metres and a weak grain of
/// amplitude in `grain`.
fn plain_material(rng: &mut SynthRng, grain: (f64, f64)) -> Material {
    let a = random_colour(rng, (0.0, 0.35), (0.45, 0.9));
    let b = a * uniform(rng, 0.92, 1.08);
    let texture = Texture::Gradient {
        axis: unit_vector(rng),
        length: uniform(rng, 2.0, 6.0),
        a,
        b: b.map(|c| c.clamp(0.0, 1.0)),
    };
    let seed = splitmix64((normal(rng).to_bits()) ^ 0x9A17);
    Material {
        texture,
        seed,
        grain: uniform(rng, grain.0, grain.1),
        grain_freq: uniform(rng, 15.0, 40.0),
    }
}

impl Material {
    /// Spatial period (metres) of a repeating pattern (checker: two cells; stripes: the
    /// period); `None` for aperiodic textures.
    pub fn period_m(&self) -> Option<f64> {
        match &self.texture {
            Texture::Checker { cell, .. } => Some(2.0 * cell),
            Texture::Stripes { period, .. } => Some(*period),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::{Tag, stream};

    #[test]
    fn noise_is_bounded_and_smooth() {
        let p = Vector3::new(0.3, -1.7, 2.2);
        let a = value_noise(3, &p);
        let b = value_noise(3, &(p + Vector3::new(1e-4, 0.0, 0.0)));
        assert!((0.0..=1.0).contains(&a));
        assert!((a - b).abs() < 1e-3);
        let f = fbm(3, &p, 5);
        assert!((0.0..=1.0).contains(&f));
    }

    #[test]
    fn albedo_is_a_function_of_the_point_and_in_range() {
        let mut rng = stream(1, Tag::Texture, 0, 0);
        for _ in 0..50 {
            let m = random_material(&mut rng, TextureFamily::Any);
            for i in 0..20 {
                let p = Point3::new(i as f64 * 0.37 - 3.0, 0.11 * i as f64, -0.5);
                let c = m.albedo(&p);
                assert!(
                    c.iter().all(|v| (0.0..=1.0).contains(v)),
                    "{c:?} of {:?}",
                    m.texture
                );
                assert_eq!(c, m.albedo(&p));
            }
        }
    }

    #[test]
    fn textures_vary_spatially() {
        let mut rng = stream(2, Tag::Texture, 0, 0);
        let m = random_material(&mut rng, TextureFamily::Wall);
        let cols: Vec<Rgb> = (0..100)
            .map(|i| m.albedo(&Point3::new(0.013 * i as f64, 0.007 * i as f64, 1.0)))
            .collect();
        let mean = cols.iter().fold(Rgb::zeros(), |a, c| a + c) / cols.len() as f64;
        let var = cols.iter().map(|c| (c - mean).norm_squared()).sum::<f64>() / cols.len() as f64;
        assert!(var > 1e-4, "texture is flat: var {var}");
    }
}
