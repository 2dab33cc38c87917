//! What every bag fuzz target does (included with `#[path]`, not a target itself):
//! write the input to a file, open it as a bag, then list, stream, index and read every
//! topic. Any input gives a bag or a named error, never a panic.
#![allow(dead_code)]

use kfmap_bag::Bag;

#[path = "common.rs"]
mod common;

/// Writes `data` to this process's temporary `<tag><ext>` file and reads it whole.
pub fn read_whole_bag(tag: &str, ext: &str, data: &[u8]) {
    let path = common::temp_path(tag, ext);
    if std::fs::write(&path, data).is_err() {
        return;
    }
    let Ok(bag) = Bag::open(&path) else {
        return;
    };
    for topic in bag.topics() {
        let _ = bag.topic(&topic.name);
        let _ = bag.point_cloud_topic(&topic.name);
        if let Ok(messages) = bag.messages(topic) {
            for message in messages {
                if message.is_err() {
                    break;
                }
            }
        }
        if let Ok(index) = bag.index(topic) {
            // Reversed: random access, not only the sequential cache hits.
            for at in index.iter().rev() {
                let _ = bag.read(at);
            }
        }
    }
}
