//! One module per subcommand: its clap arguments and its `run`.

pub mod bake;
mod cloud_summary;
mod connect_arg;
pub mod demo;
pub mod gateway;
pub mod gravity;
pub mod inspect;
pub mod inspect_bag;
pub mod inspect_cloud;
pub mod localize;
pub mod optimize_graph;
pub mod plot;
mod pose_arg;
pub mod query;
pub mod register;
pub mod relocalize;
mod report;
mod sensor_arg;
pub mod serve;
pub mod simulate;
mod source_arg;
pub mod status;
