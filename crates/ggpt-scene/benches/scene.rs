//! Benchmark of the scene pipeline stages around the network (`cargo bench -p ggpt-scene
//! --bench scene -- [views] [h] [w]`): a synthetic room seen by `views` cameras at `h x w`
//! (default 16 x 392 x 518, the VGGT resolution), 20 % DLT pixels; an identity "network".
//! Prints a table of wall-clock times per stage.

use std::time::Instant;

use clap::Parser;
use ggpt_core::{Cameras, Dims, FeedForward, Scene, SfmResult};
use ggpt_scene::SceneError;
use ggpt_scene::chunker::{ChunkInputs, ChunkParams, PcgDraws, sample_chunks};
use ggpt_scene::driver::{ChunkRefiner, RefineOptions, RefinedChunk, refine_scene};
use ggpt_scene::radius::{RadiusRule, scene_radius};
use ggpt_scene::record::ChunkRecord;
use nalgebra::{Matrix3, Matrix3x4, Rotation3, Vector3};

/// Scene pipeline stages around the network, on a synthetic room.
#[derive(Parser, Debug)]
#[command(name = "scene")]
struct Args {
    /// Views (cameras).
    #[arg(default_value_t = 16)]
    views: usize,
    /// Image height.
    #[arg(default_value_t = 392)]
    h: usize,
    /// Image width.
    #[arg(default_value_t = 518)]
    w: usize,
    /// Passed by `cargo bench`; ignored.
    #[arg(long, hide = true)]
    bench: bool,
}

/// Identity network: returns the normalised dense points with confidence 1.
struct Identity;
impl ChunkRefiner for Identity {
    fn refine(&mut self, chunks: &[ChunkRecord]) -> Result<Vec<RefinedChunk>, SceneError> {
        Ok(chunks
            .iter()
            .map(|c| RefinedChunk {
                points: c.ff_pts.clone(),
                conf: vec![1.0; c.len()],
            })
            .collect())
    }
}

/// Room `[-2, 2]^3`; camera `n` at radius 0.3 on a circle, yawed by `n · 360° / views`.
fn synth(views: usize, h: usize, w: usize) -> (Scene, SfmResult) {
    let dims = Dims { n: views, h, w };
    let f = 0.8 * w as f64;
    let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let k = Matrix3::new(f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0);
    let mut cams = Cameras {
        cam_from_world: Vec::new(),
        intrinsics: Vec::new(),
    };
    let mut pts = vec![0.0f32; 3 * dims.pixels()];
    let mut dlt = vec![0.0f32; 3 * dims.pixels()];
    let mut mask = vec![false; dims.pixels()];
    for n in 0..views {
        let yaw = n as f64 * std::f64::consts::TAU / views as f64;
        let world_from_cam = Rotation3::from_euler_angles(0.0, yaw, 0.0);
        let centre = Vector3::new(0.3 * yaw.cos(), 0.1, 0.3 * yaw.sin());
        let r = world_from_cam.inverse();
        let t = -(r * centre);
        let mut m = Matrix3x4::zeros();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(r.matrix());
        m.set_column(3, &t);
        cams.cam_from_world.push(m);
        cams.intrinsics.push(k);
        for y in 0..h {
            for x in 0..w {
                let ray =
                    world_from_cam * Vector3::new((x as f64 - cx) / f, (y as f64 - cy) / f, 1.0);
                let mut tmin = f64::INFINITY;
                for a in 0..3 {
                    if ray[a].abs() > 1e-12 {
                        let wall = if ray[a] > 0.0 { 2.0 } else { -2.0 };
                        let tt = (wall - centre[a]) / ray[a];
                        if tt > 0.0 {
                            tmin = tmin.min(tt);
                        }
                    }
                }
                let p = dims.index(n, y, x);
                let xw = centre + ray * tmin;
                for a in 0..3 {
                    pts[3 * p + a] = xw[a] as f32;
                }
                if (x + 3 * y) % 5 == 0 {
                    mask[p] = true;
                    for a in 0..3 {
                        dlt[3 * p + a] = (xw[a] * 1.001) as f32;
                    }
                }
            }
        }
    }
    let ff = FeedForward {
        points: pts,
        conf: vec![2.0; dims.pixels()],
        cameras: cams.clone(),
    };
    let scene = Scene {
        name: "bench".into(),
        dims,
        images: vec![0.5; 3 * dims.pixels()],
        gt: None,
        ff: Some(ff),
        sfm: None,
        matches: Vec::new(),
    };
    let sfm = SfmResult {
        points: dlt,
        mask,
        cameras: cams,
        camera_success: true,
        points_success: true,
    };
    (scene, sfm)
}

fn main() -> Result<(), SceneError> {
    let Args {
        views,
        h,
        w,
        bench: _,
    } = Args::parse();
    let t = Instant::now();
    let (scene, sfm) = synth(views, h, w);
    println!(
        "synthetic scene: {views} views x {h} x {w} = {} pixels, {} DLT pixels ({:.2} s to build)",
        scene.dims.pixels(),
        sfm.mask.iter().filter(|&&m| m).count(),
        t.elapsed().as_secs_f64()
    );
    let ff = scene
        .ff
        .as_ref()
        .ok_or_else(|| SceneError::Invalid("no ff".into()))?;
    println!("| stage | time (s) | notes |\n|---|---|---|");
    let t = Instant::now();
    let r = scene_radius(&ff.points, scene.dims, RadiusRule::AcrossViews, None)?;
    println!(
        "| radius (across views) | {:.3} | R = {:.4} |",
        t.elapsed().as_secs_f64(),
        r.radius
    );
    let t = Instant::now();
    let inputs = ChunkInputs {
        ff_points: &ff.points,
        dlt_points: &sfm.points,
        dlt_mask: &sfm.mask,
        roi: None,
    };
    let set = sample_chunks(
        inputs,
        r.radius,
        &ChunkParams::default(),
        &mut PcgDraws::new(42),
    )?;
    let shrinks: u32 = set.attempts.iter().map(|a| a.shrinks).sum();
    println!(
        "| chunk sampling | {:.3} | {} chunks, {} attempts, {shrinks} shrinks, stop {:?} |",
        t.elapsed().as_secs_f64(),
        set.chunks.len(),
        set.attempts.len(),
        set.stop
    );
    let t = Instant::now();
    let out = refine_scene(&scene, &sfm, &mut Identity, &RefineOptions::default())?;
    println!(
        "| refine_scene, identity network (align + radius + chunks + records + fusion) | {:.3} | {} forwards, {} tokens, {:.1} % covered |",
        t.elapsed().as_secs_f64(),
        out.forwards,
        out.total_tokens,
        100.0 * out.covered.iter().filter(|&&c| c).count() as f64 / out.covered.len() as f64
    );
    Ok(())
}
