//! Readers and writers of point clouds (KITTI `.bin`, raw `.bin`, PCD, PLY) and
//! trajectories (TUM, KITTI). Every error names the file and the line or byte.

mod bin;
mod error;
mod fields;
pub mod lzf;
mod pcd;
mod ply;
mod trajectory;

use std::fmt;
use std::path::{Path, PathBuf};

pub use bin::{BinLayout, read_bin, write_bin};
pub use error::{IoError, Location};
pub use pcd::{PcdData, read_pcd, write_pcd};
pub use ply::{PlyEncoding, read_ply, write_ply};
pub use trajectory::{
    Trajectory, format_kitti_poses, format_tum, parse_kitti_poses, parse_tum, read_keyframe_graph,
    read_trajectory,
};

use crate::cloud::{FilterOptions, FilterReport, PointCloud};

/// A point-cloud file format with its encoding.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CloudFormat {
    /// Headerless float32 records, see [`BinLayout`].
    Bin(BinLayout),
    /// PCD with its data mode.
    Pcd(PcdData),
    /// PLY with its encoding.
    Ply(PlyEncoding),
}

impl fmt::Display for CloudFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            CloudFormat::Bin(BinLayout::Xyzi) => "kitti-bin",
            CloudFormat::Bin(BinLayout::Xyz) => "raw-xyz-bin",
            CloudFormat::Pcd(PcdData::Ascii) => "pcd-ascii",
            CloudFormat::Pcd(PcdData::Binary) => "pcd-binary",
            CloudFormat::Pcd(PcdData::BinaryCompressed) => "pcd-binary-compressed",
            CloudFormat::Ply(PlyEncoding::Ascii) => "ply-ascii",
            CloudFormat::Ply(PlyEncoding::BinaryLittleEndian) => "ply-binary-le",
        })
    }
}

/// How to read a cloud file.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ReadOptions {
    /// Layout of `.bin` files; `None`: the sidecar `FILE.layout` (`xyz` or `xyzi`)
    /// if present, else KITTI `xyzi`.
    pub bin_layout: Option<BinLayout>,
    /// The invalid-return filter applied after reading.
    pub filter: FilterOptions,
}

/// A cloud as read from a file.
#[derive(Debug, Clone)]
pub struct LoadedCloud {
    /// The points (after the filter, when enabled).
    pub cloud: PointCloud,
    /// The file's format.
    pub format: CloudFormat,
    /// Field names as the file declares them.
    pub fields: Vec<String>,
    /// Points in the file before filtering.
    pub points_in_file: usize,
    /// What the filter dropped; `None` when it was disabled.
    pub filter: Option<FilterReport>,
}

fn sidecar_layout(path: &Path) -> Result<Option<BinLayout>, IoError> {
    let mut sidecar = path.as_os_str().to_owned();
    sidecar.push(".layout");
    let sidecar = PathBuf::from(sidecar);
    match std::fs::read_to_string(&sidecar) {
        Ok(text) => BinLayout::parse(&text).map(Some).ok_or_else(|| {
            IoError::malformed(
                &sidecar,
                Location::Line(1),
                format!("layout '{}' is neither 'xyz' nor 'xyzi'", text.trim()),
            )
        }),
        Err(_) => Ok(None),
    }
}

/// Reads a point cloud, telling the format by extension (`.pcd`, `.ply`, `.bin`) or,
/// failing that, by the first bytes; then validates it and applies the filter.
pub fn read_cloud(path: &Path, options: &ReadOptions) -> Result<LoadedCloud, IoError> {
    let bytes = std::fs::read(path).map_err(|e| IoError::os(path, e))?;
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    let (cloud, format, fields) = match ext.as_deref() {
        Some("bin") => {
            let layout = match options.bin_layout {
                Some(l) => l,
                None => sidecar_layout(path)?.unwrap_or(BinLayout::Xyzi),
            };
            let cloud = read_bin(path, &bytes, layout)?;
            let fields = cloud.field_names().iter().map(|s| s.to_string()).collect();
            (cloud, CloudFormat::Bin(layout), fields)
        }
        _ if ext.as_deref() == Some("pcd")
            || bytes.starts_with(b"# .PCD")
            || bytes.starts_with(b"VERSION") =>
        {
            let (cloud, data, fields) = read_pcd(path, &bytes)?;
            (cloud, CloudFormat::Pcd(data), fields)
        }
        _ if ext.as_deref() == Some("ply") || bytes.starts_with(b"ply") => {
            let (cloud, encoding, fields) = read_ply(path, &bytes)?;
            (cloud, CloudFormat::Ply(encoding), fields)
        }
        _ => {
            return Err(IoError::UnknownFormat {
                path: path.to_path_buf(),
            });
        }
    };
    let mut loaded = LoadedCloud {
        points_in_file: cloud.len(),
        cloud,
        format,
        fields,
        filter: None,
    };
    if options.filter.enabled {
        loaded.filter = Some(loaded.cloud.remove_invalid(options.filter.min_range));
    }
    Ok(loaded)
}

