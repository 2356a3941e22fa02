//! `ggpt-train plot`: the training-curve PNG of a `metrics.jsonl`.

use anyhow::{Context, Result};
use ggpt_train::plot::{FigureOptions, read_metrics, write_figure};

use crate::cli::PlotArgs;

/// Runs `plot`.
pub fn run(a: &PlotArgs) -> Result<()> {
    let m = read_metrics(&a.metrics)?;
    // the run directory's name (metrics.jsonl lives in the run directory)
    let run_label = a
        .metrics
        .parent()
        .and_then(|d| d.file_name())
        .map(|n| n.to_string_lossy().into_owned());
    let o = FigureOptions {
        smooth: a.smooth,
        width: a.width,
        panel_height: a.panel_height,
        run_label,
    };
    let s = write_figure(&a.out, &m, &o)
        .with_context(|| format!("plotting {}", a.metrics.display()))?;
    println!(
        "{}: {}x{} PNG; top: training loss (light red: per step, bold red: moving average over {} steps), steps {:.0}..{:.0}, loss {:.4}..{:.4}, last average {:.4} at step {:.0}",
        a.out.display(),
        s.width,
        s.height,
        a.smooth.max(1),
        s.steps.0,
        s.steps.1,
        s.loss.0,
        s.loss.1,
        s.last_loss_avg.1,
        s.last_loss_avg.0
    );
    match (s.auc, s.last_val) {
        (Some(r), Some(v)) => println!(
            "  bottom: held-out chunk AUC (%) over {} val lines, AUC@5 input (grey) vs refined (blue), AUC@10 dashed/lighter; AUC {:.1}..{:.1}; last (step {:.0}): AUC@5 {:.1} -> {:.1}, AUC@10 {:.1} -> {:.1}",
            m.val.len(),
            r.0,
            r.1,
            v.step,
            v.input_auc5,
            v.refined_auc5,
            v.input_auc10,
            v.refined_auc10
        ),
        _ => println!("  no validation line (kind \"val\") yet: loss panel only"),
    }
    Ok(())
}
