//! `kfmap serve`: serve a baked map to local clients over iceoryx2.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use anyhow::Context;
use kfmap_geometry::options::ConfigFile;
use kfmap_map::tiles::{SearchShare, TileIndex};
use kfmap_protocol::RequestKind;
use kfmap_protocol::remote::tile_map_name;
use kfmap_service::config::ServerConfig;
use kfmap_service::server::{LATENCY_WINDOW, ServeOptions, serve};

use kfmap_geometry::percentile::p99_label;

/// Serve a baked map (`kfmap bake`) to client processes on this host over iceoryx2
/// zero-copy shared memory, until SIGINT or SIGTERM.
///
/// The map file is memory-mapped: nothing is rebuilt, the first answer comes in
/// milliseconds. Services are named kfmap/<map-name>/{rpc,request-ready,response-ready};
/// clients (`kfmap localize`, `kfmap query`, `kfmap status`, the kfmap-client library)
/// find the server by that name. One server per map name: a second one refuses to
/// start. Requests are answered by a worker pool, clients taking turns; each client has
/// its own session (active keyframes, gravity pool), reclaimed when it dies.
///
/// Cov2cov and Localize requests that leave the mode to the server are answered in
/// approximate mode (keyframe by keyframe with the baked trees and covariances: no
/// query ever rebuilds anything) unless the map was baked with `[map] cov2cov-mode =
/// "exact"` or server.toml sets `[server] cov2cov-mode`; exact mode builds a merged
/// submap inside the query each time a client's active set changes (a stall of tens
/// to hundreds of milliseconds). The ready line says which. Server-side localization
/// runs server.toml's [tracking] checks and retry ladder.
///
/// SIGHUP (or `kfmap status --reload`) reopens the map file and switches to it
/// atomically; requests in flight finish on the old map. On SIGINT/SIGTERM queued
/// requests get a "shutting down" status, those in flight finish, and the shared-memory
/// resources are removed. Set KFMAP_LOG=debug for one log line per request with its
/// timing.
///
/// Tile sets (`kfmap bake --tile-size`): --tiles DIR serves every tile of the set, or
/// those --only names, each as its own map <map-name>.<tile> (e.g. site.x0_y-1) with its
/// own workers, in this one process; `kfmap gateway --tiles DIR` announces them to
/// remote clients, which route each request to the tile whose square holds its pose
/// guess. A site spread over several hosts runs one serve + gateway pair per host, each
/// with its --only share. The ready line comes once every tile is served.
///
/// Examples:
///   kfmap serve --map site.kfmap
///   kfmap serve --map site.kfmap --map-name site --config config/server.toml --spin
///   kfmap serve --tiles site.tiles --map-name site --only x0_y0,x1_y0
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// The baked map file.
    #[arg(long, required_unless_present = "tiles", conflicts_with = "tiles")]
    map: Option<PathBuf>,
    /// A tile set's directory (`kfmap bake --tile-size`): serve its tiles.
    #[arg(long, value_name = "DIR")]
    tiles: Option<PathBuf>,
    /// With --tiles: serve only these tiles (comma-separated ids, e.g. x0_y0,x1_y0).
    #[arg(long, value_name = "IDS", value_delimiter = ',', requires = "tiles")]
    only: Vec<String>,
    /// Name clients connect to; default: the map file's (or tile directory's) stem, or
    /// server.toml's map-name.
    #[arg(long)]
    map_name: Option<String>,
    /// server.toml (defaults: config/server.toml as shipped).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Poll for requests instead of sleeping on events: lower latency, one core busy
    /// (computations lose that core: on 2 cores a cov2cov takes about twice as long).
    #[arg(long)]
    spin: bool,
    /// Skip bytechecks of keyframe archives on first use (checksums are still verified).
    /// Only for files you baked yourself: the checksum catches accidental damage, not a
    /// crafted file, and a crafted or malformed file served with --trust is undefined
    /// behaviour (reads out of bounds, a crash or wrong answers). See docs/DESIGN.md#archive.
    #[arg(long)]
    trust: bool,
    /// iceoryx2 prefix of every shared-memory name; clients must use the same.
    #[arg(long)]
    iceoryx_prefix: Option<String>,
}

