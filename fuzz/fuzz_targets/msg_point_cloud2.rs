//! Fuzzes `sensor_msgs/PointCloud2` decoding (kfmap-bag `decode_point_cloud2`), in
//! ROS 2 CDR and ROS 1 serialization: any bytes give a cloud or a named error, never a
//! panic, and no allocation proportional to a length prefix. A decoded cloud must
//! convert (`to_cloud`) with one point per `height * width` and aligned attributes.
//! Run: `cargo +nightly fuzz run msg_point_cloud2`.
#![no_main]

#[path = "common.rs"]
mod common;

use kfmap_bag::Encoding;
use kfmap_bag::msg::decode_point_cloud2;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    for encoding in [Encoding::Cdr, Encoding::Ros1] {
        let Ok(msg) = decode_point_cloud2(data, encoding) else {
            continue;
        };
        let _ = msg.time_field();
        let _ = msg.ring_field();
        let converted = msg.to_cloud();
        if !common::strict() {
            continue;
        }
        let cloud = converted.unwrap_or_else(|e| panic!("a decoded cloud does not convert: {e}"));
        assert_eq!(cloud.len(), msg.len());
        common::assert_attributes_match(&cloud);
        assert_eq!(cloud.time.is_some(), msg.time_field().is_some());
    }
});
