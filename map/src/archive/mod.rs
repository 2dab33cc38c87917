//! Baked maps (docs/DESIGN.md#archive): one `.kfmap` file, memory-mapped read-only and
//! queried in place.
//!
//! Layout: a fixed 4096-byte [`Header`] (magic, format version, endianness, pointer
//! width, payload length and xxh3 checksum, index location and checksum, the map's
//! creation options as TOML), then the payload: one rkyv archive per keyframe (points,
//! view directions, covariances, KD-tree) at 128-byte aligned offsets, each with its
//! own checksum, and last an index archive ([`MapIndex`]: keyframe entries, covisibility
//! graph, gravity pool). Segmenting keeps every rkyv archive far below the 2 GiB reach of
//! 32-bit relative pointers while the file itself may be any size (offsets are u64).
//!
//! Opening checks the header and the index (checksum + bytecheck) and nothing else, so
//! cold start is O(keyframes); each keyframe's checksum and archive are verified the
//! first time it is used, before any of its bytes is trusted.

mod baked;
mod header;
mod records;
mod writer;

pub use baked::{BakedKeyframe, BakedPlaceGrid, OpenOptions, OpenedMap, open_map};
pub use header::{FORMAT_VERSION, HEADER_LEN, Header, POINTER_WIDTH, SEGMENT_ALIGN};
pub use records::{GravityRecord, KeyframeEntry, KeyframeRecord, MapIndex, PlaceEntry};
pub use writer::{MapWriter, SerializedKeyframe, WriteSummary, save_map};

#[cfg(not(target_endian = "little"))]
compile_error!(
    "baked maps are read in place as little-endian data; big-endian hosts are not supported"
);

use std::path::PathBuf;

use kfmap_geometry::KeyframeId;

/// Why a map file could not be written, opened or used.
#[derive(Debug, Clone, thiserror::Error)]
pub enum ArchiveError {
    /// The file system refused (missing file, permissions, full disk, ...).
    #[error("{path}: {message}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What the system said.
        message: String,
    },
    /// The path is a directory or a special file.
    #[error("{0}: not a regular file")]
    NotAFile(PathBuf),
    /// A zero-length file.
    #[error("{0}: empty file (0 bytes), not a kfmap map")]
    EmptyFile(PathBuf),
    /// The first bytes are not a kfmap header.
    #[error("not a kfmap map file (bad magic bytes)")]
    BadMagic,
    /// Written by a newer kfmap.
    #[error(
        "map format version {found} is newer than this build supports ({supported}); upgrade kfmap"
    )]
    NewerVersion {
        /// Version in the file.
        found: u32,
        /// Version this build reads.
        supported: u32,
    },
    /// Written by an older kfmap.
    #[error(
        "map format version {found} is older than this build supports ({supported}); bake the map again"
    )]
    OldVersion {
        /// Version in the file.
        found: u32,
        /// Version this build reads.
        supported: u32,
    },
    /// Archived for the other byte order.
    #[error("map archived as {found}; this build reads little-endian maps")]
    WrongEndianness {
        /// Byte order in the file.
        found: &'static str,
    },
    /// Archived with another rkyv pointer width (e.g. a 64-bit-pointer build).
    #[error(
        "map archived with {found}-byte rkyv pointers; this build reads {expected}-byte pointers"
    )]
    PointerWidth {
        /// Width in the file.
        found: u8,
        /// Width this build reads.
        expected: u8,
    },
    /// The header checksum does not match.
    #[error("map header is corrupt (checksum mismatch)")]
    HeaderCorrupt,
    /// The file is shorter than its header says.
    #[error("map file is truncated: {actual} bytes, expected {expected}")]
    Truncated {
        /// Bytes the header promises.
        expected: u64,
        /// Bytes present.
        actual: u64,
    },
    /// The creation options do not fit in the header.
    #[error("map options take {0} bytes, more than the header holds")]
    OptionsTooLarge(usize),
    /// The creation options in the header are unreadable or invalid.
    #[error("map options in the header are invalid: {0}")]
    BadOptions(String),
    /// The index checksum, archive or contents are wrong.
    #[error("map index is corrupt: {0}")]
    IndexCorrupt(String),
    /// The whole-payload checksum does not match (`kfmap inspect --verify`).
    #[error("map payload is corrupt (checksum mismatch)")]
    PayloadCorrupt,
    /// A keyframe's segment failed verification on first use.
    #[error("keyframe {id} is corrupt: {reason}")]
    KeyframeCorrupt {
        /// The keyframe.
        id: KeyframeId,
        /// What failed.
        reason: String,
    },
    /// A keyframe is too large for one segment.
    #[error(
        "keyframe {id} has {points} points, more than one segment holds ({max}); downsample it"
    )]
    KeyframeTooLarge {
        /// The keyframe.
        id: KeyframeId,
        /// Its points.
        points: usize,
        /// The limit.
        max: usize,
    },
    /// rkyv could not serialize a record.
    #[error("cannot serialize {0}")]
    Serialize(String),
}

impl ArchiveError {
    fn io(path: &std::path::Path, e: &std::io::Error) -> Self {
        Self::Io {
            path: path.to_path_buf(),
            message: e.to_string(),
        }
    }
}

// A unit test rather than an integration test: its 20 s of writing and page faults,
// mostly on one core, overlap the other unit tests instead of running alone.
#[cfg(test)]
mod large_map_tests;
#[cfg(test)]
mod tests;
