//! Bags as datasets: the containers robots record into (MCAP, rosbag2 sqlite3, ROS 1
//! `.bag` v2.0) and the messages kfmap reads from them (`sensor_msgs/PointCloud2`,
//! `sensor_msgs/Imu`, and a localizer's recorded pose and diagnostics, in ROS 2 CDR or
//! ROS 1 serialization).
//!
//! A bag is never read whole: [`Bag::messages`] streams one topic in log-time order with
//! memory bounded by one chunk, and [`Bag::index`] + [`Bag::read`] fetch single messages
//! for the passes of a bake that revisit scans.

mod chunked;
mod error;
mod mcap_reader;
pub mod msg;
mod raw;
mod ros1;
mod sqlite;

use std::fmt;
use std::path::{Path, PathBuf};

pub use error::BagError;

/// How a bag stores its messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Storage {
    /// An MCAP file (`.mcap`, or a rosbag2 folder whose `metadata.yaml` says `mcap`).
    Mcap,
    /// A rosbag2 SQLite database (`.db3`, or its folder with `metadata.yaml`).
    Sqlite3,
    /// A ROS 1 bag, format version 2.0.
    Ros1,
}

impl fmt::Display for Storage {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Storage::Mcap => "mcap",
            Storage::Sqlite3 => "rosbag2-sqlite3",
            Storage::Ros1 => "ros1-bag-v2.0",
        })
    }
}

/// How a topic's messages are serialized.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Encoding {
    /// ROS 2: OMG CDR with its 4-byte encapsulation header (either byte order).
    Cdr,
    /// ROS 1: little-endian, no alignment, `u32` length prefixes.
    Ros1,
}

/// One topic of a bag.
#[derive(Debug, Clone, PartialEq)]
pub struct Topic {
    /// Its name, e.g. `/ouster/points`.
    pub name: String,
    /// Its message type as ROS writes it, e.g. `sensor_msgs/msg/PointCloud2` (ROS 2) or
    /// `sensor_msgs/PointCloud2` (ROS 1).
    pub msg_type: String,
    /// How its messages are serialized.
    pub encoding: Encoding,
    /// Messages on it.
    pub count: u64,
    /// Log time of its first and last message, nanoseconds since the epoch.
    pub first_ns: Option<u64>,
    /// See `first_ns`.
    pub last_ns: Option<u64>,
}

impl Topic {
    /// The message type without the ROS 2 `/msg/` infix: `sensor_msgs/PointCloud2`.
    pub fn short_type(&self) -> String {
        self.msg_type.replace("/msg/", "/")
    }

    /// True for `sensor_msgs/PointCloud2` in either spelling.
    pub fn is_point_cloud(&self) -> bool {
        self.short_type() == "sensor_msgs/PointCloud2"
    }

    /// True for `sensor_msgs/Imu` in either spelling.
    pub fn is_imu(&self) -> bool {
        self.short_type() == "sensor_msgs/Imu"
    }

    /// True for `geometry_msgs/PoseWithCovarianceStamped` in either spelling.
    pub fn is_pose_with_covariance(&self) -> bool {
        self.short_type() == "geometry_msgs/PoseWithCovarianceStamped"
    }

    /// True for `diagnostic_msgs/DiagnosticArray` in either spelling.
    pub fn is_diagnostics(&self) -> bool {
        self.short_type() == "diagnostic_msgs/DiagnosticArray"
    }
}

/// One message's bytes and the time the recorder logged it.
#[derive(Debug, Clone, PartialEq)]
pub struct Message {
    /// Log (receive) time, nanoseconds since the epoch.
    pub log_time_ns: u64,
    /// The serialized message (CDR with its encapsulation header, or ROS 1).
    pub data: Vec<u8>,
}

/// Where one message lies in its bag, for [`Bag::read`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MessageRef {
    /// Log time, nanoseconds since the epoch.
    pub log_time_ns: u64,
    /// Container-specific: the chunk's file offset (MCAP, ROS 1) or the row id (sqlite3).
    pub(crate) locator: u64,
    /// Container-specific: the record's offset inside the decompressed chunk.
    pub(crate) offset: u64,
}

