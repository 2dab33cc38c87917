//! One module per subcommand: its clap arguments and its `run`.

pub mod demo;
pub mod inspect_cloud;
mod report;
pub mod simulate;
