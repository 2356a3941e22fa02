//! Synthetic scene generator (filled in by the synthetic-scene work).
