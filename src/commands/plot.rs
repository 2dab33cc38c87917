//! `kfmap plot`: pictures of a map, of a trajectory against its reference, and of a
//! recorded localization run (drawn by the kfmap-plot crate).

use std::path::PathBuf;

use kfmap_plot::{
    MapPlotOptions, RunTopics, TrajectoryOptions, TrajectoryPlotInputs, render_map_summary,
    render_run_summary, render_trajectory_summary,
};

/// Draw a baked map, a trajectory against its reference, or a recorded localization run,
/// as a PNG or SVG picture (the extension of --out decides).
///
/// Map (kfmap plot MAP.kfmap --out FILE): the map seen from above (x right, y up,
/// metres, equal scale on both axes). Points are coloured by height z in the map
/// frame, the colours spanning the 2nd to 98th percentile of the drawn heights (the
/// colour bar gives the range). Every keyframe is an arrow at its position pointing
/// along its x axis. Covisibility edges (from the map file) join keyframes that see the
/// same voxels: faint grey, each keyframe's 3 strongest (most shared voxels; in open
/// areas every keyframe sees every other one), and magenta all those of a revisit: two
/// keyframes near each other (within 3 median keyframe steps or 5 m) with a keyframe
/// path between them longer than twice their distance plus 10 m (the robot drove away
/// and came back: a loop closure or a later pass; the map file keeps no other record
/// of loops). The legend and the printed line give the totals. --no-edges leaves the
/// edges out.
///
/// At most 300 000 points are drawn in a PNG (60 000 in an SVG): every n-th point of
/// the map, the same ones every time, the highest last (as seen from above). The view
/// spans every keyframe and the 0.5th to 99.5th percentile of the points' x and y, so
/// a few spurious far returns do not shrink the map to a dot; points outside it are
/// not drawn.
///
/// Trajectory (kfmap plot --trajectory EST --ground-truth REF --out FILE): two panels.
/// Top: the reference from above as a grey line, the estimate over it coloured by each
/// pose's position error (metres; colours saturate at the 98th percentile, the colour
/// bar gives the range). Bottom: the position error against time (seconds since the
/// first estimated pose). Both files are TUM (t x y z qx qy qz qw), taken to be in the
/// same frame; --align first moves the estimate rigidly onto the reference (rotation
/// and translation, no scale: the least-squares fit of the matched positions, as the
/// ATE does) and prints the motion. Each estimated pose is compared with the reference
/// pose nearest in time, when within --max-dt-ms (default 5 ms); poses without one are
/// left out and counted, and no match at all is an error. --scan-log takes the output of
/// `kfmap localize --json-lines` (one JSON object per scan; the summary line is skipped)
/// and marks its lost or failed scans with red crosses and its degraded scans with
/// orange triangles in both panels.
///
/// Recorded run (kfmap plot --bag RUN.mcap --out FILE): what RViz shows of a localizer,
/// from a bag of its outputs (e.g. `ros2 bag record /kfmap/pose /kfmap/map_cloud
/// /diagnostics` beside kfmap-ros2; MCAP, rosbag2 sqlite3 or ROS 1). Top: the last map
/// cloud on --map-cloud-topic (the latched, thinned map) from above on a dark ground,
/// coloured by height; every pose of --pose-topic
/// (geometry_msgs/PoseWithCovarianceStamped) as an arrow along its x axis, coloured by
/// the health the diagnostics of the same stamp give (kfmap-ros2's `status` value: ok
/// cyan, degraded orange; grey when no diagnostics match), joined by the path, with the
/// 3-sigma ellipse of its x-y covariance at true scale; scans whose diagnostics came
/// with no pose (lost, no server, a bad cloud) as red crosses where the last pose was.
/// Bottom: each pose's horizontal standard deviation (the major axis of its x-y
/// covariance) over time. The topics default to kfmap-ros2's: /kfmap/pose,
/// /kfmap/map_cloud and /diagnostics; a defaulted map cloud or diagnostics topic the bag
/// lacks is left out (and said), a named one is an error.
///
/// Prints one line: the file written and what it shows. The picture is written under a
/// temporary name beside --out and renamed when complete. Exit code 2 with a message for
/// a missing or unreadable input, an empty trajectory, an unknown extension or a bad
/// --size.
///
/// Examples:
///   kfmap plot campus.kfmap --out campus.png
///   kfmap plot campus.kfmap --out campus.svg --no-edges --size 2400x1800
///   kfmap localize --map-name site --dataset runs/site-2 --out run.tum --json-lines > run.jsonl
///   kfmap plot --trajectory run.tum --ground-truth runs/site-2/poses_gt.txt \
///       --scan-log run.jsonl --out run.png
///   kfmap plot --trajectory odometry.tum --ground-truth gt.tum --align --out drift.svg
///   kfmap plot --bag run.mcap --out run.png
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
#[command(group(clap::ArgGroup::new("input").required(true).args(["map", "trajectory", "bag"])))]
pub struct Args {
    /// The map to draw (.kfmap).
    map: Option<PathBuf>,
    /// Picture to write: FILE.png or FILE.svg.
    #[arg(long)]
    out: PathBuf,
    /// Picture size in pixels, WIDTHxHEIGHT.
    #[arg(long, value_name = "WxH", default_value = "1600x1200", value_parser = parse_size)]
    size: Size,
    /// Map: leave out the covisibility edges.
    #[arg(long, conflicts_with_all = ["trajectory", "bag"])]
    no_edges: bool,
    /// A recorded localization run to draw: a bag (.mcap, .db3, rosbag2 folder, ROS 1
    /// .bag) with the localizer's poses, diagnostics and map cloud.
    #[arg(long, value_name = "RUN", conflicts_with_all = ["map", "trajectory"])]
    bag: Option<PathBuf>,
    /// Recorded run: the geometry_msgs/PoseWithCovarianceStamped topic [default: /kfmap/pose].
    #[arg(long, value_name = "TOPIC", requires = "bag")]
    pose_topic: Option<String>,
    /// Recorded run: the map cloud topic (sensor_msgs/PointCloud2)
    /// [default: /kfmap/map_cloud when present].
    #[arg(long, value_name = "TOPIC", requires = "bag")]
    map_cloud_topic: Option<String>,
    /// Recorded run: the diagnostic_msgs/DiagnosticArray topic
    /// [default: /diagnostics when present].
    #[arg(long, value_name = "TOPIC", requires = "bag")]
    diagnostics_topic: Option<String>,
    /// Estimated trajectory to draw (TUM: t x y z qx qy qz qw).
    #[arg(long, value_name = "EST.tum", requires = "ground_truth")]
    trajectory: Option<PathBuf>,
    /// Reference trajectory the estimate is compared with (TUM, same frame).
    #[arg(
        long,
        visible_alias = "reference",
        value_name = "REF.tum",
        requires = "trajectory"
    )]
    ground_truth: Option<PathBuf>,
    /// `kfmap localize --json-lines` output: marks its lost, failed and degraded scans.
    #[arg(long, value_name = "LOG.jsonl", requires = "trajectory")]
    scan_log: Option<PathBuf>,
    /// Title of the trajectory picture (default: the two file names).
    #[arg(long, requires = "trajectory")]
    title: Option<String>,
    /// Largest stamp difference between an estimated pose and its reference pose, ms.
    #[arg(
        long,
        value_name = "MS",
        default_value_t = kfmap_plot::DEFAULT_MAX_DT * 1e3,
        requires = "trajectory"
    )]
    max_dt_ms: f64,
    /// Move the estimate rigidly (rotation and translation, no scale) onto the reference
    /// first: the least-squares fit of the matched positions (Umeyama/Horn, as the ATE).
    #[arg(long, requires = "trajectory")]
    align: bool,
}

