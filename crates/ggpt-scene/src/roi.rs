//! Region-of-interest restrictions of the official evaluation (`pipeline.md` §10.5, evaluation
//! option): they feed the mask `F` of the radius (§4) and the chunk sampler (§5).
//!
//! * [`RegionOfInterest::Mask`] (4D-DRESS: the GT human mask): dense points enter chunks only on
//!   `F`, and the DLT mask becomes `M_s ∧ F`.
//! * [`RegionOfInterest::Box`] (Tanks and Temples: a GT-derived box in the SfM frame, see
//!   [`gt_roi_box`]): `F = (aligned X_d in the box)` and `M_s ∧ (X_s in the box)`.
//!
//! Box tests are closed and in `f32`, as in the official loader. Applied after the Sim(3)
//! pre-alignment (which uses the unrestricted `M_s`).

use crate::error::{SceneError, check_len};

/// Fraction of the GT radius added around the GT extent (`pipeline.md` §10.5: ±10 %).
pub const ROI_BOX_MARGIN: f64 = 0.1;

/// An evaluation region of interest.
#[derive(Debug, Clone, PartialEq)]
pub enum RegionOfInterest {
    /// Per-pixel mask `F` (`[N, h, w]`), used for dense and DLT points alike.
    Mask(Vec<bool>),
    /// Axis-aligned box in the SfM frame (scene units), tested separately on the aligned dense
    /// points and on the DLT points.
    Box {
        /// Lower corner.
        min: [f32; 3],
        /// Upper corner.
        max: [f32; 3],
    },
}

/// Masks derived from a region of interest.
#[derive(Debug, Clone, PartialEq)]
pub struct RoiMasks {
    /// `F`: dense points allowed in chunks (`[P]`).
    pub dense: Vec<bool>,
    /// The restricted DLT mask (`[P]`).
    pub dlt_mask: Vec<bool>,
}

fn in_box(x: &[f32], lo: &[f32; 3], hi: &[f32; 3]) -> bool {
    x.len() == 3 && (0..3).all(|a| lo[a] <= x[a] && x[a] <= hi[a])
}

impl RegionOfInterest {
    /// `F` and `M_s ∧ ...` for aligned dense points `ff_aligned` (`[P, 3]`, SfM frame), DLT
    /// points `dlt_points` (`[P, 3]`) and mask `dlt_mask` (`[P]`).
    pub fn masks(
        &self,
        ff_aligned: &[f32],
        dlt_points: &[f32],
        dlt_mask: &[bool],
    ) -> Result<RoiMasks, SceneError> {
        let p = dlt_mask.len();
        check_len("roi: aligned dense points", ff_aligned.len(), 3 * p)?;
        check_len("roi: DLT points", dlt_points.len(), 3 * p)?;
        match self {
            RegionOfInterest::Mask(f) => {
                check_len("roi: region-of-interest mask", f.len(), p)?;
                Ok(RoiMasks {
                    dense: f.clone(),
                    dlt_mask: dlt_mask.iter().zip(f).map(|(&m, &k)| m && k).collect(),
                })
            }
            RegionOfInterest::Box { min, max } => Ok(RoiMasks {
                dense: ff_aligned
                    .chunks_exact(3)
                    .map(|x| in_box(x, min, max))
                    .collect(),
                dlt_mask: dlt_points
                    .chunks_exact(3)
                    .zip(dlt_mask)
                    .map(|(x, &m)| m && in_box(x, min, max))
                    .collect(),
            }),
        }
    }
}

/// The Tanks-and-Temples box of the official loader from the **aligned** GT points (`[P, 3]`,
/// SfM frame) and GT mask: `ρ = 3 · mean_axis std(GT points)` (unbiased, f64), box =
/// `[min - 0.1 ρ, max + 0.1 ρ]` per axis (f32 arithmetic as the official torch code).
pub fn gt_roi_box(gt_aligned: &[f32], gt_mask: &[bool]) -> Result<RegionOfInterest, SceneError> {
    check_len(
        "roi: aligned GT points",
        gt_aligned.len(),
        3 * gt_mask.len(),
    )?;
    let dims = ggpt_core::Dims {
        n: 1,
        h: 1,
        w: gt_mask.len(),
    };
    let rho = crate::radius::scene_radius(
        gt_aligned,
        dims,
        crate::radius::RadiusRule::Pooled,
        Some(gt_mask),
    )?
    .radius;
    let margin = (rho * ROI_BOX_MARGIN) as f32;
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for (x, _) in gt_aligned.chunks_exact(3).zip(gt_mask).filter(|(_, m)| **m) {
        for a in 0..3 {
            lo[a] = lo[a].min(x[a]);
            hi[a] = hi[a].max(x[a]);
        }
    }
    Ok(RegionOfInterest::Box {
        min: lo.map(|v| v - margin),
        max: hi.map(|v| v + margin),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_and_mask_semantics() {
        // 4 pixels; dense point 1 and DLT point 2 outside the box [0, 1]^3.
        let ff = [0.5, 0.5, 0.5, 2.0, 0.5, 0.5, 0.5, 0.5, 0.5, 1.0, 1.0, 1.0];
        let dlt = [0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 5.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let msk = [true, true, true, false];
        let b = RegionOfInterest::Box {
            min: [0.0; 3],
            max: [1.0; 3],
        };
        let m = b.masks(&ff, &dlt, &msk).unwrap();
        assert_eq!(m.dense, vec![true, false, true, true]); // closed box: (1,1,1) inside
        assert_eq!(m.dlt_mask, vec![true, true, false, false]);
        let f = RegionOfInterest::Mask(vec![true, false, true, true]);
        let m = f.masks(&ff, &dlt, &msk).unwrap();
        assert_eq!(m.dlt_mask, vec![true, false, true, false]);
        assert!(
            RegionOfInterest::Mask(vec![true])
                .masks(&ff, &dlt, &msk)
                .is_err()
        );
    }

    #[test]
    fn gt_box_margin() {
        // Valid GT x values 0 and 2 (y = z = 0): std_x = sqrt(2), std_y = std_z = 0 -> ρ = sqrt(2).
        let gt = [0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 100.0, 100.0, 100.0];
        let msk = [true, true, false];
        match gt_roi_box(&gt, &msk).unwrap() {
            RegionOfInterest::Box { min, max } => {
                let m = (2f64.sqrt() * 0.1) as f32;
                assert_eq!(min, [-m, -m, -m]);
                assert_eq!(max, [2.0 + m, m, m]);
            }
            other => panic!("expected a box, got {other:?}"),
        }
    }
}
