//! `kfmap bench`: measurements that need whole processes or files too big for criterion.
//! This file is the command line and its dispatch; each benchmark is a module of its
//! own, the table's rows are measured by the modules `suite` lists. `server_child` runs
//! `kfmap serve` and its clients as child processes (for the benchmarks and `kfmap
//! demo`); `data_dir` finds the real data beside the checkout.

mod anchors;
mod automotive;
mod bags;
mod child;
mod city;
mod cov2cov;
mod fixtures;
mod ipc;
mod kdtree;
mod kernels;
mod load;
mod localization;
mod pose_graph;
mod registration;
mod remote;
mod soak;
mod soak_client;
mod suite;
mod table;

pub mod data_dir;
pub mod server_child;

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};

/// Benchmarks. With no subcommand: the system benchmarks in one table. `load`: cold
/// start of a baked map against rebuilding it. `ipc`: the map server's round trips and
/// throughput. `soak`: many clients for minutes.
///
/// `kfmap bench` (no subcommand) measures, each row naming its data and threads, with
/// the anchor's figure (small_gicp, GTSAM) beside it where one was measured on the same
/// data: per-point covariances, cov2cov per scan (approximate, exact on a new active
/// set, exact cached), GICP per scan pair, pose-graph optimization, cold start against
/// rebuild and bake throughput (`load`), IPC round trips of 1k/10k/100k points and
/// cov2cov throughput (`ipc`), remote against local localize (`remote`), and localization per scan with its error on the real
/// sequence balm_os0, with the same scans relocalized with no guess beside it (median,
/// p99, and its ratio to the tracking step's median), and the automotive drive
/// kitti00_drive built by `bake --build-poses --deskew azimuth` (wall time, aligned ATE,
/// KITTI-style drift) beside KISS-ICP on the same scans, once its extract.sh has written
/// them (about 45 s more). Real data comes from ../shared/data (or $KFMAP_DATA_DIR); without
/// it, synthetic scans stand in and rows that need it are listed as skipped. About 75 s
/// on 2 cores; --quick (fewer repetitions, a 40-keyframe generated map) under a
/// minute, with noisier figures. --json: {"rows": [{name, data, threads, value, unit,
/// anchor: {tool, value, script} | null}], "skipped": [...]}.
///
/// `kfmap bench load` generates a map (default 500 keyframes x 40 000 points, about
/// 1.3 GB, under --dir), then measures: the time from starting a fresh `kfmap` process
/// to its first answered nearest-neighbour query on the memory-mapped file (median of
/// 5, page cache warm); the rebuild path (every tree and covariance from the points,
/// as a map without baked caches must do); bake throughput on 1 and 2 threads; and
/// query throughput on the archived map against the same map on the heap.
///
/// `kfmap bench ipc` bakes a small synthetic map (12 keyframes x 40 000 points),
/// starts `kfmap serve` on it as a child process and measures: echo round trips (no
/// compute) of 1k, 10k and 100k points, median and p99; cov2cov of a 10k-point scan
/// over IPC against the same call in process; and cov2cov throughput of one client
/// against four client processes at once (scans/s, p99). --spin makes server and
/// client poll instead of sleeping on events.
///
/// `kfmap bench remote` (run it inside `unshare -rn`, as the table does: network
/// benchmarks stay on a private loopback) starts `kfmap serve` and `kfmap gateway` on the
/// same synthetic map and measures server-side localize of a 20k-point scan through the
/// gateway (Zenoh over TCP) against the same request over iceoryx2, alternated request
/// by request (median, p99 as JSON), then the throughput of 4 client processes each way. Without
/// user namespaces the table lists these rows as skipped.
///
/// `kfmap bench city` lays 20 000 keyframes (2 000 points each) along a street grid over
/// a 10 x 10 km site, bakes them into one map, then bakes the same keyframes into 250 m
/// tiles with a 50 m halo as `kfmap bake --tile-size` does (streamed into the tiles), and
/// reports bake throughput whole and into tiles, the cold start of the largest tiles (a
/// fresh process to its first answer) and the place grids' bytes against the tile files.
/// About 4 GB on disk under --dir while it runs; --quick: 800 keyframes over 2 x 2 km.
///
/// `kfmap bench soak` starts `kfmap serve` on the same synthetic map and --clients
/// client processes, each sending --rate requests per second for --seconds: scans of
/// 30k-120k points, mixed kinds (cov2cov, nearest, radius, localize, IMU windows,
/// status). It reports requests, failed (an error status), lost (no answer within
/// 30 s), busy (refused by the server's budgets), latency per kind, the server's RSS
/// after warm-up (the first tenth of the run, at most 60 s; in all and as heap, map-file
/// pages and shared memory), at the end and at most, and the
/// shared-memory files left after shutdown. --flood N adds an overload phase: a 1 Hz
/// client alone, then the same client while N processes send back to back. Exits 1
/// when any request failed or was lost, or shared memory was left behind.
///
/// A p99 over fewer than 100 samples is their maximum; the text output says so
/// ("p99 (= max of 30)"). Each subcommand's own options: kfmap bench load --help
/// (ipc, soak alike).
///
/// Examples:
///   kfmap bench
///   kfmap bench --quick --json
///   kfmap bench load --dir /var/tmp/kfmap-bench
///   kfmap bench ipc --spin --json
///   kfmap bench soak --clients 8 --seconds 300 --json
///   kfmap bench soak --clients 2 --seconds 20 --flood 4
#[derive(clap::Args)]
#[command(verbatim_doc_comment, disable_help_subcommand = true)]
pub struct Args {
    /// What to measure: load, ipc or soak (none: the whole table).
    #[command(subcommand)]
    what: Option<What>,
    /// Table and ipc: fewer repetitions and a smaller generated map (a smoke run).
    #[arg(long, global = true)]
    quick: bool,
    /// Folder for the generated map (default: the system temp folder).
    #[arg(long, global = true)]
    dir: Option<PathBuf>,
    /// Print the figures as JSON.
    #[arg(long, global = true)]
    json: bool,
}

