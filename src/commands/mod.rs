//! One module per subcommand: its clap arguments and its `run`.

pub mod bake;
pub mod bench;
pub mod demo;
pub mod gravity;
pub mod inspect;
pub mod inspect_cloud;
pub mod optimize_graph;
pub mod register;
mod report;
pub mod simulate;
