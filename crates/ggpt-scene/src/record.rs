//! Per-chunk records normalised to the chunk frame (`pipeline.md` §6).
//!
//! For an accepted chunk `(Mk, c, r)` the pixel list is `{p : Mk[p]}` in pixel order and
//!
//! * `ff_pts  = (X_d[p] - c) / f32(r)` (aligned dense points, SfM frame -> chunk frame),
//! * `ff_conf = c_d[p]` (raw confidence),
//! * `geo_pts = (X_s[p] - c) / f32(r)` (`X_s[p] = 0` where `M_s[p]` is false -> `-c / r`),
//! * `geo_msk = M_s[p]`, `rgb = images_ff[p]`,
//! * training / evaluation: `gt_pts = (X_gt[p] - c) / f32(r)` (aligned GT, 0 where invalid), `gt_msk`.
//!
//! All in `f32` with `r` rounded to `f32` once, which reproduces the official records bit-exactly.

use ggpt_core::chunk_input::{AsChunkView, ChunkInput, ChunkView};

use crate::chunker::Chunk;
use crate::error::{SceneError, check_len};

/// Per-pixel scene arrays a record is cut from (flat, pixel order).
#[derive(Debug, Clone, Copy)]
pub struct RecordSources<'a> {
    /// Aligned dense points `X_d`, `[P, 3]`, SfM frame.
    pub ff_points: &'a [f32],
    /// Raw feed-forward confidence `c_d`, `[P]`.
    pub ff_conf: &'a [f32],
    /// DLT points `X_s`, `[P, 3]`, SfM frame.
    pub dlt_points: &'a [f32],
    /// `M_s`, `[P]`.
    pub dlt_mask: &'a [bool],
    /// `images_ff`, `[P, 3]` in `[0, 1]`.
    pub images: &'a [f32],
    /// Aligned GT points (`[P, 3]`, SfM frame, 0 where invalid) and GT mask (`[P]`), when known.
    pub gt: Option<(&'a [f32], &'a [bool])>,
}

impl RecordSources<'_> {
    /// Checks the array lengths against the pixel count `P = dlt_mask.len()`.
    pub fn validate(&self) -> Result<usize, SceneError> {
        let p = self.dlt_mask.len();
        check_len("record: ff_points", self.ff_points.len(), 3 * p)?;
        check_len("record: ff_conf", self.ff_conf.len(), p)?;
        check_len("record: dlt_points", self.dlt_points.len(), 3 * p)?;
        check_len("record: images", self.images.len(), 3 * p)?;
        if let Some((g, m)) = self.gt {
            check_len("record: gt points", g.len(), 3 * p)?;
            check_len("record: gt mask", m.len(), p)?;
        }
        Ok(p)
    }
}

/// Normalised GT of a chunk (training / evaluation only).
#[derive(Debug, Clone, PartialEq)]
pub struct GtRecord {
    /// `(X_gt[p] - c) / r`, chunk frame.
    pub pts: Vec<[f32; 3]>,
    /// GT valid.
    pub msk: Vec<bool>,
}

/// One chunk ready for the network: its network input (`network.md` §2) plus book-keeping.
///
/// The per-pixel network arrays live in [`ChunkRecord::input`] (the one [`ChunkInput`]
/// definition shared with the planner and the training chunks); the record dereferences to it,
/// so `record.ff_pts` reads as before, and a refiner hands `&[ChunkRecord]` to the planner
/// (`AsChunkView`) without copying them.
#[derive(Debug, Clone, PartialEq)]
pub struct ChunkRecord {
    /// Chunk index in sampling order.
    pub index: usize,
    /// Scene pixels of the chunk, ascending pixel order (`K` entries).
    pub pixels: Vec<u32>,
    /// Centre `c` (SfM frame).
    pub center: [f32; 3],
    /// Half-size `r` (scene units).
    pub radius: f64,
    /// Network input, chunk frame, `[K]` each: normalised dense points `ff_pts`, raw confidence
    /// `ff_conf`, normalised DLT points `geo_pts` (meaningless where `geo_msk` is false) and the
    /// DLT mask `geo_msk`.
    pub input: ChunkInput,
    /// Colours in `[0, 1]`, `[K]` (export only).
    pub rgb: Vec<[f32; 3]>,
    /// Normalised GT, when known.
    pub gt: Option<GtRecord>,
}

impl std::ops::Deref for ChunkRecord {
    type Target = ChunkInput;
    fn deref(&self) -> &ChunkInput {
        &self.input
    }
}