/// `kfmap bench`'s subcommands; without one, the whole table.
#[derive(clap::Subcommand)]
enum What {
    /// Cold start of a baked map against rebuilding it.
    Load(LoadArgs),
    /// The map server's round trips and throughput.
    Ipc(IpcArgs),
    /// Many clients for minutes against one server.
    Soak(SoakArgs),
    /// A synthetic city map baked whole and cut into tiles: bake throughput, cold start
    /// per tile, place grid share.
    City(CityArgs),
    /// Server-side localize through `kfmap gateway` against the same over iceoryx2 (run
    /// it in a private network namespace: `unshare -rn`, as the table does).
    Remote,
    /// Stream, then decode, every PointCloud2 of a bag: seconds and GB/s as JSON (the
    /// rosbags anchor script runs it beside its own reader on the same file).
    BagRead { file: PathBuf },
    /// Internal (load): open MAP, answer one query, print the microseconds since start.
    #[command(hide = true)]
    Probe { map: PathBuf },
    /// Internal (remote): run as one throughput client of the server under PREFIX, over
    /// iceoryx2 or (--remote) through the gateway.
    #[command(hide = true)]
    RemoteWorker {
        prefix: String,
        /// Seconds to send requests.
        #[arg(long)]
        seconds: f64,
        /// Through the gateway.
        #[arg(long)]
        remote: bool,
    },
    /// Internal (ipc): run as one throughput client of the server under PREFIX.
    #[command(hide = true)]
    IpcWorker {
        prefix: String,
        /// Seconds to send requests.
        #[arg(long)]
        seconds: f64,
    },
    /// Internal (ipc): hold PORTS raw client ports to the server under PREFIX until
    /// killed (the client process the IPC bench SIGKILLs).
    #[command(hide = true)]
    IpcHolder {
        prefix: String,
        /// Client ports to open.
        #[arg(long)]
        ports: usize,
    },
    /// Internal (soak): run as one soak client of the server under PREFIX.
    #[command(hide = true)]
    SoakClient {
        prefix: String,
        /// Requests per second (0: back to back).
        #[arg(long)]
        rate: f64,
        /// Seconds to run.
        #[arg(long)]
        seconds: f64,
        /// The client's seed.
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
}

/// `kfmap bench load`.
#[derive(clap::Args)]
struct LoadArgs {
    /// Keyframes of the generated map.
    #[arg(long, default_value_t = 500)]
    keyframes: usize,
    /// Points per keyframe.
    #[arg(long, default_value_t = 40_000)]
    points: usize,
    /// Keep the generated map file.
    #[arg(long)]
    keep: bool,
}

/// `kfmap bench city`.
#[derive(clap::Args)]
struct CityArgs {
    /// Edge of the square site, metres (--quick: 2000).
    #[arg(long, default_value_t = 10_000.0)]
    extent_m: f64,
    /// Keyframes along its streets, about 10 m apart (--quick: 800).
    #[arg(long, default_value_t = 20_000)]
    keyframes: usize,
    /// Points per keyframe.
    #[arg(long, default_value_t = 2_000)]
    points: usize,
    /// Tile edge, metres.
    #[arg(long, default_value_t = 250.0)]
    tile_size: f64,
    /// Halo around each tile, metres.
    #[arg(long, default_value_t = 50.0)]
    halo: f64,
}

/// `kfmap bench ipc`.
#[derive(clap::Args)]
struct IpcArgs {
    /// Server and client poll instead of waiting on events.
    #[arg(long)]
    spin: bool,
}

/// `kfmap bench soak`.
#[derive(clap::Args)]
struct SoakArgs {
    /// Client processes.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=32))]
    clients: u32,
    /// Seconds the clients run.
    #[arg(long, default_value_t = 300.0)]
    seconds: f64,
    /// Requests per second of each client (0: back to back).
    #[arg(long, default_value_t = 10.0)]
    rate: f64,
    /// Processes flooding the server in the overload phase (0: no such phase).
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u32).range(0..=16))]
    flood: u32,
}