/// A picture size, pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Size {
    width: u32,
    height: u32,
}

fn parse_size(s: &str) -> Result<Size, String> {
    let bad = || {
        format!(
            "'{s}' is not a size: expected WIDTHxHEIGHT in pixels, e.g. 1600x1200, each side {}..={}",
            kfmap_plot::MIN_SIDE,
            kfmap_plot::MAX_SIDE
        )
    };
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    let width: u32 = w.trim().parse().map_err(|_| bad())?;
    let height: u32 = h.trim().parse().map_err(|_| bad())?;
    kfmap_plot::check_size(width, height).map_err(|_| bad())?;
    Ok(Size { width, height })
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    let Size { width, height } = args.size;
    let out = &args.out;
    if let Some(bag) = &args.bag {
        let topics = RunTopics {
            pose: args.pose_topic.clone(),
            map_cloud: args.map_cloud_topic.clone(),
            diagnostics: args.diagnostics_topic.clone(),
        };
        let s = render_run_summary(bag, &topics, out, width, height)?;
        let latency = s
            .latency_ms_p50
            .map_or(String::new(), |l| format!(", cloud -> pose p50 {l:.1} ms"));
        println!(
            "{}: {} poses ({} ok, {} degraded, {} without diagnostics), {} scans without a pose, \
             map cloud {} points, horizontal sigma median {:.4} m, max {:.4} m{latency}; {width}x{height}",
            out.display(),
            s.poses,
            s.ok,
            s.degraded,
            s.unrated,
            s.without_pose,
            kfmap_plot::grouped(s.map_points as u64),
            s.sigma_m.0,
            s.sigma_m.1
        );
        return Ok(());
    }
    if let Some(estimate) = &args.trajectory {
        let reference = args
            .ground_truth
            .as_deref()
            .ok_or_else(|| anyhow::anyhow!("--trajectory needs --ground-truth"))?;
        let inputs = TrajectoryPlotInputs {
            estimate,
            reference,
            scan_log: args.scan_log.as_deref(),
            title: args.title.as_deref(),
        };
        let options = TrajectoryOptions {
            max_dt: args.max_dt_ms / 1e3,
            align: args.align,
        };
        let s = render_trajectory_summary(&inputs, out, width, height, &options)?;
        let log = match s.logged_scans {
            Some(n) => format!(
                "; {} lost/failed, {} degraded of {n} logged scans",
                s.lost, s.degraded
            ),
            None => String::new(),
        };
        let aligned = s.alignment.map_or(String::new(), |a| {
            format!(
                " after aligning the estimate (rotated {:.2} deg, moved {:.3} m)",
                a.rotation.angle().to_degrees(),
                a.translation.vector.norm()
            )
        });
        println!(
            "{}: {} of {} estimated poses matched a reference pose within {} ms, position error{aligned} RMSE {:.4} m, max {:.4} m{log}; {width}x{height}",
            out.display(),
            s.matched,
            s.estimate_poses,
            kfmap_plot::ms_label(options.max_dt),
            s.rmse,
            s.max
        );
        return Ok(());
    }
    let map = args
        .map
        .as_deref()
        .ok_or_else(|| anyhow::anyhow!("give a map file or --trajectory"))?;
    let options = MapPlotOptions {
        edges: !args.no_edges,
        width,
        height,
    };
    let s = render_map_summary(map, out, &options)?;
    let edges = if options.edges {
        format!(
            ", {} covisibility edges ({} drawn), {} of them on revisits",
            s.covisibility_edges,
            s.drawn_edges.0 + s.drawn_edges.1,
            s.revisit_edges
        )
    } else {
        String::new()
    };
    println!(
        "{}: {}, {} points (drawn {}), height colours {:.2}..{:.2} m{edges}; {width}x{height}",
        out.display(),
        kfmap_plot::plural(s.keyframes, "keyframe"),
        kfmap_plot::grouped(s.points),
        kfmap_plot::grouped(s.drawn as u64),
        s.height_range.0,
        s.height_range.1
    );
    Ok(())
}
