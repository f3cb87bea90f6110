//! The CLI verbs that work on single files rather than graphs: each module owns one group of
//! verbs (its clap arguments and its `run`), so main.rs only dispatches.

pub mod mesh;
pub mod metrology;
pub mod separate;
