//! Fuzzes `sensor_msgs/Imu` decoding (kfmap-bag `decode_imu`), in ROS 2 CDR and ROS 1
//! serialization: any bytes give a message or a named error, never a panic, and no
//! allocation proportional to the frame_id length prefix.
//! Run: `cargo +nightly fuzz run msg_imu`.
#![no_main]

use kfmap_bag::Encoding;
use kfmap_bag::msg::decode_imu;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    for encoding in [Encoding::Cdr, Encoding::Ros1] {
        if let Ok(msg) = decode_imu(data, encoding) {
            let _ = msg.sample();
        }
    }
});
