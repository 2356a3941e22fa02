//! `ggpt-train grads`: one training step made visible (loss, outputs, every gradient,
//! BatchNorm statistics, optional Adam step), for checks against a reference.

use anyhow::{Context, Result, bail};
use ggpt_cli::Bar;
use ggpt_model::Ggpt;

use crate::cli::GradsArgs;

/// Runs `grads`.
pub fn run(a: &GradsArgs) -> Result<()> {
    if let Some(lr) = a.adam_step_lr
        && !(lr.is_finite() && lr > 0.0)
    {
        bail!("--adam-step-lr {lr}: must be a finite number > 0");
    }
    let cfg = super::model_config(&a.model, None)?;
    let weights = a.model.require_weights()?;
    let plain = ggpt_model::device::device_from_name(&a.device.device.to_string())?;
    let device = plain.clone().autodiff();
    let fresh = ggpt_model::weights::load_checkpoint(Ggpt::new(&cfg, &plain), weights)
        .with_context(|| format!("loading weights {}", weights.display()))?;
    let cases = ggpt_train::grads::read_cases(&a.input)
        .with_context(|| format!("reading {}", a.input.display()))?;
    let bar = Bar::new("cases", cases.len() as u64);
    let mut results = Vec::with_capacity(cases.len());
    for (k, case) in cases.iter().enumerate() {
        let lr = if k == 0 { a.adam_step_lr } else { None };
        let r = ggpt_train::grads::run_case(&fresh, &cfg, case, &device, lr)
            .with_context(|| format!("case {k}"))?;
        tracing::info!(
            "case {k}: {} tokens, L {:.6} (L_conf {:.6}, L_id {:.6}), {} gradients",
            case.num_tokens(),
            r.loss[0],
            r.loss[1],
            r.loss[2],
            r.grads.len()
        );
        results.push(r);
        bar.inc(1);
    }
    bar.finish();
    ggpt_train::grads::write_results(&a.output, &results)
        .with_context(|| format!("writing {}", a.output.display()))?;
    println!("{}", a.output.display());
    Ok(())
}
