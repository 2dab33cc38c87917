//! Where a dataset's scans, poses and IMU samples come from: a folder of scan files
//! (with a pose file and `imu.csv` beside them) or a bag (point clouds on one topic, IMU
//! samples on another). Everything downstream sees a [`ScanList`] and an
//! [`ImuSource`], whatever the origin.

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use kfmap_bag::msg::decode_point_cloud2;
use kfmap_bag::{Bag, BagError, MessageRef, Topic};
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::io::BinLayout;

use crate::config::BakeConfig;
use crate::error::BakeError;
use crate::files::{IMU_FILES, POSE_FILES, find_in};
use crate::scan_files::{find_scans, load_raw_scan};
// Where it was first: an IMU source is part of a dataset's source.
pub use crate::gravity::ImuSource;

/// A header stamp this far from the recorder's log time is reported (seconds): a
/// driver stamping with another clock, or a recorder far behind.
const STAMP_LOG_GAP_WARN_S: f64 = 1.0;

/// Where a dataset comes from.
#[derive(Debug, Clone, PartialEq)]
pub enum Source {
    /// A folder of scan files (`DIR/scans/` or `DIR`), its pose file and IMU log beside.
    Folder(PathBuf),
    /// A bag.
    Bag(BagSource),
}

/// A bag as a dataset: its clouds on one topic, optionally its IMU on another.
#[derive(Debug, Clone, PartialEq)]
pub struct BagSource {
    /// The bag: an `.mcap`, `.db3` or `.bag` file, or a rosbag2 folder.
    pub path: PathBuf,
    /// The `sensor_msgs/PointCloud2` topic whose clouds are the scans.
    pub points_topic: String,
    /// The `sensor_msgs/Imu` topic, if the IMU is used.
    pub imu_topic: Option<String>,
}

impl Source {
    /// The folder or bag path, for messages.
    pub fn path(&self) -> &Path {
        match self {
            Source::Folder(dir) => dir,
            Source::Bag(b) => &b.path,
        }
    }

    /// The pose file found in a folder (the first of [`POSE_FILES`]); a bag has none
    /// (pass `--poses`).
    pub fn pose_file(&self) -> Option<PathBuf> {
        match self {
            Source::Folder(dir) => find_in(dir, &POSE_FILES),
            Source::Bag(_) => None,
        }
    }

    /// The IMU log: a folder's `imu.csv` / `imu.txt`, a bag's `--imu-topic`.
    pub fn imu(&self) -> Option<ImuSource> {
        match self {
            Source::Folder(dir) => find_in(dir, &IMU_FILES).map(ImuSource::File),
            Source::Bag(b) => b.imu_topic.as_ref().map(|topic| ImuSource::Topic {
                bag: b.path.clone(),
                topic: topic.clone(),
            }),
        }
    }

    /// The scans: a folder's sorted scan files, or a bag's clouds on the points topic
    /// (one pass over them reads their header stamps; `progress(done, total)` follows it).
    pub fn scans(&self, progress: &mut dyn FnMut(usize, usize)) -> Result<ScanList, BakeError> {
        match self {
            Source::Folder(dir) => Ok(ScanList::files(find_scans(dir)?)),
            Source::Bag(b) => ScanList::bag(&b.path, &b.points_topic, progress),
        }
    }
}

/// The scans of a dataset, in order: files, or clouds of a bag topic. Cheap to clone
/// (a bag is shared), and [`ScanList::select`] keeps a range of it.
#[derive(Debug, Clone)]
pub struct ScanList {
    scans: Scans,
}

#[derive(Debug, Clone)]
enum Scans {
    Files(Vec<PathBuf>),
    Bag(BagClouds),
}

/// A bag topic's clouds: where each lies and its header stamp.
#[derive(Debug, Clone)]
struct BagClouds {
    bag: Arc<Bag>,
    topic: Arc<Topic>,
    refs: Vec<MessageRef>,
    stamps: Vec<f64>,
    /// Index on the topic of `refs[0]` (after a [`ScanList::select`]).
    first: usize,
}

impl ScanList {
    /// Scan files, in order.
    pub fn files(paths: Vec<PathBuf>) -> Self {
        Self {
            scans: Scans::Files(paths),
        }
    }