/// What every container reader offers.
pub(crate) trait Container: Send + Sync {
    /// Every topic, sorted by name.
    fn topics(&self) -> &[Topic];
    /// Every message of `topic`, in log-time order, streamed.
    fn messages<'a>(
        &'a self,
        topic: &Topic,
    ) -> Result<Box<dyn Iterator<Item = Result<Message, BagError>> + Send + 'a>, BagError>;
    /// Where every message of `topic` lies, in log-time order.
    fn index(&self, topic: &Topic) -> Result<Vec<MessageRef>, BagError>;
    /// One message of `index`.
    fn read(&self, at: &MessageRef) -> Result<Message, BagError>;
}

/// An open bag of any supported storage.
pub struct Bag {
    path: PathBuf,
    storage: Storage,
    inner: Box<dyn Container>,
}

impl fmt::Debug for Bag {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Bag")
            .field("path", &self.path)
            .field("storage", &self.storage)
            .finish_non_exhaustive()
    }
}

/// ROS 1 bag files start with this line.
const ROS1_MAGIC: &[u8] = b"#ROSBAG V2.0\n";
/// MCAP files start (and end) with these bytes.
const MCAP_MAGIC: &[u8] = b"\x89MCAP0\r\n";
/// SQLite databases start with this.
const SQLITE_MAGIC: &[u8] = b"SQLite format 3\0";

impl Bag {
    /// Opens `path`: an `.mcap`, `.db3` or ROS 1 `.bag` file (told by its first bytes),
    /// or a rosbag2 folder (its `metadata.yaml` names the storage and the files; a
    /// split bag of several files is refused with a clear error).
    pub fn open(path: &Path) -> Result<Bag, BagError> {
        let file = if path.is_dir() {
            rosbag2_folder_file(path)?
        } else {
            path.to_path_buf()
        };
        let mut head = [0u8; 16];
        let read = {
            use std::io::Read;
            let mut f = std::fs::File::open(&file).map_err(|e| BagError::os(&file, e))?;
            let mut n = 0;
            while n < head.len() {
                match f.read(&mut head[n..]) {
                    Ok(0) => break,
                    Ok(k) => n += k,
                    Err(e) => return Err(BagError::os(&file, e)),
                }
            }
            n
        };
        let head = &head[..read];
        let (storage, inner): (Storage, Box<dyn Container>) = if head.starts_with(MCAP_MAGIC) {
            (Storage::Mcap, Box::new(mcap_reader::McapBag::open(&file)?))
        } else if head.starts_with(SQLITE_MAGIC) {
            (Storage::Sqlite3, Box::new(sqlite::SqliteBag::open(&file)?))
        } else if head.starts_with(ROS1_MAGIC) {
            (Storage::Ros1, Box::new(ros1::Ros1Bag::open(&file)?))
        } else if head.starts_with(b"#ROSBAG V") {
            return Err(BagError::malformed(
                &file,
                0,
                "a ROS 1 bag of another format version; only V2.0 is read",
            ));
        } else {
            return Err(BagError::UnknownFormat { path: file });
        };
        Ok(Bag {
            path: file,
            storage,
            inner,
        })
    }

    /// The file read (inside the folder, for a rosbag2 folder).
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// How the bag stores its messages.
    pub fn storage(&self) -> Storage {
        self.storage
    }

    /// Every topic, sorted by name.
    pub fn topics(&self) -> &[Topic] {
        self.inner.topics()
    }

    /// The topic named `name`; the error lists the bag's PointCloud2 and Imu topics.
    pub fn topic(&self, name: &str) -> Result<&Topic, BagError> {
        self.named_topic(name, "PointCloud2 and Imu", |t| {
            t.is_point_cloud() || t.is_imu()
        })
    }

    /// The topic named `name`; the error lists the bag's topics of `kinds` (`is`).
    fn named_topic(
        &self,
        name: &str,
        kinds: &str,
        is: impl Fn(&Topic) -> bool,
    ) -> Result<&Topic, BagError> {
        self.topics()
            .iter()
            .find(|t| t.name == name)
            .ok_or_else(|| BagError::NoTopic {
                path: self.path.clone(),
                topic: name.to_string(),
                kinds: kinds.to_string(),
                candidates: self.listing(is),
            })
    }

    /// The topic named `name`, which must be a PointCloud2 topic.
    pub fn point_cloud_topic(&self, name: &str) -> Result<&Topic, BagError> {
        self.typed_topic(name, "sensor_msgs/PointCloud2", Topic::is_point_cloud)
    }

    /// The topic named `name`, which must be an Imu topic.
    pub fn imu_topic(&self, name: &str) -> Result<&Topic, BagError> {
        self.typed_topic(name, "sensor_msgs/Imu", Topic::is_imu)
    }

