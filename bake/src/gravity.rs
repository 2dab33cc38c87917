//! Gravity from a dataset (`kfmap gravity`, and `kfmap bake` when the dataset has an
//! IMU log): keyframe windows of the IMU stream pooled by the aligner, with and without
//! motion compensation.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use kfmap_geometry::KeyframeId;
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::gravity::{
    GravityAligner, GravityCorrection, GravityParams, KeyframeStamp, MotionModel, PoolFill,
    fill_pool,
};
use kfmap_geometry::imu::{ImuSample, read_imu_csv};
use kfmap_geometry::io::{IoError, Trajectory, read_trajectory};
use kfmap_geometry::options::InvalidOption;
use kfmap_map::archive::GravityRecord;

use kfmap_bag::msg::decode_imu;
use kfmap_bag::{Bag, BagError};

// Where they were first: gravity reads the dataset's files through here too.
pub use crate::files::{IMU_FILES, POSE_FILES, find_in};

/// Why gravity could not be estimated from a dataset.
#[derive(Debug, thiserror::Error)]
pub enum GravityError {
    /// No file of the kind needed.
    #[error("{dir}: no {what}; pass --{flag} FILE or put one of {tried} in the dataset")]
    Missing {
        /// The dataset.
        dir: PathBuf,
        /// "IMU log" or "poses".
        what: &'static str,
        /// The command-line flag naming it.
        flag: &'static str,
        /// File names looked for.
        tried: String,
    },
    /// Poses without timestamps (KITTI) cannot be matched to IMU samples.
    #[error(
        "{0}: poses have no timestamps (KITTI format); gravity needs TUM poses (t x y z qx qy qz qw)"
    )]
    NoStamps(PathBuf),
    /// The IMU log has no samples.
    #[error("{0}: no IMU samples")]
    NoImu(PathBuf),
    /// No IMU sample falls inside the trajectory's time span.
    #[error(
        "{imu}: IMU samples span {imu_span}, poses span {pose_span}: they do not overlap (different clocks?)"
    )]
    NoOverlap {
        /// The IMU log.
        imu: PathBuf,
        /// Its time span.
        imu_span: String,
        /// The pose file's time span.
        pose_span: String,
    },
    /// A file could not be read.
    #[error(transparent)]
    Io(#[from] IoError),
    /// A bag could not be read (boxed: its errors carry the bag's topic listing).
    #[error(transparent)]
    Bag(Box<kfmap_bag::BagError>),
    /// A parameter is out of range.
    #[error(transparent)]
    Invalid(#[from] InvalidOption),
}

/// Where `kfmap gravity` reads from and how it picks keyframes.
#[derive(Debug, Clone)]
pub struct GravityInput {
    /// IMU log (`imu.csv`, or whitespace-separated `t ax ay az wx wy wz`), or a bag's
    /// Imu topic.
    pub imu: ImuSource,
    /// TUM poses `T_map_body` on the IMU's clock.
    pub poses: PathBuf,
    /// A pose becomes a keyframe once this many seconds passed since the last one.
    pub keyframe_interval: f64,
}

impl GravityInput {
    /// Files found in a dataset folder, unless given.
    pub fn in_dataset(
        dataset: &Path,
        imu: Option<PathBuf>,
        poses: Option<PathBuf>,
        keyframe_interval: f64,
    ) -> Result<Self, GravityError> {
        let missing = |what, flag, names: &[&str]| GravityError::Missing {
            dir: dataset.to_path_buf(),
            what,
            flag,
            tried: names.join(", "),
        };
        Ok(Self {
            imu: ImuSource::File(match imu {
                Some(p) => p,
                None => find_in(dataset, &IMU_FILES)
                    .ok_or_else(|| missing("IMU log", "imu", &IMU_FILES))?,
            }),
            poses: match poses {
                Some(p) => p,
                None => find_in(dataset, &POSE_FILES)
                    .ok_or_else(|| missing("poses", "poses", &POSE_FILES))?,
            },
            keyframe_interval,
        })
    }
}

/// Global corrections with and without motion compensation, and per-keyframe ones.
#[derive(Debug, Clone)]
pub struct GravityReport {
    /// Poses read.
    pub poses: usize,
    /// IMU samples read.
    pub imu_samples: usize,
    /// How the pool was filled (with the configured compensation).
    pub fill: PoolFill,
    /// The configured estimate (`None`: fewer pooled keyframes than `min-keyframes`).
    pub correction: Option<GravityCorrection>,
    /// The estimate without motion compensation, for comparison.
    pub uncompensated: Option<GravityCorrection>,
    /// Per-keyframe corrections (keyframe id = pose index), when asked for.
    pub per_keyframe: BTreeMap<KeyframeId, GravityCorrection>,
    /// Keyframe times, by id.
    pub keyframe_times: BTreeMap<KeyframeId, f64>,
}

/// Per-keyframe corrections to compute: window half width and members needed.
#[derive(Debug, Clone, Copy)]
pub struct PerKeyframe {
    /// Keyframes on each side of the one corrected.
    pub half_width: usize,
    /// Members the window needs.
    pub min_pool: usize,
}

/// Keyframes from timestamped poses: the first pose, then each pose at least
/// `interval` seconds after the previous keyframe. Ids are pose indices.
pub fn keyframes_every(stamps: &[f64], poses: &[Pose], interval: f64) -> Vec<KeyframeStamp> {
    let mut chosen: Vec<KeyframeStamp> = Vec::new();
    for (i, (&t, pose)) in stamps.iter().zip(poses).enumerate() {
        if chosen.last().is_none_or(|last| t - last.t >= interval) {
            chosen.push(KeyframeStamp {
                id: i as KeyframeId,
                t,
                pose: *pose,
            });
        }
    }
    chosen
}

/// Reads IMU samples, refusing an empty log.
pub fn read_imu(path: &Path) -> Result<Vec<ImuSample>, GravityError> {
    let imu = read_imu_csv(path)?;
    if imu.is_empty() {
        return Err(GravityError::NoImu(path.to_path_buf()));
    }
    Ok(imu)
}

/// Pose timestamps, refusing files without them.
pub fn pose_stamps<'t>(path: &Path, trajectory: &'t Trajectory) -> Result<&'t [f64], GravityError> {
    trajectory
        .stamps
        .as_deref()
        .ok_or_else(|| GravityError::NoStamps(path.to_path_buf()))
}

