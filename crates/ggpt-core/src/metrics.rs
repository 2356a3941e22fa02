//! Evaluation metrics (`pipeline.md` §10). Filled in by the evaluation work.
