//! `kfmap gateway`: answer clients on other hosts through the local map server.

use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use anyhow::Context;
use kfmap_gateway::{GatewayConfig, GatewayOptions};
use kfmap_geometry::options::ConfigFile;
use kfmap_map::tiles::TileIndex;

/// Answer remote clients (other hosts) through the local `kfmap serve`, over Zenoh,
/// until SIGINT or SIGTERM.
///
/// Run one beside each `kfmap serve` whose map other hosts use. It declares the Zenoh
/// queryable kfmap/<map-name>/v<protocol>/whole/rpc/* and forwards each request over
/// iceoryx2 to the local server, each remote client with a server session of its own
/// (active keyframes, gravity pool), and holds the liveliness token
/// kfmap/<map-name>/v<protocol>/whole/alive while the server answers: remote clients
/// learn within milliseconds that the server died and when it is back.
///
/// Listens on tcp/127.0.0.1:7447 (loopback only) unless told otherwise. For a network,
/// give a Zenoh config file with TLS or mutual TLS and an access control list
/// (docs/DESIGN.md#notes-remote has a working example); multicast scouting is off:
/// clients name the gateway's endpoint.
///
/// Remote clients: `kfmap localize|relocalize|status|query --remote tcp/HOST:7447
/// --map-name NAME`, `kfmap_remote::connect` in Rust, `kfmap.Client.remote` in Python.
///
/// Tile sets: --tiles DIR (the directory `kfmap bake --tile-size` wrote, as given to
/// `kfmap serve --tiles`) announces each tile served on this host (all, or --only) as
/// kfmap/<map-name>/v<protocol>/<tile>/..., forwarded to the local map <map-name>.<tile>,
/// and answers the tile index on kfmap/<map-name>/v<protocol>/index. Remote clients
/// route each request by its pose guess to the tile whose square holds it (staying on
/// a tile a little past its border), and ask every tile at once to relocalize.
///
/// Examples:
///   kfmap serve --map site.kfmap &
///   kfmap gateway --map-name site --listen tcp/0.0.0.0:7447
///   kfmap gateway --map-name site --config gateway.toml
///   kfmap serve --tiles site.tiles --map-name site --only x0_y0,x1_y0 &
///   kfmap gateway --tiles site.tiles --map-name site --only x0_y0,x1_y0
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// The served map's name (as `kfmap serve` announces it).
    #[arg(long)]
    map_name: String,
    /// gateway.toml (defaults: config/gateway.toml as shipped).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Zenoh endpoint to listen on, replacing the config's `listen` (repeatable), e.g.
    /// tcp/0.0.0.0:7447 or tls/0.0.0.0:7447.
    #[arg(long)]
    listen: Vec<String>,
    /// A Zenoh config file (JSON5: TLS, access control), replacing the config's.
    #[arg(long)]
    zenoh_config: Option<PathBuf>,
    /// iceoryx2 prefix of the local server.
    #[arg(long)]
    iceoryx_prefix: Option<String>,
    /// A tile set's directory (`kfmap bake --tile-size`): announce its tiles.
    #[arg(long, value_name = "DIR")]
    tiles: Option<PathBuf>,
    /// With --tiles: announce only these tiles (comma-separated ids), those this host's
    /// `kfmap serve --tiles --only` serves.
    #[arg(long, value_name = "IDS", value_delimiter = ',', requires = "tiles")]
    only: Vec<String>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut config = GatewayConfig::load(args.config.as_deref())?.gateway;
    if !args.listen.is_empty() {
        config.listen = args.listen.clone();
    }
    if let Some(path) = &args.zenoh_config {
        config.zenoh_config = path.display().to_string();
    }
    let mut options = match &args.tiles {
        None => GatewayOptions::new(&args.map_name, config),
        Some(dir) => {
            let index = TileIndex::load(dir)?;
            let tiles: Vec<String> = index
                .select(&args.only, dir)?
                .iter()
                .map(|t| t.id.clone())
                .collect();
            GatewayOptions::tiled(&args.map_name, index, &tiles, config)
        }
    };
    options.iceoryx_prefix = args.iceoryx_prefix.clone();
    let stop = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(signal, stop.clone())
            .context("install the SIGINT/SIGTERM handler")?;
    }
    let tiles = match options.index {
        Some(_) => format!(" ({} tiles)", options.tiles.len()),
        None => String::new(),
    };
    kfmap_gateway::run(&options, &stop, |locators| {
        // One line on stdout when ready: scripts and tests wait for it.
        let mut out = std::io::stdout().lock();
        let _ = writeln!(
            out,
            "ready: gateway for map {}{} listening on {}",
            args.map_name,
            tiles,
            locators.join(", ")
        );
        let _ = out.flush();
    })?;
    eprintln!("gateway stopped");
    Ok(())
}