    /// The topic `name`, which must carry `geometry_msgs/PoseWithCovarianceStamped`.
    pub fn pose_with_covariance_topic(&self, name: &str) -> Result<&Topic, BagError> {
        self.typed_topic(
            name,
            "geometry_msgs/PoseWithCovarianceStamped",
            Topic::is_pose_with_covariance,
        )
    }

    /// The topic `name`, which must carry `diagnostic_msgs/DiagnosticArray`.
    pub fn diagnostics_topic(&self, name: &str) -> Result<&Topic, BagError> {
        self.typed_topic(
            name,
            "diagnostic_msgs/DiagnosticArray",
            Topic::is_diagnostics,
        )
    }

    fn typed_topic(
        &self,
        name: &str,
        wanted: &str,
        is: fn(&Topic) -> bool,
    ) -> Result<&Topic, BagError> {
        // A sensor topic not found lists both sensors' topics (a cloud asked for under
        // the IMU's name shows); a localizer's output, the topics of its type.
        let topic = if wanted.starts_with("sensor_msgs/") {
            self.topic(name)?
        } else {
            self.named_topic(name, wanted.rsplit('/').next().unwrap_or(wanted), is)?
        };
        if !is(topic) {
            return Err(BagError::WrongType {
                path: self.path.clone(),
                topic: name.to_string(),
                found: topic.msg_type.clone(),
                wanted: wanted.to_string(),
                candidates: self.listing(is),
            });
        }
        Ok(topic)
    }

    fn listing(&self, keep: impl Fn(&Topic) -> bool) -> String {
        let names: Vec<String> = self
            .topics()
            .iter()
            .filter(|t| keep(t))
            .map(|t| format!("{} ({})", t.name, t.short_type()))
            .collect();
        if names.is_empty() {
            "none".into()
        } else {
            names.join(", ")
        }
    }

    /// Every message of `topic` in log-time order, streamed (memory: one chunk).
    pub fn messages<'a>(
        &'a self,
        topic: &Topic,
    ) -> Result<Box<dyn Iterator<Item = Result<Message, BagError>> + Send + 'a>, BagError> {
        self.inner.messages(topic)
    }

    /// Where every message of `topic` lies, in log-time order.
    pub fn index(&self, topic: &Topic) -> Result<Vec<MessageRef>, BagError> {
        self.inner.index(topic)
    }

    /// One message found by [`Bag::index`].
    pub fn read(&self, at: &MessageRef) -> Result<Message, BagError> {
        self.inner.read(at)
    }
}

/// The one storage file of a rosbag2 folder, from its `metadata.yaml`
/// (`relative_file_paths`); without the metadata, the folder's only `.mcap` or `.db3`.
fn rosbag2_folder_file(dir: &Path) -> Result<PathBuf, BagError> {
    let metadata = dir.join("metadata.yaml");
    let mut files: Vec<PathBuf> = Vec::new();
    if let Ok(text) = std::fs::read_to_string(&metadata) {
        // The list under `relative_file_paths:` is all the reader needs of the YAML.
        let mut in_list = false;
        for line in text.lines() {
            let trimmed = line.trim();
            if trimmed.starts_with("relative_file_paths:") {
                in_list = true;
                continue;
            }
            if in_list {
                if let Some(item) = trimmed.strip_prefix("- ") {
                    files.push(dir.join(item.trim().trim_matches(['"', '\''])));
                } else if !trimmed.is_empty() {
                    in_list = false;
                }
            }
        }
    }
    if files.is_empty() {
        let entries = std::fs::read_dir(dir).map_err(|e| BagError::os(dir, e))?;
        files = entries
            .filter_map(Result::ok)
            .map(|e| e.path())
            .filter(|p| {
                p.extension().is_some_and(|e| {
                    e.eq_ignore_ascii_case("mcap") || e.eq_ignore_ascii_case("db3")
                })
            })
            .collect();
        files.sort();
    }
    match files.len() {
        1 => Ok(files.remove(0)),
        0 => Err(BagError::NotABag {
            path: dir.to_path_buf(),
            reason: "a folder without metadata.yaml or an .mcap / .db3 file".into(),
        }),
        n => Err(BagError::NotABag {
            path: dir.to_path_buf(),
            reason: format!(
                "a split bag of {n} files; kfmap reads one file: pass it directly (e.g. {})",
                files[0].display()
            ),
        }),
    }
}

#[cfg(test)]
mod tests;
