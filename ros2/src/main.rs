//! `kfmap-ros2`: the ROS 2 localization node (see the crate's documentation).

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use anyhow::Context as _;
use clap::Parser;
use kfmap_geometry::options::ConfigFile;
use kfmap_ros2::config::{DEFAULT_ROS2_TOML, Ros2Config};
use tracing_subscriber::layer::SubscriberExt as _;
use tracing_subscriber::util::SubscriberInitExt as _;

/// A ROS 2 localization node over a running `kfmap serve` on this host.
///
/// Subscribes to a LiDAR's sensor_msgs/PointCloud2 (any layout `kfmap localize --bag`
/// reads; per-point time fields deskew the scan), optionally sensor_msgs/Imu (IMU
/// windows for the server's gravity pool), /initialpose (RViz's "2D Pose Estimate"),
/// /tf (odom -> base_link) and /tf_static (the sensor's mounting). Every cloud is
/// localized with the tracker `kfmap localize` uses: the first one, and every one after
/// the tracker is lost, is relocalized (no pose needed); /initialpose restarts tracking
/// from the pose given. Publishes the base's pose with its 6x6 covariance
/// (geometry_msgs/PoseWithCovarianceStamped, stamped with the cloud's stamp),
/// nav_msgs/Odometry, the map -> odom transform on /tf (map -> base_link when nothing
/// publishes odom -> base_link), diagnostic_msgs/DiagnosticArray (ok / degraded / lost
/// and the reasons; a bad cloud or a missing server is said there, never a crash), the
/// served map as a latched, thinned PointCloud2 and the gravity once pooled.
///
/// DDS without a ROS installation (ros2-client over RustDDS); interoperates with Cyclone
/// DDS (what rmw_cyclonedds_cpp uses). The domain is --domain-id, else ROS_DOMAIN_ID,
/// else ros2.toml's.
///
/// Examples:
///   kfmap serve --map site.kfmap --map-name site &
///   kfmap-ros2 --map-name site
///   kfmap-ros2 --config robot.toml --domain-id 7
///   kfmap-ros2 --print-config > ros2.toml
#[derive(Parser)]
#[command(name = "kfmap-ros2", version, verbatim_doc_comment)]
struct Args {
    /// The node's configuration (TOML, see --print-config); default: built-in.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// DDS domain (overrides ROS_DOMAIN_ID and the config).
    #[arg(long)]
    domain_id: Option<u16>,
    /// The map name `kfmap serve` announces (overrides [server] map-name).
    #[arg(long)]
    map_name: Option<String>,
    /// The server's iceoryx2 prefix (overrides [server] iceoryx-prefix).
    #[arg(long)]
    iceoryx_prefix: Option<String>,
    /// Print the default configuration, every key explained, and exit.
    #[arg(long)]
    print_config: bool,
}

/// Allocations of at least this many bytes get pages of their own, given back on
/// free. glibc raises its threshold to the largest block freed so far (up to 32 MB),
/// after which every 2.7 MB cloud buffer comes from the heap and freed ones stay
/// resident as fragments: 85-103 MB against 31-45 MB with the threshold fixed, for
/// 112k-point clouds at 10 Hz (docs/DESIGN.md#notes-ros2-memory).
const MMAP_THRESHOLD_BYTES: libc::c_int = 256 * 1024;

fn main() -> std::process::ExitCode {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets an allocator parameter; it is called before any thread
    // starts, as glibc asks.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES);
    }
    let level = std::env::var("KFMAP_LOG")
        .ok()
        .and_then(|l| l.parse::<tracing::Level>().ok())
        .unwrap_or(tracing::Level::INFO);
    // RustDDS warns at every message it fragments (the map cloud, large scans): its
    // errors show, its warnings from KFMAP_LOG=debug, the rest from trace.
    let rustdds = match level {
        tracing::Level::TRACE => tracing::Level::TRACE,
        tracing::Level::DEBUG => tracing::Level::WARN,
        _ => tracing::Level::ERROR,
    };
    let filter = tracing_subscriber::filter::Targets::new()
        .with_default(level)
        .with_target("rustdds", rustdds);
    tracing_subscriber::fmt()
        .with_max_level(level)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_writer(std::io::stderr)
        .finish()
        .with(filter)
        .init();
    match run(Args::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(args: Args) -> anyhow::Result<()> {
    if args.print_config {
        print!("{DEFAULT_ROS2_TOML}");
        return Ok(());
    }
    let mut config = Ros2Config::load(args.config.as_deref())?;
    if let Some(name) = args.map_name {
        config.server.map_name = name;
    }
    if let Some(prefix) = args.iceoryx_prefix {
        config.server.iceoryx_prefix = prefix;
    }
    let from_env = match std::env::var("ROS_DOMAIN_ID") {
        Ok(text) if !text.trim().is_empty() => Some(
            text.trim()
                .parse::<u16>()
                .ok()
                .filter(|d| *d <= 232)
                .with_context(|| format!("ROS_DOMAIN_ID={text:?} is not a domain (0 to 232)"))?,
        ),
        _ => None,
    };
    let domain_id = args.domain_id.or(from_env).unwrap_or(config.node.domain_id);
    anyhow::ensure!(
        domain_id <= 232,
        "--domain-id {domain_id}: a domain is 0 to 232"
    );
    let stop = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(signal, stop.clone()).context("install a signal handler")?;
    }
    let summary = kfmap_ros2::node::run(&config, domain_id, &stop, || {
        println!(
            "ready: kfmap-ros2 node {}{} on DDS domain {domain_id}, map {}, clouds from {}",
            config.node.namespace.trim_end_matches('/'),
            format_args!("/{}", config.node.name),
            config.server.map_name,
            config.topics.points
        );
    })?;
    eprintln!(
        "stopped: {} clouds received, {} localized, {} skipped for newer ones, {} bad, {} without a server; {} IMU samples dropped; {} poses held back without a mounting",
        summary.received,
        summary.localized,
        summary.skipped,
        summary.bad,
        summary.unanswered,
        summary.imu_dropped,
        summary.unmounted
    );
    Ok(())
}
