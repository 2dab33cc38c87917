//! What goes wrong reading a bag: which file, where, what.

use std::path::{Path, PathBuf};

/// A bag could not be read.
#[derive(Debug, thiserror::Error)]
pub enum BagError {
    /// The operating system refused (missing file, permissions).
    #[error("{}: {cause}", path.display())]
    Os {
        /// The file.
        path: PathBuf,
        /// What the OS said.
        cause: std::io::Error,
    },
    /// Neither MCAP, SQLite nor a ROS 1 bag.
    #[error(
        "{}: not a bag; supported: MCAP (.mcap), rosbag2 sqlite3 (.db3 or its folder with metadata.yaml), ROS 1 bag v2.0 (.bag)",
        path.display()
    )]
    UnknownFormat {
        /// The file.
        path: PathBuf,
    },
    /// A folder that holds no single bag file.
    #[error("{}: {reason}", path.display())]
    NotABag {
        /// The folder.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// The bytes break the container's format (truncated, corrupt).
    #[error("{}: byte {offset}: {reason}", path.display())]
    Malformed {
        /// The file.
        path: PathBuf,
        /// Where, bytes from the start of the file (or of the record, as the reason says).
        offset: u64,
        /// What is wrong.
        reason: String,
    },
    /// A chunk compressed with a codec kfmap does not read.
    #[error("{}: byte {offset}: chunk compression '{codec}' is not supported (supported: {supported})", path.display())]
    Codec {
        /// The file.
        path: PathBuf,
        /// The chunk's offset.
        offset: u64,
        /// The codec named in the file.
        codec: String,
        /// What is supported for this container.
        supported: &'static str,
    },
    /// No topic of that name.
    #[error("{}: no topic '{topic}'; its {kinds} topics: {candidates}", path.display())]
    NoTopic {
        /// The bag.
        path: PathBuf,
        /// The name asked for.
        topic: String,
        /// What kinds of topic `candidates` lists, e.g. `PointCloud2 and Imu`.
        kinds: String,
        /// The bag's topics of those kinds (`name (type)`), or `none`.
        candidates: String,
    },
    /// A topic of another message type than the one asked for.
    #[error("{}: topic '{topic}' carries {found}, not {wanted}; topics of that type: {candidates}", path.display())]
    WrongType {
        /// The bag.
        path: PathBuf,
        /// The topic.
        topic: String,
        /// Its type.
        found: String,
        /// The type wanted.
        wanted: String,
        /// Topics of the wanted type, or `none`.
        candidates: String,
    },
    /// A message that does not decode as its type.
    #[error("{}: {topic} message {index} (log time {log_time_ns} ns): {reason}", path.display())]
    Message {
        /// The bag.
        path: PathBuf,
        /// Its topic.
        topic: String,
        /// Its index on the topic (0-based).
        index: usize,
        /// Its log time.
        log_time_ns: u64,
        /// What is wrong.
        reason: String,
    },
}

impl BagError {
    /// A [`BagError::Os`].
    pub fn os(path: impl AsRef<Path>, cause: std::io::Error) -> Self {
        BagError::Os {
            path: path.as_ref().to_path_buf(),
            cause,
        }
    }

    /// A [`BagError::Message`]: message `index` of `topic` in the bag at `path`, logged
    /// at `log_time_ns`, is wrong as `reason` says.
    pub fn message(
        path: impl AsRef<Path>,
        topic: &str,
        index: usize,
        log_time_ns: u64,
        reason: impl ToString,
    ) -> Self {
        BagError::Message {
            path: path.as_ref().to_path_buf(),
            topic: topic.to_string(),
            index,
            log_time_ns,
            reason: reason.to_string(),
        }
    }

    /// A [`BagError::Malformed`] at `offset`.
    pub fn malformed(path: impl AsRef<Path>, offset: u64, reason: impl Into<String>) -> Self {
        BagError::Malformed {
            path: path.as_ref().to_path_buf(),
            offset,
            reason: reason.into(),
        }
    }
}