/// Encodes `cloud` in `format`.
pub fn encode_cloud(cloud: &PointCloud, format: CloudFormat) -> Vec<u8> {
    match format {
        CloudFormat::Bin(layout) => write_bin(cloud, layout),
        CloudFormat::Pcd(data) => write_pcd(cloud, data),
        CloudFormat::Ply(encoding) => write_ply(cloud, encoding),
    }
}

/// Writes bytes to `path` atomically: a temporary file in the same directory, fsync,
/// rename. A crash mid-write never leaves a partial file under the final name.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), IoError> {
    use std::io::Write;
    let tmp = temp_path_beside(path)?;
    let result = (|| {
        let mut file = std::fs::File::create(&tmp)?;
        file.write_all(bytes)?;
        file.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    result.map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        IoError::os(path, e)
    })
}

/// As [`write_atomic`] without the fsync: the file is whole or absent, and durable once
/// the caller syncs the file system ([`sync_file_system`]); a tile set writes hundreds
/// of files and makes them durable at once, before its index.
pub fn write_replacing(path: &Path, bytes: &[u8]) -> Result<(), IoError> {
    let tmp = temp_path_beside(path)?;
    std::fs::write(&tmp, bytes)
        .and_then(|()| std::fs::rename(&tmp, path))
        .map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            IoError::os(path, e)
        })
}

/// Makes everything written to the file system holding `dir` durable (Linux `syncfs`;
/// elsewhere a full `sync`).
pub fn sync_file_system(dir: &Path) -> Result<(), IoError> {
    #[cfg(target_os = "linux")]
    {
        use std::os::fd::AsRawFd;
        let handle = std::fs::File::open(dir).map_err(|e| IoError::os(dir, e))?;
        // SAFETY: the descriptor is open for the call's duration; syncfs only flushes.
        if unsafe { libc::syncfs(handle.as_raw_fd()) } != 0 {
            return Err(IoError::os(dir, std::io::Error::last_os_error()));
        }
    }
    #[cfg(not(target_os = "linux"))]
    {
        let _ = dir;
        // SAFETY: sync takes no arguments and only flushes.
        unsafe { libc::sync() };
    }
    Ok(())
}

/// Bytes an unprivileged process may still write on the file system holding `dir`
/// (`statvfs`), `None` where it cannot be read.
pub fn free_bytes(dir: &Path) -> Option<u64> {
    use std::os::unix::ffi::OsStrExt;
    let path = std::ffi::CString::new(dir.as_os_str().as_bytes()).ok()?;
    // SAFETY: `statvfs` is a plain C struct of integers, for which all-zero bytes are
    // a valid value.
    let mut stat: libc::statvfs = unsafe { std::mem::zeroed() };
    // SAFETY: `path` is a NUL-terminated C string that outlives the call, and `stat` a
    // writable `statvfs` the call fills.
    let rc = unsafe { libc::statvfs(path.as_ptr(), &mut stat) };
    (rc == 0).then(|| stat.f_bavail.saturating_mul(stat.f_frsize))
}

/// A hidden temporary name in `path`'s directory (same file system, so a rename onto
/// `path` is atomic): `.NAME.tmpPID`.
pub fn temp_path_beside(path: &Path) -> Result<std::path::PathBuf, IoError> {
    let dir = path
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let name = path
        .file_name()
        .ok_or_else(|| IoError::malformed(path, Location::File, "not a file path"))?;
    let mut tmp_name = std::ffi::OsString::from(".");
    tmp_name.push(name);
    tmp_name.push(format!(".tmp{}", std::process::id()));
    Ok(dir.join(tmp_name))
}

/// Writes `cloud` to `path` in `format`, atomically.
pub fn write_cloud(path: &Path, cloud: &PointCloud, format: CloudFormat) -> Result<(), IoError> {
    write_atomic(path, &encode_cloud(cloud, format))
}

#[cfg(test)]
mod tests;
