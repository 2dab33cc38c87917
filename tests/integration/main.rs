//! The integration tests of this crate, as one binary (one link instead of one per
//! file: each release test binary is a thin-LTO link of every dependency).

// libtest starts tests in name order, two at a time on two cores. The ROS 2 test waits
// on sensor rates for most of its minute and a half: its module sorts first, so that the
// waiting overlaps the CPU-bound tests instead of idling a core at the end of the run
// (measured: the last 70 s of the run at 12-70 % CPU when it sorted last).
#[path = "ros2.rs"]
mod a_ros2;
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
mod serve;
