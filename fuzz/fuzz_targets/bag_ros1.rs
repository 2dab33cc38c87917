//! Fuzzes the ROS 1 bag v2.0 reader of kfmap-bag: any bytes give a bag or a named error, never a
//! panic nor an allocation from an unchecked length; every topic is listed, streamed,
//! indexed and each message read back. Seeds: fuzz/corpus/bag_ros1 (written by
//! bag/tests/support/write_bags.py --corpus). Run: `cargo +nightly fuzz run bag_ros1`.
#![no_main]

#[path = "bag_common.rs"]
mod bag_common;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    bag_common::read_whole_bag("bag_ros1", ".bag", data);
});
