//! Unit tests of the container dispatch.

use super::*;

#[test]
fn a_file_of_no_bag_format_is_refused_by_name() {
    let dir = std::env::temp_dir().join(format!("kfmap-bag-unit-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("x.bag");
    std::fs::write(&file, b"hello, not a bag").unwrap();
    let err = Bag::open(&file).unwrap_err().to_string();
    assert!(err.contains("not a bag"), "{err}");
    std::fs::write(&file, b"#ROSBAG V1.2\n").unwrap();
    let err = Bag::open(&file).unwrap_err().to_string();
    assert!(err.contains("V2.0"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}
