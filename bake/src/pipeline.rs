//! `kfmap bake`: a scan sequence with poses -> one `.kfmap` file. Keyframes are chosen
//! by the decider on the poses alone, then read, downsampled, indexed (tree +
//! covariances, in parallel) and written a chunk at a time, so memory stays bounded by
//! one chunk of keyframes plus the covisibility index, whatever the map's size. Beside
//! the map a bake can write the trajectory it used (TUM) and, when it built the poses,
//! its keyframe pose graph (g2o) and how each scan lies on its neighbours (CSV).

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::time::Instant;

use kfmap_geometry::KeyframeId;
use kfmap_geometry::cloud::{PointCloud, Twist, deskew};
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::imu::ImuSample;
use kfmap_geometry::io::{Trajectory, format_tum, write_atomic};
use kfmap_geometry::motion::DeskewMode;
use kfmap_geometry::registration::Fitness;
use kfmap_geometry::trajectory_error::{absolute_trajectory_error, rigid_alignment};
use kfmap_graph::pose_graph::{PoseEdge, PoseGraph, write_g2o};
use kfmap_graph::refine::{Consistency, RefineReport};
use kfmap_map::archive::{MapWriter, WriteSummary};
use kfmap_map::covis::CovisibilityGraph;
use kfmap_map::map::{Keyframe, KeyframeMapOptions};
use kfmap_map::tiles::TileGeometry;
use rayon::prelude::*;

use crate::config::BakeConfig;
use crate::dataset::{ScanPoses, scan_poses};
use crate::error::BakeError;
use crate::gravity::{BakeGravity, bake_gravity, check_overlap};
use crate::mapping::{
    OdometryOutcome, RefineClouds, ScanCheck, ScanVerdict, Stage, build_trajectory,
    refine_trajectory,
};
use crate::scan_range::ScanRange;
use crate::source::{ScanList, Source};
use crate::tiling::{TileSetSummary, TileSetWriter};

/// Where a bake reads from.
#[derive(Debug, Clone)]
pub struct BakeInput {
    /// The dataset: a folder (simulator output, or scans + a pose file), or a bag.
    pub source: Source,
    /// Pose file; default: the first of [`POSE_FILES`](crate::gravity::POSE_FILES) in a dataset folder.
    pub poses: Option<PathBuf>,
    /// Build the poses from the scans (odometry, loops, pose graph) even when a pose
    /// file exists; it then serves as ground truth for the ATE. Without any pose file
    /// the poses are always built.
    pub build_poses: bool,
    /// Only these scans of the dataset's scan list (sorted files, or the bag topic's
    /// clouds in log-time order); scans named
    /// by frame number keep their number's pose, others their place in the pose file.
    pub scans: ScanRange,
    /// Take the poses from the pose file (e.g. a trajectory an earlier bake built) and
    /// only refine them jointly (`[build.refine]`) before baking; the dataset's own pose
    /// file, when there is one besides, gives the ATE before and after.
    pub refine_only: bool,
}

impl BakeInput {
    /// Reads `dataset` (every scan, its own pose file, poses built only without one).
    pub fn dataset(dataset: impl Into<PathBuf>) -> Self {
        Self {
            source: Source::Folder(dataset.into()),
            poses: None,
            build_poses: false,
            scans: ScanRange::ALL,
            refine_only: false,
        }
    }

    /// The pose file the bake reads: `poses`, else the first of [`POSE_FILES`](crate::gravity::POSE_FILES) in a
    /// dataset folder; `None` when there is none.
    pub fn pose_file(&self) -> Option<PathBuf> {
        self.poses.clone().or_else(|| self.source.pose_file())
    }

    /// True when the bake builds the poses from the scans (no pose file, or
    /// `build_poses`), so that it has a pose graph.
    pub fn builds_poses(&self) -> bool {
        self.build_poses || self.pose_file().is_none()
    }
}

/// What a bake writes.
#[derive(Debug, Clone)]
pub struct BakeOutput {
    /// The map file (`.kfmap`).
    pub map: PathBuf,
    /// A TUM trajectory (`t x y z qx qy qz qw`, seconds and metres): one pose
    /// `T_map_scan` per baked scan, in the map frame of the written map (after any
    /// gravity levelling), stamped with the dataset's times (its scan index where it has
    /// none).
    pub trajectory: Option<PathBuf>,
    /// The keyframe pose graph as g2o (`VERTEX_SE3:QUAT` per graph keyframe, id = its
    /// scan index in the dataset, pose in the map frame of the written map;
    /// `EDGE_SE3:QUAT` per consecutive and loop edge with its information; `FIX` on the
    /// first). Only when the poses are built from the scans.
    pub graph: Option<PathBuf>,
    /// Bake a tile set into the directory `map` instead of one map file.
    pub tiles: Option<TileOutput>,
}

