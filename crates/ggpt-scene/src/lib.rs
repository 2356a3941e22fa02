//! Scene pipeline (filled in by the pipeline work).
