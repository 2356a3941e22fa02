//! The learning-rate schedule (constant, or linear warm-up + cosine decay).

use super::{LrSchedule, TrainOptions};

/// Learning rate of step `step` (0-based).
pub fn learning_rate(o: &TrainOptions, step: u64) -> f64 {
    match o.lr_schedule {
        LrSchedule::Constant => o.lr,
        LrSchedule::Cosine => {
            if step < o.warmup_steps {
                o.lr * (step + 1) as f64 / o.warmup_steps as f64
            } else {
                let span = o.steps.saturating_sub(o.warmup_steps).max(1) as f64;
                let t = (step - o.warmup_steps) as f64 / span;
                0.5 * o.lr * (1.0 + (std::f64::consts::PI * t.min(1.0)).cos())
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::trainer::test_util::options;

    #[test]
    fn cosine_schedule_warms_up_and_decays_to_zero() {
        let o = TrainOptions {
            steps: 10,
            warmup_steps: 2,
            lr: 1.0,
            ..options(10)
        };
        assert!((learning_rate(&o, 0) - 0.5).abs() < 1e-12);
        assert!((learning_rate(&o, 1) - 1.0).abs() < 1e-12);
        assert!((learning_rate(&o, 2) - 1.0).abs() < 1e-12);
        assert!(learning_rate(&o, 6) < 1.0 && learning_rate(&o, 6) > 0.0);
        assert!(learning_rate(&o, 10).abs() < 1e-12);
        let c = TrainOptions {
            lr_schedule: LrSchedule::Constant,
            ..o
        };
        assert_eq!(learning_rate(&c, 7), 1.0);
    }
}
