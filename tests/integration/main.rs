//! The integration tests of this crate, as one binary (one link instead of one per
//! file: each release test binary is a thin-LTO link of every dependency).

mod bags;
mod cli;
mod common;
mod demo;
mod health;
mod hostile;
mod localize_real;
mod localize_sim;
mod plot;
mod relocalize;
mod remote;
mod ros2;
mod serve;
