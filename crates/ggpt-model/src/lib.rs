//! GGPT network (filled in by the network work).

pub mod plan;