impl AsChunkView for ChunkRecord {
    fn chunk_view(&self) -> ChunkView<'_> {
        self.input.view()
    }
}

impl ChunkRecord {
    /// Builds the record of `chunk` from the scene arrays (see the module doc for the formulas).
    pub fn build(chunk: &Chunk, src: &RecordSources<'_>) -> Result<ChunkRecord, SceneError> {
        let p_total = src.validate()?;
        let r32 = chunk.radius as f32;
        let c = chunk.center;
        let k = chunk.pixels.len();
        let mut rec = ChunkRecord {
            index: chunk.index,
            pixels: chunk.pixels.clone(),
            center: c,
            radius: chunk.radius,
            input: ChunkInput {
                ff_pts: Vec::with_capacity(k),
                ff_conf: Vec::with_capacity(k),
                geo_pts: Vec::with_capacity(k),
                geo_msk: Vec::with_capacity(k),
            },
            rgb: Vec::with_capacity(k),
            gt: None,
        };
        let mut gt = src.gt.map(|_| GtRecord {
            pts: Vec::with_capacity(k),
            msk: Vec::with_capacity(k),
        });
        for &p32 in &chunk.pixels {
            let p = p32 as usize;
            if p >= p_total {
                return Err(SceneError::Invalid(format!(
                    "record: chunk {} pixel {p} out of range ({p_total} pixels)",
                    chunk.index
                )));
            }
            let input = &mut rec.input;
            input.ff_pts.push(normalise(vec3(src.ff_points, p), c, r32));
            input.ff_conf.push(src.ff_conf[p]);
            input
                .geo_pts
                .push(normalise(vec3(src.dlt_points, p), c, r32));
            input.geo_msk.push(src.dlt_mask[p]);
            rec.rgb.push(vec3(src.images, p));
            if let (Some(g), Some((gp, gm))) = (gt.as_mut(), src.gt) {
                g.pts.push(normalise(vec3(gp, p), c, r32));
                g.msk.push(gm[p]);
            }
        }
        rec.gt = gt;
        Ok(rec)
    }

    /// Number of pixels (dense tokens) `K`.
    pub fn len(&self) -> usize {
        self.pixels.len()
    }
    /// True for an empty chunk (never produced by the sampler).
    pub fn is_empty(&self) -> bool {
        self.pixels.is_empty()
    }
    /// Network tokens of the chunk: `K` dense tokens plus one DLT token per DLT pixel.
    pub fn num_tokens(&self) -> usize {
        self.len() + self.geo_msk.iter().filter(|&&m| m).count()
    }
}

/// `(x - c) / r32` per axis in `f32`.
#[inline]
pub fn normalise(x: [f32; 3], c: [f32; 3], r32: f32) -> [f32; 3] {
    [
        (x[0] - c[0]) / r32,
        (x[1] - c[1]) / r32,
        (x[2] - c[2]) / r32,
    ]
}

/// Inverse of [`normalise`]: `x' · f32(r) + c` per axis in `f32` (official `pts * radius + center`),
/// chunk frame -> SfM frame.
#[inline]
pub fn unnormalise(x: [f32; 3], c: [f32; 3], r: f64) -> [f32; 3] {
    let r32 = r as f32;
    [x[0] * r32 + c[0], x[1] * r32 + c[1], x[2] * r32 + c[2]]
}