/// Runs the subcommand; `process_start` is when this process started (the probe's
/// cold start counts from it).
pub fn run(args: Args, process_start: Instant) -> anyhow::Result<()> {
    let dir = || -> anyhow::Result<PathBuf> {
        let dir = args.dir.clone().unwrap_or_else(std::env::temp_dir);
        std::fs::create_dir_all(&dir).with_context(|| dir.display().to_string())?;
        Ok(dir)
    };
    match &args.what {
        None => suite::run(args.quick, args.json, &dir()?),
        Some(What::Load(load)) => {
            if load.keyframes < 2 || load.points < 100 {
                bail!("--keyframes must be at least 2 and --points at least 100");
            }
            let size = load::MapSize {
                keyframes: load.keyframes,
                points: load.points,
            };
            load::run(&dir()?, size, load.keep, args.json)
        }
        Some(What::Ipc(ipc)) => ipc::run(&dir()?, ipc.spin, args.quick, args.json),
        Some(What::Remote) => remote::run(&dir()?, args.quick),
        Some(What::City(city)) => {
            let plan = city::CityPlan {
                extent_m: if args.quick { 2_000.0 } else { city.extent_m },
                keyframes: if args.quick { 800 } else { city.keyframes },
                points: city.points,
                tiles: kfmap_map::tiles::TileGeometry {
                    tile_size: city.tile_size,
                    halo: city.halo,
                },
            };
            city::run(&dir()?, plan, args.json)
        }
        Some(What::Soak(soak)) => {
            let plan = soak::SoakPlan {
                clients: soak.clients as usize,
                seconds: soak.seconds,
                rate: soak.rate,
                flood: soak.flood as usize,
            };
            soak::run(&dir()?, plan, args.json)
        }
        Some(What::Probe { map }) => load::probe(map, process_start),
        Some(What::BagRead { file }) => bags::run_read(file),
        Some(What::IpcWorker { prefix, seconds }) => ipc::worker(prefix, *seconds),
        Some(What::IpcHolder { prefix, ports }) => ipc::holder(prefix, *ports),
        Some(What::RemoteWorker {
            prefix,
            seconds,
            remote,
        }) => remote::worker(prefix, *remote, *seconds),
        Some(What::SoakClient {
            prefix,
            rate,
            seconds,
            seed,
        }) => {
            let plan = soak_client::ClientPlan {
                rate_hz: *rate,
                seconds: *seconds,
                seed: *seed,
            };
            soak_client::run(prefix, plan)
        }
    }
}

/// A number of a JSON report (NaN when absent), for printing.
pub fn json_number(value: &serde_json::Value) -> f64 {
    value.as_f64().unwrap_or(f64::NAN)
}