/// A tile set baked instead of one map file (`kfmap bake --tile-size`,
/// [`TileSetWriter`]).
#[derive(Debug, Clone, Copy)]
pub struct TileOutput {
    /// How the map is cut.
    pub geometry: TileGeometry,
    /// Also write the whole map, as [`merged_map_path`](crate::tiling::merged_map_path).
    pub keep_merged: bool,
}

/// The scan check's sidecar of a trajectory file: `FILE` + `.check.csv`, one line per
/// baked scan (`scan,t,verdict,inlier_ratio,rmse_m,shift_m,moved_m`), written beside
/// the trajectory when the poses are built.
pub fn scan_check_sidecar(trajectory: &Path) -> PathBuf {
    let mut name = trajectory.as_os_str().to_owned();
    name.push(".check.csv");
    PathBuf::from(name)
}

impl BakeOutput {
    /// The map file alone.
    pub fn map(path: impl Into<PathBuf>) -> Self {
        Self {
            map: path.into(),
            trajectory: None,
            graph: None,
            tiles: None,
        }
    }
}

/// Which part of a bake is running.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BakeStage {
    /// A bag's clouds read once for their header stamps.
    Indexing,
    /// Odometry over the scans (building poses).
    Odometry,
    /// Keyframe-to-keyframe edges (building poses).
    Keyframes,
    /// Loop detection and pose-graph optimization (building poses).
    Optimizing,
    /// Every scan checked against its neighbours (building poses).
    Checking,
    /// Every pose refined jointly against the planes the scans share (building poses;
    /// done/total count solver steps, total is an upper bound).
    Refining,
    /// Keyframes indexed and written.
    Writing,
    /// A tile set's tiles finished (grids cut, indexes, Autoware clouds).
    Tiling,
}

/// Progress of a bake.
#[derive(Debug, Clone, Copy)]
pub struct BakeProgress {
    /// The stage.
    pub stage: BakeStage,
    /// Items of the stage done (scans, keyframes).
    pub done: usize,
    /// Items of the stage in total.
    pub total: usize,
    /// Points written so far.
    pub points_done: u64,
}

/// What building the poses from the scans did.
#[derive(Debug, Clone)]
pub struct MappingSummary {
    /// Graph keyframes.
    pub keyframes: usize,
    /// Loop candidates examined.
    pub loops_found: usize,
    /// Pose-graph error before and after optimization.
    pub graph_error: (f64, f64),
    /// The optimized keyframe pose graph: vertex id = the keyframe's scan index in the
    /// dataset, poses as in [`MappingSummary::poses`]; consecutive and loop edges.
    pub graph: PoseGraph,
    /// Every baked scan's built pose (`T_map_scan`, map = the first baked scan's frame,
    /// before any gravity levelling).
    pub poses: Vec<Pose>,
    /// Keyframe ATE against the dataset's pose file, metres, when there is one.
    pub ate: Option<f64>,
    /// The pose file's frame seen from the built poses' (`T_built_file`: the rigid fit
    /// of the file's positions onto the built ones), when there is a pose file.
    pub built_from_file: Option<Pose>,
    /// ATE of every scan's pose against the pose file, metres.
    pub ate_scans: Option<f64>,
    /// The same before the joint refinement.
    pub ate_scans_before_refine: Option<f64>,
    /// The joint refinement (`None`: disabled in `[build.refine]`).
    pub refine: Option<RefineReport>,
    /// The poses were given and only refined (`--refine-only`): no odometry, loops,
    /// graph or scan check ran.
    pub refined_only: bool,
    /// The map consistency at the pose file's poses, on the same scans and keyframes as
    /// the refinement's figures (`None`: no pose file, or no refinement).
    pub reference_consistency: Option<Consistency>,
    /// Every loop candidate verified, in scan indices, with its fitness.
    pub loop_checks: Vec<LoopSummary>,
    /// Scans odometry found only after retrying wider hypotheses.
    pub recovered_scans: Vec<usize>,
    /// Scans odometry registered well by no hypothesis (the scan check judges their
    /// final pose).
    pub odometry_poor_scans: Vec<usize>,
    /// Every baked scan's check against its neighbours, in order.
    pub checks: Vec<ScanCheck>,
    /// Scans that did not fit their neighbours and were re-registered onto them.
    pub reregistered_scans: Vec<usize>,
    /// Scans that fit their neighbours neither as built nor re-registered: their pose
    /// may be off.
    pub poor_scans: Vec<usize>,
    /// The same for odometry alone.
    pub ate_odometry: Option<f64>,
    /// The gyro bias odometry learned, IMU frame, rad/s (`None`: no IMU log used).
    pub gyro_bias: Option<[f64; 3]>,
    /// How odometry deskewed the scans (`auto` settled: `azimuth` or `per-point`).
    pub deskew: DeskewMode,
    /// The sweep duration azimuth times spanned, seconds (one scan interval when the
    /// scans have no timestamps); `None` unless `deskew` is `azimuth`.
    pub sweep_seconds: Option<f64>,
}

