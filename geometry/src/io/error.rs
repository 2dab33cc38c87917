//! The error of every reader and writer: which file, where in it, what is wrong.

use std::fmt;
use std::path::PathBuf;

/// Where in a file a problem was found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Location {
    /// A 1-based line of a text file or header.
    Line(usize),
    /// A byte offset from the start of the file.
    Byte(u64),
    /// The file as a whole (its size, its name).
    File,
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Location::Line(n) => write!(f, "line {n}"),
            Location::Byte(b) => write!(f, "byte {b}"),
            Location::File => write!(f, "file"),
        }
    }
}

/// A read or write failed.
#[derive(Debug, thiserror::Error)]
pub enum IoError {
    /// The operating system refused (missing file, permissions, full disk).
    // Not a `source` field: the message already says it, and error chains would
    // repeat it.
    #[error("{}: {cause}", path.display())]
    Os {
        /// The file.
        path: PathBuf,
        /// What the OS said.
        cause: std::io::Error,
    },
    /// The content is not what its format requires.
    #[error("{}: {location}: {reason}", path.display())]
    Malformed {
        /// The file.
        path: PathBuf,
        /// Where the problem is.
        location: Location,
        /// What is wrong, and what was expected.
        reason: String,
    },
    /// The name and content match no supported format.
    #[error("{}: unknown point-cloud format; supported: .pcd, .ply, .bin (KITTI x y z intensity, or raw x y z with --bin-layout xyz)", path.display())]
    UnknownFormat {
        /// The file.
        path: PathBuf,
    },
}

impl IoError {
    /// A [`IoError::Malformed`] at `location` of `path`.
    pub fn malformed(
        path: impl Into<PathBuf>,
        location: Location,
        reason: impl Into<String>,
    ) -> Self {
        IoError::Malformed {
            path: path.into(),
            location,
            reason: reason.into(),
        }
    }

    /// A [`IoError::Os`] for `path`.
    pub fn os(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        IoError::Os {
            path: path.into(),
            cause: source,
        }
    }
}