/// Point `p` of a flat `[P, 3]` array (the caller has checked the length).
#[inline]
fn vec3(a: &[f32], p: usize) -> [f32; 3] {
    [a[3 * p], a[3 * p + 1], a[3 * p + 2]]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::chunker::tests_support::replay_fixture_chunks;
    use crate::prealign::apply_matrix_f32;
    use crate::test_util::Fixture;
    use nalgebra::Matrix3x4;

    #[test]
    fn fixture_records_bit_exact() {
        let steps = Fixture::sfm_steps();
        let inputs = Fixture::sfm_inputs();
        let reference = Fixture::official_reference();
        let aligned = steps.f32("sim3/ff_aligned");
        let dlt = steps.f32("scatter/points");
        let msk = steps.bool("scatter/point_masks");
        let conf = inputs.f32("ff/points_conf");
        let images = inputs.f32("ff/images_ff");
        // Scene GT: gt.bin points aligned with the official GT Sim(3), zeroed where invalid.
        let gt_mat = steps.f32("sim3/gt_sim3d_mat");
        let gt_msk = reference.bool("gt/point_masks");
        let mut gt = apply_matrix_f32(
            &Matrix3x4::from_row_slice(&gt_mat),
            &reference.f32("gt/points"),
        );
        for (p, &m) in gt_msk.iter().enumerate() {
            if !m {
                gt[3 * p..3 * p + 3].fill(0.0);
            }
        }
        let chunks = replay_fixture_chunks(&steps, &aligned, &dlt, &msk);
        let src = RecordSources {
            ff_points: &aligned,
            ff_conf: &conf,
            dlt_points: &dlt,
            dlt_mask: &msk,
            images: &images,
            gt: Some((&gt, &gt_msk)),
        };
        let offsets = steps.i64("chunks/offsets");
        assert_eq!(offsets.len(), 4);
        let want_ff = steps.f32("chunks/ff_pts");
        let want_geo = steps.f32("chunks/geo_pts");
        let want_gt = steps.f32("chunks/gt_pts");
        let want_conf = steps.f32("chunks/ff_pts_conf");
        let want_gmsk = steps.bool("chunks/geo_msks");
        let want_gtmsk = steps.bool("chunks/gt_msks");
        let want_rgb = steps.f32("chunks/rgbs");
        for k in 0..3 {
            let rec = ChunkRecord::build(&chunks[k], &src).unwrap();
            let (a, b) = (offsets[k] as usize, offsets[k + 1] as usize);
            assert_eq!(rec.len(), b - a, "chunk {k} size");
            let bits3 =
                |v: &[[f32; 3]]| v.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(
                bits3(&rec.ff_pts),
                bits(&want_ff[3 * a..3 * b]),
                "chunk {k} ff_pts"
            );
            assert_eq!(
                bits3(&rec.geo_pts),
                bits(&want_geo[3 * a..3 * b]),
                "chunk {k} geo_pts"
            );
            let g = rec.gt.as_ref().unwrap();
            assert_eq!(
                bits3(&g.pts),
                bits(&want_gt[3 * a..3 * b]),
                "chunk {k} gt_pts"
            );
            assert_eq!(g.msk, want_gtmsk[a..b], "chunk {k} gt_msks");
            assert_eq!(
                bits(&rec.ff_conf),
                bits(&want_conf[a..b]),
                "chunk {k} ff_pts_conf"
            );
            assert_eq!(rec.geo_msk, want_gmsk[a..b], "chunk {k} geo_msks");
            assert_eq!(
                bits3(&rec.rgb),
                bits(&want_rgb[3 * a..3 * b]),
                "chunk {k} rgbs"
            );
            // The centre pixel is a DLT token at the origin.
            let ci = rec
                .pixels
                .iter()
                .position(|&p| p == chunks[k].center_pixel)
                .unwrap();
            assert_eq!(rec.geo_pts[ci], [0.0; 3]);
            assert!(rec.geo_msk[ci]);
        }
    }

    #[test]
    fn normalise_roundtrip_and_tokens() {
        let chunk = Chunk {
            index: 0,
            pixels: vec![0, 2],
            center: [1.0, 2.0, 3.0],
            center_pixel: 0,
            radius: 0.5,
            n_dlt: 1,
        };
        let ff = [1.0, 2.0, 3.0, 9.0, 9.0, 9.0, 1.5, 1.0, 3.25];
        let dlt = [1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let msk = [true, false, false];
        let conf = [1.0, 2.0, 3.0];
        let img = [0.1f32; 9];
        let src = RecordSources {
            ff_points: &ff,
            ff_conf: &conf,
            dlt_points: &dlt,
            dlt_mask: &msk,
            images: &img,
            gt: None,
        };
        let r = ChunkRecord::build(&chunk, &src).unwrap();
        assert_eq!(r.ff_pts, vec![[0.0, 0.0, 0.0], [1.0, -2.0, 0.5]]);
        assert_eq!(r.geo_pts[1], [-2.0, -4.0, -6.0]); // zeros -> -c/r
        assert_eq!(r.ff_conf, vec![1.0, 3.0]);
        assert_eq!(r.num_tokens(), 3);
        assert!(r.gt.is_none());
        assert_eq!(
            unnormalise(r.ff_pts[1], chunk.center, chunk.radius),
            [1.5, 1.0, 3.25]
        );
        let bad = Chunk {
            pixels: vec![7],
            ..chunk
        };
        assert!(ChunkRecord::build(&bad, &src).is_err());
    }
}