impl MappingSummary {
    /// Loops verified and added to the graph.
    pub fn loops_accepted(&self) -> usize {
        self.loop_checks.iter().filter(|c| c.accepted).count()
    }
}

/// One verified loop candidate, in scan indices.
#[derive(Debug, Clone, Copy)]
pub struct LoopSummary {
    /// The older scan (a graph keyframe).
    pub older_scan: usize,
    /// The newer scan (a graph keyframe).
    pub newer_scan: usize,
    /// How the newer keyframe lay on the older one's neighbourhood (`None`: the
    /// registration could not run).
    pub fitness: Option<Fitness>,
    /// Became a graph edge.
    pub accepted: bool,
}

/// What a bake produced.
#[derive(Debug, Clone)]
pub struct BakeReport {
    /// Scans in the dataset.
    pub dataset_scans: usize,
    /// The scans baked (indices in the dataset's sorted scan list).
    pub scans: Range<usize>,
    /// The input frame (the pose file's; with built poses, the pose file they are
    /// measured against) seen from the written map's: `T_map_input`, also stored in
    /// the map for clients comparing with ground truth.
    pub map_from_input: Pose,
    /// Pose building, when the poses came from the scans.
    pub mapping: Option<MappingSummary>,
    /// The gravity stage, when the dataset has an IMU log.
    pub gravity: Option<BakeGravity>,
    /// The file written (a tile set's: every keyframe once, the bytes and place grids of
    /// all its tiles).
    pub written: WriteSummary,
    /// The tile set, when one was baked.
    pub tiles: Option<TileSetSummary>,
    /// Wall time, seconds.
    pub seconds: f64,
}

impl BakeReport {
    /// Points baked per second.
    pub fn points_per_second(&self) -> f64 {
        self.written.points as f64 / self.seconds.max(1e-9)
    }
}

