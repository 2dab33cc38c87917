//! Fuzzes the mcap reader of kfmap-bag: any bytes give a bag or a named error, never a
//! panic nor an allocation from an unchecked length; every topic is listed, streamed,
//! indexed and each message read back. Seeds: fuzz/corpus/bag_mcap (written by
//! bag/tests/support/write_bags.py --corpus). Run: `cargo +nightly fuzz run bag_mcap`.
#![no_main]

#[path = "bag_common.rs"]
mod bag_common;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    bag_common::read_whole_bag("bag_mcap", ".mcap", data);
});
