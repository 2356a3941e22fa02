//! Inputs and measurements shared by the bench targets (`forward`, `plan`, `ggpt-train`'s
//! `train`): a deterministic surface-like chunk shaped like the fixture's clouds, the
//! process's peak resident set size, and the printout of a pass's device counts.

use crate::device_stats::DeviceCounts;
use crate::plan::ChunkInput;

/// Fraction of pixels with a DLT point.
pub const GUIDANCE_FRACTION: f32 = 0.3;

/// A wavy surface seen from a camera: `k` pixels on a grid, depth-like variation, 30 % guidance
/// near the dense points, a few points outside the unit cube. Deterministic in `seed`.
pub fn surface_chunk(k: usize, seed: u64) -> ChunkInput {
    let mut s = seed.wrapping_mul(0x9E3779B97F4A7C15) | 1;
    let mut next = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 11) as f32 / (1u64 << 53) as f32
    };
    let w = ((k as f32) * 4.0 / 3.0).sqrt().ceil() as usize;
    let mut c = ChunkInput::default();
    for i in 0..k {
        let (u, v) = (
            (i % w) as f32 / w as f32 * 2.0 - 1.0,
            (i / w) as f32 / w as f32 * 2.0 - 1.0,
        );
        let z = 0.35 * (2.5 * u).sin() * (1.7 * v).cos() + 0.1 * (7.0 * u * v).sin();
        let p = [0.95 * u + 0.002 * next(), 0.95 * v, z];
        c.ff_pts.push(p);
        c.ff_conf.push(1.0 + 5.0 * next());
        let g = next() < GUIDANCE_FRACTION;
        c.geo_msk.push(g);
        c.geo_pts.push(if g {
            [
                p[0] + 0.003 * (next() - 0.5),
                p[1] + 0.003 * (next() - 0.5),
                p[2],
            ]
        } else {
            [0.0; 3]
        });
    }
    c
}

/// Peak resident set size of this process in MiB (Linux `VmHWM`).
pub fn peak_rss_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse::<f64>().ok())
        })
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

/// Resets the process's peak RSS (`VmHWM`) to the current RSS (Linux: writes `5` to
/// `/proc/self/clear_refs`); returns false where that is not possible.
pub fn reset_peak_rss() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

/// Dense pixels `k` of a chunk with `tokens` network tokens (dense + DLT) at
/// [`GUIDANCE_FRACTION`] guidance.
pub fn pixels_for_tokens(tokens: usize) -> usize {
    ((tokens as f32) / (1.0 + GUIDANCE_FRACTION)).round() as usize
}

/// Prints what [`crate::device_stats::observe`] counted: one `counts:` line to stdout (launches,
/// readbacks, distinct kernels) and the 40 most launched (or, with `timed`, the 40 slowest)
/// kernels to stderr.
pub fn print_device_counts(c: &DeviceCounts, timed: bool) {
    let launches = if c.launches_observed {
        c.launches.to_string()
    } else {
        "not observed (no CubeCL backend compiled)".to_string()
    };
    println!(
        "counts: {launches} kernel launches, {} host readbacks, {} distinct kernels",
        c.readbacks,
        c.kernels.len()
    );
    let mut kernels = c.kernels.clone();
    if timed {
        kernels.sort_by(|a, b| b.seconds.total_cmp(&a.seconds));
    }
    for k in kernels.iter().take(40) {
        if timed {
            eprintln!(
                "kernel {:>6} x {:>9.3} s  {}",
                k.launches, k.seconds, k.name
            );
        } else {
            eprintln!("kernel {:>6} x  {}", k.launches, k.name);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn surface_chunk_is_deterministic_with_about_thirty_percent_guidance() {
        let a = surface_chunk(2000, 7);
        assert_eq!(a.ff_pts, surface_chunk(2000, 7).ff_pts);
        assert_eq!(a.ff_pts.len(), 2000);
        let g = a.geo_msk.iter().filter(|&&m| m).count() as f32 / 2000.0;
        assert!(
            (g - GUIDANCE_FRACTION).abs() < 0.05,
            "guidance fraction {g}"
        );
        assert!(peak_rss_mib() > 0.0);
    }
}