/// Poses built from `scans` (dataset indices from `first`); `truth` (a pose file, the
/// same scans) gives stamps and the ATE.
fn build_poses(
    scans: &ScanList,
    first: usize,
    config: &BakeConfig,
    truth: Option<&ScanPoses>,
    imu: Vec<ImuSample>,
    progress: &mut impl FnMut(BakeProgress),
) -> Result<(ScanPoses, MappingSummary), BakeError> {
    let report = |stage, done, total| BakeProgress {
        stage,
        done,
        total,
        points_done: 0,
    };
    // Without a pose file or header stamps the scans are taken to be evenly spaced
    // (the motion model then predicts per scan instead of per second).
    let stamps: Vec<f64> = match (truth, scans.stamps()) {
        (Some(t), _) => t.stamps.clone(),
        (None, Some(header)) => header.to_vec(),
        (None, None) => (first..first + scans.len()).map(|i| i as f64).collect(),
    };
    let stamped = truth.is_some_and(|t| t.stamped) || scans.stamps().is_some();
    let mut build = config.build;
    if !stamped {
        // The stamps count scans: a sweep is taken to last one scan interval.
        build.odometry.sweep.seconds = 1.0;
    }
    let built = build_trajectory::<BakeError>(
        &stamps,
        imu,
        |i| scans.load_raw(i, config),
        &build,
        |stage| {
            progress(match stage {
                Stage::Odometry(d, t) => report(BakeStage::Odometry, d, t),
                Stage::Keyframes(d, t) => report(BakeStage::Keyframes, d, t),
                Stage::Optimizing => report(BakeStage::Optimizing, 0, 1),
                Stage::Checking => report(BakeStage::Checking, 0, 1),
                Stage::Refining(d, t) => report(BakeStage::Refining, d, t),
            })
        },
    )?;
    let at_keyframes =
        |poses: &[Pose]| -> Vec<Pose> { built.keyframe_scans.iter().map(|&i| poses[i]).collect() };
    let ate = |poses: &[Pose]| {
        truth.map(|t| absolute_trajectory_error(&at_keyframes(poses), &at_keyframes(&t.poses)))
    };
    // A keyframe's vertex is named by its scan's index in the dataset.
    let vertex = |k: u64| (first + built.keyframe_scans[k as usize]) as u64;
    let mut graph = PoseGraph::default();
    for &scan in &built.keyframe_scans {
        graph.add_pose((first + scan) as u64, built.poses[scan])?;
    }
    for edge in &built.edges {
        graph.add_edge(PoseEdge {
            from: vertex(edge.from),
            to: vertex(edge.to),
            ..*edge
        })?;
    }
    let summary = MappingSummary {
        keyframes: built.keyframe_scans.len(),
        loops_found: built.loops_found,
        graph_error: (built.graph.initial_error, built.graph.final_error),
        graph,
        ate: ate(&built.poses),
        built_from_file: truth.map(|t| rigid_alignment(&t.poses, &built.poses)),
        ate_scans: truth.map(|t| absolute_trajectory_error(&built.poses, &t.poses)),
        ate_scans_before_refine: truth
            .map(|t| absolute_trajectory_error(&built.before_refine, &t.poses)),
        refine: built.refine.clone(),
        refined_only: false,
        reference_consistency: truth
            .zip(built.refine_clouds.as_ref())
            .map(|(t, clouds)| clouds.consistency_at(&t.poses, &built.keyframe_scans)),
        loop_checks: built
            .loop_checks
            .iter()
            .map(|c| LoopSummary {
                older_scan: first + built.keyframe_scans[c.older],
                newer_scan: first + built.keyframe_scans[c.newer],
                fitness: c.verdict.map(|v| v.fitness),
                accepted: c.verdict.is_some_and(|v| v.accepted),
            })
            .collect(),
        recovered_scans: scans_where(&built.outcomes, OdometryOutcome::Recovered, first),
        odometry_poor_scans: scans_where(&built.outcomes, OdometryOutcome::Poor, first),
        reregistered_scans: checked(&built.checks, ScanVerdict::Reregistered, first),
        poor_scans: checked(&built.checks, ScanVerdict::Poor, first),
        checks: built.checks.clone(),
        ate_odometry: ate(&built.odometry),
        poses: built.poses.clone(),
        gyro_bias: built.gyro_bias.map(Into::into),
        deskew: build.odometry.deskew,
        sweep_seconds: (build.odometry.deskew == DeskewMode::Azimuth)
            .then_some(build.odometry.sweep.seconds),
    };
    let poses = ScanPoses {
        poses: built.poses,
        stamps,
        stamped,
    };
    Ok((poses, summary))
}

/// The dataset's IMU log for the odometry's motion model: read when the gyro is enabled
/// and the scans have timestamps (from the pose file, or a bag's header stamps) to
/// place it on; empty otherwise.
fn odometry_imu(
    source: &Source,
    config: &BakeConfig,
    stamps: Option<&[f64]>,
) -> Result<Vec<ImuSample>, BakeError> {
    let imu = source.imu().filter(|_| config.build.odometry.gyro.enabled);
    let (Some(imu), Some(stamps)) = (imu, stamps) else {
        return Ok(Vec::new());
    };
    let samples = imu.read()?;
    check_overlap(&imu.label(), &samples, stamps)?;
    Ok(samples)
}

/// Dataset indices of the scans (the first at `first`) whose odometry outcome was `which`.
fn scans_where(outcomes: &[OdometryOutcome], which: OdometryOutcome, first: usize) -> Vec<usize> {
    (0..outcomes.len())
        .filter(|&i| outcomes[i] == which)
        .map(|i| first + i)
        .collect()
}

/// Dataset indices of the scans (the first at `first`) the scan check found `which`.
fn checked(checks: &[ScanCheck], which: ScanVerdict, first: usize) -> Vec<usize> {
    (0..checks.len())
        .filter(|&i| checks[i].verdict == which)
        .map(|i| first + i)
        .collect()
}

/// The sensor's twist at scan `i` from its poses and times: towards the next scan (the
/// previous one for the last), for deskewing scans that carry per-point times.
fn scan_twist(poses: &[Pose], stamps: &[f64], i: usize) -> Option<Twist> {
    let (a, b) = if i + 1 < poses.len() {
        (i, i + 1)
    } else {
        (i.checked_sub(1)?, i)
    };
    Twist::between(&poses[a], &poses[b], stamps[b] - stamps[a])
}

/// `config` with `[build.odometry] deskew = "auto"` settled for `scans`: `azimuth` when
/// every scan is a KITTI velodyne `.bin` (x y z intensity: raw sweeps of a spinning
/// sensor, stored without per-point times), else `per-point` (a bag's clouds too:
/// drivers write per-point times).
pub fn settle_deskew(config: &BakeConfig, scans: &ScanList) -> BakeConfig {
    let mut settled = config.clone();
    let odometry = &mut settled.build.odometry;
    odometry.deskew = odometry.deskew.resolve(scans.all_kitti_bin(config));
    settled
}

