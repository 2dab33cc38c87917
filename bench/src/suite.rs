//! `kfmap bench` with no subcommand: the system benchmarks in one table. Each row names
//! its data and threads; the anchor's figure stands beside it where one was measured on
//! the same data, with the script that measured it.

use std::path::Path;

use super::automotive;
use super::bags;
use super::cov2cov;
use super::ipc;
use super::kdtree;
use super::kernels;
use super::load;
use super::localization;
use super::pose_graph;
use super::registration;
use super::remote;
use super::table::Table;
use crate::data_dir::shared_data_dir;

/// Runs every benchmark and prints the table (or JSON rows).
pub(super) fn run(quick: bool, json_out: bool, dir: &Path) -> anyhow::Result<()> {
    let mut table = Table::new(quick, json_out)?;
    let data = shared_data_dir();
    kernels::measure(&mut table, data.as_deref())?;
    kdtree::measure(&mut table, data.as_deref())?;
    cov2cov::measure(&mut table, data.as_deref())?;
    registration::measure(&mut table, data.as_deref())?;
    pose_graph::measure(&mut table, data.as_deref())?;
    load::table_rows(&mut table, dir)?;
    ipc::table_rows(&mut table, dir)?;
    remote::table_rows(&mut table, dir)?;
    localization::measure(&mut table, data.as_deref(), dir)?;
    bags::measure(&mut table, data.as_deref(), dir)?;
    automotive::measure(&mut table, data.as_deref(), dir)?;
    table.finish();
    if json_out {
        println!("{}", serde_json::to_string_pretty(&table.json())?);
    } else {
        print!("{}", table.text());
    }
    Ok(())
}