/// The map name: the flag, else the config's, else the file stem.
fn map_name(args: &Args, config: &ServerConfig) -> anyhow::Result<String> {
    if let Some(name) = &args.map_name {
        return Ok(name.clone());
    }
    if !config.server.map_name.is_empty() {
        return Ok(config.server.map_name.clone());
    }
    let path = args
        .map
        .as_ref()
        .or(args.tiles.as_ref())
        .expect("clap: --map or --tiles");
    path.file_stem()
        .and_then(|s| s.to_str())
        .map(str::to_string)
        .with_context(|| {
            format!(
                "{}: no file stem to name the map; pass --map-name",
                path.display()
            )
        })
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let config = ServerConfig::load(args.config.as_deref())?;
    let name = map_name(&args, &config)?;
    if let Some(dir) = &args.tiles {
        return serve_tiles(&args, dir, &name, config);
    }
    let options = ServeOptions {
        map_name: name,
        map_path: args.map.clone().expect("clap: --map without --tiles"),
        config,
        iceoryx_prefix: args.iceoryx_prefix.clone(),
        spin: args.spin,
        trust: args.trust,
        search_share: None,
    };
    let stop = AtomicBool::new(false);
    // Writes ignore errors: a closed stdout or stderr (the reader gone) must not stop a
    // server, nor panic it.
    let summary = serve(&options, &stop, |info| {
        // One line on stdout when ready: scripts and tests wait for it.
        let mut out = std::io::stdout().lock();
        let _ = writeln!(
            out,
            "ready: serving map {} ({} keyframes, {} points, {} cov2cov by default) with {} workers, started in {:.1} ms",
            info.map_name,
            info.keyframes,
            info.points,
            info.default_mode,
            info.workers,
            info.startup_ms
        );
        let _ = out.flush();
    })?;
    print_summary(&summary, None);
    Ok(())
}

/// Serves the tiles of the tile set `dir` (all, or `--only`), each as map
/// `<name>.<tile>` on a thread of its own, until SIGINT/SIGTERM or one tile fails.
fn serve_tiles(args: &Args, dir: &Path, name: &str, config: ServerConfig) -> anyhow::Result<()> {
    let index = TileIndex::load(dir)?;
    let tiles = index.select(&args.only, dir)?;
    let stop = AtomicBool::new(false);
    let ready = AtomicUsize::new(0);
    let total = tiles.len();
    let outcomes = std::thread::scope(|scope| {
        let threads: Vec<_> = tiles
            .iter()
            .map(|tile| {
                let options = ServeOptions {
                    map_name: tile_map_name(name, &tile.id),
                    map_path: dir.join(&tile.file),
                    config: config.clone(),
                    iceoryx_prefix: args.iceoryx_prefix.clone(),
                    spin: args.spin,
                    trust: args.trust,
                    search_share: SearchShare::of(&index, &tile.id),
                };
                let (stop, ready) = (&stop, &ready);
                scope.spawn(move || {
                    let outcome = serve(&options, stop, |info| {
                        let mut out = std::io::stdout().lock();
                        let _ = writeln!(
                            out,
                            "tile {} ready: map {} ({} keyframes, {} points, {} cov2cov) with {} workers, started in {:.1} ms",
                            tile.id, info.map_name, info.keyframes, info.points,
                            info.default_mode, info.workers, info.startup_ms
                        );
                        if ready.fetch_add(1, Ordering::SeqCst) + 1 == total {
                            let _ = writeln!(
                                out,
                                "ready: serving {total} tiles of {name} (maps {name}.<tile>) from {}",
                                dir.display()
                            );
                        }
                        let _ = out.flush();
                    });
                    // One tile failing stops them all: a partial tile set is a wrong one.
                    stop.store(true, Ordering::SeqCst);
                    (tile.id.clone(), outcome)
                })
            })
            .collect();
        threads
            .into_iter()
            .map(|t| t.join().expect("a tile's server thread panicked"))
            .collect::<Vec<_>>()
    });
    let mut failed = None;
    for (id, outcome) in outcomes {
        match outcome {
            Ok(summary) => print_summary(&summary, Some(&id)),
            Err(e) => {
                failed.get_or_insert(anyhow::anyhow!("tile {id}: {e}"));
            }
        }
    }
    failed.map_or(Ok(()), Err)
}

/// The closing lines on stderr: uptime and per-kind figures (of `tile`, if one).
fn print_summary(summary: &kfmap_service::server::ServeSummary, tile: Option<&str>) {
    let mut err = std::io::stderr().lock();
    let _ = writeln!(
        err,
        "{}stopped after {:.1} s; {} queued requests refused at shutdown",
        tile.map_or(String::new(), |t| format!("tile {t}: ")),
        summary.uptime_s,
        summary.refused_at_shutdown
    );
    for kind in RequestKind::ALL {
        let f = summary.figures[kind as usize];
        if f.count > 0 {
            let _ = writeln!(
                err,
                "  {:<10} {:>8} requests, p50 {:.0} us, {} {:.0} us",
                kind.name(),
                f.count,
                f.p50_us,
                p99_label((f.count as usize).min(LATENCY_WINDOW)),
                f.p99_us
            );
        }
    }
}