/// Reads and filters scan `i` of `scans`; a scan without per-point times gets them from
/// its azimuths ([build.odometry] sweep) when `[build.odometry] deskew` is `azimuth`
/// (after [`settle_deskew`], also `auto` on raw sweeps).
pub fn load_timed(
    scans: &ScanList,
    i: usize,
    config: &BakeConfig,
) -> Result<PointCloud, BakeError> {
    let mut raw = scans.load_raw(i, config)?;
    let odometry = &config.build.odometry;
    if odometry.deskew == DeskewMode::Azimuth {
        odometry.sweep.time_scan(&mut raw);
    }
    Ok(raw)
}

/// Reads and filters scan `i` of `scans` and deskews it by `twist` as `[build.odometry]
/// deskew` says (azimuth times first for raw sweeps without them).
fn timed_and_deskewed(
    scans: &ScanList,
    i: usize,
    config: &BakeConfig,
    twist: Option<Twist>,
) -> Result<PointCloud, BakeError> {
    let mut raw = load_timed(scans, i, config)?;
    let odometry = &config.build.odometry;
    if let Some(twist) = twist.filter(|_| odometry.deskew.uses_point_times()) {
        deskew(&mut raw, &twist, 0.0).map_err(|e| BakeError::Scan {
            path: scans.name(i).to_path_buf(),
            message: e.to_string(),
        })?;
    }
    Ok(raw)
}

