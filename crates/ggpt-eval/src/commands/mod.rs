//! The subcommands of the `ggpt-eval` binary (binary-only code).

pub mod demo;