    /// The clouds of `topic` in the bag at `path`, read once for their header stamps.
    pub fn bag(
        path: &Path,
        topic: &str,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<Self, BakeError> {
        let bag = Bag::open(path)?;
        let topic = bag.point_cloud_topic(topic)?.clone();
        let refs = bag.index(&topic)?;
        let total = refs.len();
        let mut stamps = Vec::with_capacity(total);
        let mut widest_gap = (0.0f64, 0usize);
        // By the refs already listed (not a second index pass), through the chunk cache.
        for (index, at) in refs.iter().enumerate() {
            let message = bag.read(at)?;
            let fail = |reason: String| {
                BagError::message(bag.path(), &topic.name, index, message.log_time_ns, reason)
            };
            let cloud = decode_point_cloud2(&message.data, topic.encoding)
                .map_err(|e| fail(e.to_string()))?;
            let log_time = message.log_time_ns as f64 * 1e-9;
            // A driver that leaves the stamp unset: the log time is the best there is.
            let stamp = if cloud.stamp.nanos() == 0 {
                log_time
            } else {
                cloud.stamp.seconds()
            };
            if let Some(&last) = stamps.last().filter(|&&last| stamp <= last) {
                return Err(fail(format!(
                    "header stamp {stamp:.6} s is not after the previous cloud's {last:.6} s; scans must be in time order"
                ))
                .into());
            }
            let gap = (stamp - log_time).abs();
            if gap > widest_gap.0 {
                widest_gap = (gap, index);
            }
            stamps.push(stamp);
            progress(index + 1, total);
        }
        if stamps.is_empty() {
            return Err(BakeError::NoScans(path.to_path_buf()));
        }
        if widest_gap.0 > STAMP_LOG_GAP_WARN_S {
            tracing::warn!(
                "{}: {}: cloud {} has its header stamp {:.3} s from its log time; kfmap uses the header stamps (the IMU topic must share their clock)",
                path.display(),
                topic.name,
                widest_gap.1,
                widest_gap.0
            );
        }
        Ok(Self {
            scans: Scans::Bag(BagClouds {
                bag: Arc::new(bag),
                topic: Arc::new(topic),
                refs,
                stamps,
                first: 0,
            }),
        })
    }

    /// Scans in the list.
    pub fn len(&self) -> usize {
        match &self.scans {
            Scans::Files(paths) => paths.len(),
            Scans::Bag(b) => b.refs.len(),
        }
    }

    /// True when the list is empty.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Scans `range` only.
    pub fn select(&self, range: Range<usize>) -> Self {
        let scans = match &self.scans {
            Scans::Files(paths) => Scans::Files(paths[range].to_vec()),
            Scans::Bag(b) => Scans::Bag(BagClouds {
                bag: b.bag.clone(),
                topic: b.topic.clone(),
                refs: b.refs[range.clone()].to_vec(),
                stamps: b.stamps[range.clone()].to_vec(),
                first: b.first + range.start,
            }),
        };
        Self { scans }
    }

    /// The scan files, when the scans are files.
    pub fn paths(&self) -> Option<&[PathBuf]> {
        match &self.scans {
            Scans::Files(paths) => Some(paths),
            Scans::Bag(_) => None,
        }
    }

    /// Each scan's header stamp, seconds, when the scans come from a bag.
    pub fn stamps(&self) -> Option<&[f64]> {
        match &self.scans {
            Scans::Files(_) => None,
            Scans::Bag(b) => Some(&b.stamps),
        }
    }

    /// Scan `i`'s name for messages: its file, or `BAG:TOPIC#N` (N counting clouds).
    pub fn name(&self, i: usize) -> PathBuf {
        match &self.scans {
            Scans::Files(paths) => paths[i].clone(),
            Scans::Bag(b) => PathBuf::from(format!(
                "{}:{}#{}",
                b.bag.path().display(),
                b.topic.name,
                b.first + i
            )),
        }
    }

    /// The frame number of every scan when every scan file is named by one (KITTI
    /// `000123.bin`); `None` otherwise and for bags.
    pub fn frame_numbers(&self) -> Option<Vec<usize>> {
        self.paths()?
            .iter()
            .map(|s| s.file_stem()?.to_str()?.parse().ok())
            .collect()
    }

    /// True when every scan is a KITTI velodyne `.bin` (x y z intensity: a raw sweep
    /// stored without per-point times).
    pub fn all_kitti_bin(&self, config: &BakeConfig) -> bool {
        let Some(paths) = self.paths() else {
            return false;
        };
        let kitti_bin = |path: &PathBuf| {
            let bin = path
                .extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("bin"));
            let sidecar = std::fs::read_to_string(path.with_extension("bin.layout")).ok();
            let layout = sidecar.map_or(Some(config.input.bin_layout), |s| BinLayout::parse(&s));
            bin && layout == Some(BinLayout::Xyzi)
        };
        !paths.is_empty() && paths.iter().all(kitti_bin)
    }

    /// Reads scan `i` and drops invalid returns (the bake configuration's filter), as
    /// for scan files: NaN, the origin and returns closer than `min-range`.
    pub fn load_raw(&self, i: usize, config: &BakeConfig) -> Result<PointCloud, BakeError> {
        match &self.scans {
            Scans::Files(paths) => load_raw_scan(&paths[i], config),
            Scans::Bag(b) => {
                let at = &b.refs[i];
                let message = b.bag.read(at)?;
                let fail = |reason: String| {
                    BagError::message(
                        b.bag.path(),
                        &b.topic.name,
                        b.first + i,
                        at.log_time_ns,
                        reason,
                    )
                };
                let decoded = decode_point_cloud2(&message.data, b.topic.encoding)
                    .map_err(|e| fail(e.to_string()))?;
                let mut cloud = decoded.to_cloud().map_err(|e| fail(e.to_string()))?;
                if config.filter.enabled {
                    cloud.remove_invalid(config.filter.min_range);
                }
                cloud.raise_elevation(config.input.vertical_angle_offset_deg);
                Ok(cloud)
            }
        }
    }
}