/// Reads, filters and downsamples scan `i` of `scans`, taken at `pose` (map frame): on
/// the map's voxel grid, with each point's raw count, when keyframes are fused.
fn load_scan(
    scans: &ScanList,
    i: usize,
    config: &BakeConfig,
    pose: &Pose,
    twist: Option<Twist>,
) -> Result<(PointCloud, Option<Vec<u32>>), BakeError> {
    let fused = config.map.fuse_overlapping_keyframes;
    let path = scans.name(i);
    let path = path.as_path();
    let raw = timed_and_deskewed(scans, i, config, twist)?;
    let (cloud, weights) = raw
        .into_keyframe_points(config.keyframes.voxel_size, fused.then_some(pose))
        .map_err(|e| BakeError::Scan {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
    if cloud.is_empty() {
        return Err(BakeError::Scan {
            path: path.to_path_buf(),
            message: "no valid points left after filtering".into(),
        });
    }
    Ok((cloud, weights))
}

/// Bakes `input` into `output` with `config`; `progress` is called after each keyframe.
/// Runs on the current rayon pool. The trajectory and graph files are written (each
/// atomically) after the map is complete.
pub fn bake(
    input: &BakeInput,
    config: &BakeConfig,
    output: &BakeOutput,
    mut progress: impl FnMut(BakeProgress) + Send,
) -> Result<BakeReport, BakeError> {
    let started = Instant::now();
    let all_scans = input.source.scans(&mut |done, total| {
        progress(BakeProgress {
            stage: BakeStage::Indexing,
            done,
            total,
            points_done: 0,
        })
    })?;
    let range = input.scans.within(all_scans.len())?;
    let scans = &all_scans.select(range.clone());
    let config = &settle_deskew(config, scans);
    let (scan_poses, mapping) = poses_of_scans(
        input,
        config,
        output,
        &all_scans,
        range.clone(),
        &mut progress,
    )?;
    let ScanPoses {
        mut poses,
        stamps,
        stamped,
    } = scan_poses;
    let chosen = choose_keyframes(config, &poses);
    let keyframe_scans: Vec<(KeyframeId, usize)> = chosen
        .iter()
        .enumerate()
        .map(|(id, &scan)| (id as KeyframeId, scan))
        .collect();
    let mut gravity = bake_gravity(
        input.source.imu().as_ref(),
        &config.gravity,
        &poses,
        stamped.then_some(&stamps),
        &keyframe_scans,
    )?;
    let level = level_by_gravity(config, gravity.as_mut(), &mut poses);
    // The input frame is the pose file's: given, or the reference of built poses.
    let map_from_input = level
        * mapping
            .as_ref()
            .and_then(|m| m.built_from_file)
            .unwrap_or_else(Pose::identity);
    let sequence = Sequence {
        scans,
        poses: &poses,
        stamps: &stamps,
        stamped,
    };
    let (written, tiles) = write_map(
        &sequence,
        &chosen,
        config,
        output,
        &map_from_input,
        gravity.as_ref(),
        &mut progress,
    )?;
    let first = range.start;
    write_trajectory_and_graph(output, poses, stamps, mapping.as_ref(), &level, first)?;
    Ok(BakeReport {
        dataset_scans: all_scans.len(),
        scans: range,
        map_from_input,
        mapping,
        gravity,
        written,
        tiles,
        seconds: started.elapsed().as_secs_f64(),
    })
}

/// The pose of every scan in `range`: from the pose file, or built from the scans
/// (odometry, loops, pose graph) with the pose file, if any, as ground truth. Poses are
/// matched against the whole dataset, so a range keeps each scan's pose.
fn poses_of_scans(
    input: &BakeInput,
    config: &BakeConfig,
    output: &BakeOutput,
    all_scans: &ScanList,
    range: Range<usize>,
    progress: &mut impl FnMut(BakeProgress),
) -> Result<(ScanPoses, Option<MappingSummary>), BakeError> {
    let pose_file = input.pose_file();
    if input.refine_only && (input.build_poses || pose_file.is_none()) {
        return Err(BakeError::RefineOnly(
            "it refines given poses: pass them with --poses FILE (e.g. an earlier bake's \
             --trajectory-out), without --build-poses"
                .into(),
        ));
    }
    match pose_file {
        Some(path) if !input.build_poses => {
            if output.graph.is_some() {
                return Err(BakeError::NoPoseGraph(path));
            }
            let given = scan_poses(&path, all_scans)?.select(range.clone());
            if !input.refine_only {
                return Ok((given, None));
            }
            // The dataset's own pose file, when --poses named another, is the reference.
            let truth = input
                .source
                .pose_file()
                .filter(|own| *own != path)
                .map(|own| scan_poses(&own, all_scans).map(|t| t.select(range.clone())))
                .transpose()?;
            let scans = all_scans.select(range.clone());
            let (refined, summary) =
                refine_given_poses(&scans, config, given, truth.as_ref(), progress)?;
            Ok((refined, Some(summary)))
        }
        truth => {
            let truth = truth
                .map(|p| scan_poses(&p, all_scans).map(|t| t.select(range.clone())))
                .transpose()?;
            let scans = all_scans.select(range.clone());
            let stamps = match &truth {
                Some(t) => t.stamped.then_some(&t.stamps[..]),
                None => scans.stamps(),
            };
            let imu = odometry_imu(&input.source, config, stamps)?;
            let (built, summary) =
                build_poses(&scans, range.start, config, truth.as_ref(), imu, progress)?;
            Ok((built, Some(summary)))
        }
    }
}

/// `kfmap bake --refine-only`: the given poses refined jointly on the scans (read and
/// deskewed as a bake at given poses reads them, on the refinement's voxel grid), with
/// the figures a build reports where they apply (no odometry, loops, graph or check).
fn refine_given_poses(
    scans: &ScanList,
    config: &BakeConfig,
    given: ScanPoses,
    truth: Option<&ScanPoses>,
    progress: &mut impl FnMut(BakeProgress),
) -> Result<(ScanPoses, MappingSummary), BakeError> {
    let params = config.build.refine;
    if !params.enabled {
        return Err(BakeError::RefineOnly(
            "[build.refine] enabled = false in the config: nothing to do".into(),
        ));
    }
    let count = scans.len();
    let clouds = (0..count)
        .into_par_iter()
        .map(|i| {
            let twist = given
                .stamped
                .then(|| scan_twist(&given.poses, &given.stamps, i))
                .flatten();
            let raw = timed_and_deskewed(scans, i, config, twist)?;
            let path = scans.name(i);
            raw.voxel_downsample(params.point_voxel)
                .map(|c| c.points)
                .map_err(|e| BakeError::Scan {
                    path: path.to_path_buf(),
                    message: e.to_string(),
                })
        })
        .collect::<Result<Vec<_>, BakeError>>()?;
    let clouds = RefineClouds::new(clouds, vec![Pose::identity(); count], &params);
    let keyframes = choose_keyframes(config, &given.poses);
    let mut poses = given.poses.clone();
    let report = refine_trajectory(
        &clouds,
        &mut poses,
        &given.poses,
        &keyframes,
        &params,
        |d, t| {
            progress(BakeProgress {
                stage: BakeStage::Refining,
                done: d,
                total: t,
                points_done: 0,
            })
        },
    );
    let at_keyframes = |p: &[Pose]| -> Vec<Pose> { keyframes.iter().map(|&i| p[i]).collect() };
    let ate = |p: &[Pose]| {
        truth.map(|t| absolute_trajectory_error(&at_keyframes(p), &at_keyframes(&t.poses)))
    };
    let summary = MappingSummary {
        keyframes: keyframes.len(),
        loops_found: 0,
        graph_error: (0.0, 0.0),
        graph: PoseGraph::default(),
        ate: ate(&poses),
        built_from_file: truth.map(|t| rigid_alignment(&t.poses, &poses)),
        ate_scans: truth.map(|t| absolute_trajectory_error(&poses, &t.poses)),
        ate_scans_before_refine: truth.map(|t| absolute_trajectory_error(&given.poses, &t.poses)),
        reference_consistency: truth.map(|t| clouds.consistency_at(&t.poses, &keyframes)),
        refine: Some(report),
        refined_only: true,
        loop_checks: Vec::new(),
        recovered_scans: Vec::new(),
        odometry_poor_scans: Vec::new(),
        checks: vec![ScanCheck::UNCHECKED; count],
        reregistered_scans: Vec::new(),
        poor_scans: Vec::new(),
        ate_odometry: None,
        poses: poses.clone(),
        gyro_bias: None,
        deskew: config.build.odometry.deskew,
        sweep_seconds: None,
    };
    Ok((
        ScanPoses {
            poses,
            stamps: given.stamps,
            stamped: given.stamped,
        },
        summary,
    ))
}

/// The scans that become keyframes: the decider on the poses alone.
fn choose_keyframes(config: &BakeConfig, poses: &[Pose]) -> Vec<usize> {
    let decider = config.keyframes.decider();
    let mut chosen: Vec<usize> = Vec::new();
    for (i, pose) in poses.iter().enumerate() {
        if decider.should_create(chosen.iter().map(|&c| &poses[c]), pose) {
            chosen.push(i);
        }
    }
    chosen
}

/// Levels the map by the IMU's gravity when `[map] align-gravity` asks and the pool
/// gives a correction: every pose is rotated about the map origin (relative poses and
/// graph edges unchanged). Returns the levelling applied (identity when none).
fn level_by_gravity(
    config: &BakeConfig,
    gravity: Option<&mut BakeGravity>,
    poses: &mut [Pose],
) -> Pose {
    let Some(g) = gravity.filter(|_| config.map.align_gravity) else {
        return Pose::identity();
    };
    let Some(c) = &g.correction else {
        return Pose::identity();
    };
    let level = Pose::from_parts(Default::default(), c.rotation.into());
    poses.iter_mut().for_each(|p| *p = level * *p);
    g.applied = true;
    level
}

/// The scans being baked with their (map-frame) poses and times.
struct Sequence<'a> {
    scans: &'a ScanList,
    poses: &'a [Pose],
    stamps: &'a [f64],
    /// The times come from the pose file (else they are scan numbers, and no scan is
    /// deskewed from them).
    stamped: bool,
}

/// Where a bake's keyframes go: one map file, or a tile set's files.
enum KeyframeSink {
    Map(Box<MapWriter>),
    Tiles(Box<TileSetWriter>),
}

impl KeyframeSink {
    fn write_keyframes(&mut self, keyframes: &[Keyframe]) -> Result<(), BakeError> {
        match self {
            Self::Map(writer) => Ok(writer.write_keyframes(keyframes)?),
            Self::Tiles(writer) => writer.write_keyframes(keyframes),
        }
    }
}

/// Writes the map file (or tile set): the `chosen` scans read, downsampled and indexed
/// into keyframes a chunk at a time (in parallel within a chunk), the covisibility
/// graph and the gravity pool.
fn write_map(
    sequence: &Sequence,
    chosen: &[usize],
    config: &BakeConfig,
    output: &BakeOutput,
    map_from_input: &Pose,
    gravity: Option<&BakeGravity>,
    progress: &mut (impl FnMut(BakeProgress) + Send),
) -> Result<(WriteSummary, Option<TileSetSummary>), BakeError> {
    let Sequence {
        scans,
        poses,
        stamps,
        stamped,
    } = *sequence;
    let options: KeyframeMapOptions = config.map_options();
    let mut sink = match output.tiles {
        None => {
            let mut writer = MapWriter::create(&output.map, &options)?;
            writer.set_map_from_input(map_from_input);
            KeyframeSink::Map(Box::new(writer))
        }
        Some(tiles) => KeyframeSink::Tiles(Box::new(TileSetWriter::create(
            &output.map,
            tiles.geometry,
            &options,
            map_from_input,
            tiles.keep_merged,
        )?)),
    };
    let mut covis = CovisibilityGraph::new(options.covisibility);
    let chunk = 2 * rayon::current_num_threads();
    let mut done = BakeProgress {
        stage: BakeStage::Writing,
        done: 0,
        total: chosen.len(),
        points_done: 0,
    };
    let build = |chunk_index: usize, batch: &[usize]| -> Result<Vec<Keyframe>, BakeError> {
        batch
            .par_iter()
            .enumerate()
            .map(|(j, &scan)| {
                let twist = stamped.then(|| scan_twist(poses, stamps, scan)).flatten();
                let (cloud, weights) = load_scan(scans, scan, config, &poses[scan], twist)?;
                let id = (chunk_index * chunk + j) as u64;
                let (pose, stamp) = (poses[scan], stamps[scan]);
                Keyframe::build_weighted(id, pose, stamp, cloud, weights, &options.covariance)
                    .map_err(|e| BakeError::Scan {
                        path: scans.name(scan),
                        message: e.to_string(),
                    })
            })
            .collect()
    };
    let mut write = |keyframes: &[Keyframe]| -> Result<(), BakeError> {
        sink.write_keyframes(keyframes)?;
        for k in keyframes {
            covis.set_keyframe(k.id, k.map_points()?);
            done.done += 1;
            done.points_done += k.len() as u64;
            progress(done);
        }
        Ok(())
    };
    // A chunk is written while the next one is built: appending and the covisibility
    // are sequential, and would leave the other cores idle.
    let mut built: Option<Vec<Keyframe>> = None;
    for (chunk_index, batch) in chosen.chunks(chunk).enumerate() {
        let (next, wrote) = rayon::join(
            || build(chunk_index, batch),
            || built.take().map_or(Ok(()), |k| write(&k)),
        );
        wrote?;
        built = Some(next?);
    }
    if let Some(keyframes) = built {
        write(&keyframes)?;
    }
    let pool = gravity.map_or(&[][..], |g| &g.pool[..]);
    let next_id = chosen.len() as u64;
    match sink {
        KeyframeSink::Map(writer) => Ok((writer.finish(next_id, &covis.snapshot(), pool)?, None)),
        KeyframeSink::Tiles(writer) => {
            let tiles = writer.finish(next_id, &covis.snapshot(), pool, |done, total| {
                progress(BakeProgress {
                    stage: BakeStage::Tiling,
                    done,
                    total,
                    points_done: 0,
                })
            })?;
            let written = WriteSummary {
                keyframes: chosen.len(),
                points: done.points_done,
                bytes: tiles.map_bytes,
                place_bytes: tiles.place_bytes,
            };
            Ok((written, Some(tiles)))
        }
    }
}

/// The files beside the map, each written atomically: the trajectory used (TUM) and,
/// when the poses were built, its scan check ([`scan_check_sidecar`]) and the keyframe
/// pose graph (g2o), levelled like the map. `first`: the first baked scan's index.
fn write_trajectory_and_graph(
    output: &BakeOutput,
    poses: Vec<Pose>,
    stamps: Vec<f64>,
    mapping: Option<&MappingSummary>,
    level: &Pose,
    first: usize,
) -> Result<(), BakeError> {
    if let Some(path) = &output.trajectory {
        if let Some(m) = mapping {
            let csv = format_scan_checks(&m.checks, &stamps, first);
            write_atomic(&scan_check_sidecar(path), csv.as_bytes())?;
        }
        let trajectory = Trajectory {
            stamps: Some(stamps),
            poses,
        };
        write_atomic(path, format_tum(&trajectory).as_bytes())?;
    }
    if let (Some(path), Some(m)) = (&output.graph, mapping) {
        let mut graph = m.graph.clone();
        for &id in m.graph.ids() {
            let levelled = level * m.graph.pose(id).expect("a listed vertex");
            graph.set_pose(id, levelled)?;
        }
        write_g2o(path, &graph, m.graph.ids().first().copied())?;
    }
    Ok(())
}

/// The scan check as CSV: a header, then per scan its dataset index, time, verdict,
/// fitness at its final pose (empty when unchecked), how far its local map pulled it
/// and how far the check moved it (metres).
fn format_scan_checks(checks: &[ScanCheck], stamps: &[f64], first: usize) -> String {
    let mut csv = String::from("scan,t,verdict,inlier_ratio,rmse_m,shift_m,moved_m\n");
    let blank =
        |v: Option<f64>, digits: usize| v.map_or(String::new(), |v| format!("{v:.digits$}"));
    for (i, (c, t)) in checks.iter().zip(stamps).enumerate() {
        csv.push_str(&format!(
            "{},{t:.6},{},{},{},{},{:.3}\n",
            first + i,
            c.verdict.name(),
            blank(c.fitness.map(|f| f.inlier_ratio), 3),
            blank(c.fitness.map(|f| f.rmse), 3),
            blank(c.shift, 3),
            c.moved
        ));
    }
    csv
}