/// Smallest and largest of `values`.
fn span(values: impl Iterator<Item = f64>) -> (f64, f64) {
    values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    })
}

/// Checks that the IMU log and the poses share a clock (their spans overlap).
pub fn check_overlap(
    imu_path: &Path,
    imu: &[ImuSample],
    stamps: &[f64],
) -> Result<(), GravityError> {
    let (i0, i1) = span(imu.iter().map(|s| s.t));
    let (p0, p1) = span(stamps.iter().copied());
    if i1 < p0 || p1 < i0 {
        return Err(GravityError::NoOverlap {
            imu: imu_path.to_path_buf(),
            imu_span: format!("{i0:.3}..{i1:.3} s"),
            pose_span: format!("{p0:.3}..{p1:.3} s"),
        });
    }
    Ok(())
}

/// Estimates gravity over a dataset's IMU log and poses.
pub fn estimate_dataset_gravity(
    input: &GravityInput,
    params: &GravityParams,
    per_keyframe: Option<PerKeyframe>,
) -> Result<GravityReport, GravityError> {
    params.validate()?;
    let trajectory = read_trajectory(&input.poses)?;
    let stamps = pose_stamps(&input.poses, &trajectory)?;
    let imu = input.imu.read()?;
    check_overlap(&input.imu.label(), &imu, stamps)?;
    let keyframes = keyframes_every(stamps, &trajectory.poses, input.keyframe_interval);
    let motion = MotionModel::new(stamps.iter().copied().zip(trajectory.poses.iter().copied()));
    let poses: BTreeMap<KeyframeId, Pose> = keyframes.iter().map(|k| (k.id, k.pose)).collect();
    let pooled = |compensate: bool| -> Result<(GravityAligner, PoolFill), GravityError> {
        let mut aligner = GravityAligner::new(GravityParams {
            motion_compensation: compensate,
            ..*params
        })?;
        let fill = fill_pool(&mut aligner, &keyframes, &imu, motion.as_ref());
        Ok((aligner, fill))
    };
    let (aligner, fill) = pooled(params.motion_compensation)?;
    let uncompensated = match params.motion_compensation {
        true => pooled(false)?.0.estimate_global_correction(&poses),
        false => None,
    };
    let per_keyframe = per_keyframe.map_or_else(BTreeMap::new, |p| {
        aligner.estimate_per_kf_correction(&poses, p.half_width, p.min_pool)
    });
    Ok(GravityReport {
        poses: trajectory.poses.len(),
        imu_samples: imu.len(),
        fill,
        correction: aligner.estimate_global_correction(&poses),
        uncompensated,
        per_keyframe,
        keyframe_times: keyframes.iter().map(|k| (k.id, k.t)).collect(),
    })
}

/// What a bake did with the dataset's IMU log.
#[derive(Debug, Clone)]
pub struct BakeGravity {
    /// The IMU log read (a file, or `BAG:TOPIC`).
    pub imu: PathBuf,
    /// How the pool was filled.
    pub fill: PoolFill,
    /// The global correction (`None`: too few keyframes with samples).
    pub correction: Option<GravityCorrection>,
    /// True when the keyframe poses were rotated by the correction.
    pub applied: bool,
    /// The pool as stored in the map.
    pub pool: Vec<GravityRecord>,
}

