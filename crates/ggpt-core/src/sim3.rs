//! Sim(3) estimation (`pipeline.md` §3.1). Filled in by the evaluation work.
