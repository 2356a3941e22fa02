//! GGPT SfM stage (filled in by the SfM work).