/// The gravity stage of a bake: pools the IMU windows of the chosen keyframes (`ids`
/// and `keyframe_scans` in step: keyframe id, index of its scan), with motion taken
/// from every scan's pose and stamp. `Ok(None)` without an IMU log, or (with a warning)
/// when the poses have no timestamps to cut its windows with.
pub fn bake_gravity(
    imu: Option<&ImuSource>,
    params: &GravityParams,
    scan_poses: &[Pose],
    scan_stamps: Option<&[f64]>,
    keyframe_scans: &[(KeyframeId, usize)],
) -> Result<Option<BakeGravity>, GravityError> {
    let Some(imu_source) = imu else {
        return Ok(None);
    };
    let imu_path = imu_source.label();
    let Some(stamps) = scan_stamps else {
        tracing::warn!(
            "{}: the poses have no timestamps, so its IMU windows cannot be cut; the map is baked without gravity",
            imu_path.display()
        );
        return Ok(None);
    };
    let imu = imu_source.read()?;
    check_overlap(&imu_path, &imu, stamps)?;
    let keyframes: Vec<KeyframeStamp> = keyframe_scans
        .iter()
        .map(|&(id, scan)| KeyframeStamp {
            id,
            t: stamps[scan],
            pose: scan_poses[scan],
        })
        .collect();
    let motion = MotionModel::new(stamps.iter().copied().zip(scan_poses.iter().copied()));
    let mut aligner = GravityAligner::new(*params)?;
    let fill = fill_pool(&mut aligner, &keyframes, &imu, motion.as_ref());
    let poses: BTreeMap<KeyframeId, Pose> = keyframes.iter().map(|k| (k.id, k.pose)).collect();
    let pool = aligner
        .samples()
        .iter()
        .map(|(&id, s)| GravityRecord {
            keyframe: id,
            mean_acc: s.a_body.into(),
            std: s.a_std,
            samples: s.n as u64,
        })
        .collect();
    Ok(Some(BakeGravity {
        imu: imu_path,
        fill,
        correction: aligner.estimate_global_correction(&poses),
        applied: false,
        pool,
    }))
}

impl From<kfmap_bag::BagError> for GravityError {
    fn from(error: kfmap_bag::BagError) -> Self {
        Self::Bag(Box::new(error))
    }
}

/// Where IMU samples come from.
#[derive(Debug, Clone, PartialEq)]
pub enum ImuSource {
    /// An `imu.csv` (or whitespace-separated `t ax ay az wx wy wz`) file.
    File(PathBuf),
    /// A `sensor_msgs/Imu` topic of a bag; samples at their header stamps.
    Topic {
        /// The bag.
        bag: PathBuf,
        /// The topic.
        topic: String,
    },
}

impl ImuSource {
    /// A name for messages: the file, or `BAG:TOPIC`.
    pub fn label(&self) -> PathBuf {
        match self {
            ImuSource::File(path) => path.clone(),
            ImuSource::Topic { bag, topic } => PathBuf::from(format!("{}:{topic}", bag.display())),
        }
    }

    /// Every sample, in time order; an empty log or a sample out of order is an error.
    pub fn read(&self) -> Result<Vec<ImuSample>, GravityError> {
        match self {
            ImuSource::File(path) => read_imu(path),
            ImuSource::Topic { bag, topic } => read_imu_topic(bag, topic),
        }
    }
}

/// The samples of a bag's Imu topic, at their header stamps.
fn read_imu_topic(path: &Path, topic: &str) -> Result<Vec<ImuSample>, GravityError> {
    let bag = Bag::open(path)?;
    let topic = bag.imu_topic(topic)?.clone();
    let mut samples: Vec<ImuSample> = Vec::with_capacity(topic.count.min(1 << 24) as usize);
    for (index, message) in bag.messages(&topic)?.enumerate() {
        let message = message?;
        let refused = |reason: String| {
            BagError::message(bag.path(), &topic.name, index, message.log_time_ns, reason)
        };
        let imu = decode_imu(&message.data, topic.encoding).map_err(|e| refused(e.to_string()))?;
        let Some(sample) = imu.sample() else {
            let reason = "linear acceleration or angular velocity is not finite (NaN or infinite)";
            return Err(refused(reason.into()).into());
        };
        if let Some(last) = samples.last().filter(|last| sample.t < last.t) {
            return Err(refused(format!(
                "header stamp {:.6} s is before the previous message's {:.6} s",
                sample.t, last.t
            ))
            .into());
        }
        samples.push(sample);
    }
    if samples.is_empty() {
        return Err(GravityError::NoImu(
            ImuSource::Topic {
                bag: path.to_path_buf(),
                topic: topic.name.clone(),
            }
            .label(),
        ));
    }
    Ok(samples)
}
