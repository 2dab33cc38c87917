//! `kfmap serve`: one process owns a baked map and answers clients over iceoryx2
//! (docs/DESIGN.md#overview, docs/DESIGN.md#protocol). A worker pool takes turns waiting for requests
//! (or spinning) and queues them per client; the workers answer them round-robin; the
//! main thread reclaims the sessions of clients that died, ends the loop gracefully on
//! SIGINT/SIGTERM, and swaps in a new map file on SIGHUP (or a `Reload` request).

mod answer;
mod budget;
mod dispatch;
mod imu;
mod leader;
mod limits;
mod localize;
mod ports;
mod queries;
mod queue;
mod register;
mod relocalize;
pub mod session;
pub mod state;
mod stats;
mod track;
mod unread;
mod workers;

use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use iceoryx2::node::{Node, NodeView};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::prelude::{CallbackProgression, NodeState, PortFactory, WaitSetBuilder};
use iceoryx2::waitset::{WaitSet, WaitSetGuard, WaitSetRunResult};
use kfmap_map::archive::ArchiveError;
use kfmap_map::tiles::SearchShare;
use kfmap_protocol::Cov2CovMode;
use kfmap_protocol::transport::{
    ALLOCATION, INITIAL_SLICE_LEN, Rpc, Transport, TransportError, create_node, iceoryx_config,
    iox, open_request_event, open_response_event, open_rpc,
};
use tracing::{info, warn};

use crate::config::ServerConfig;
pub use answer::{Answer, AnswerPairings};
use budget::{Budget, BudgetLimits};
pub use dispatch::answer;
use leader::{RequestServer, Requests};
pub use limits::{Limits, MAX_RADIUS};
pub use localize::localize_params;
use ports::ClientPorts;
use queue::FairQueue;
use session::Sessions;
pub use state::{MapSlot, ServedMap};
pub use stats::{KindFigures, Stats, WINDOW as LATENCY_WINDOW};
use unread::UnreadAnswers;
use workers::{Job, WorkerContext};

/// Free space `/dev/shm` must have at start: iceoryx2 writes into shared memory that
/// the kernel backs lazily, and a full tmpfs kills the writer with SIGBUS.
pub const MIN_SHM_FREE_BYTES: u64 = 64 << 20;
/// How often dead clients are looked for and reload signals checked.
const HOUSEKEEPING: Duration = Duration::from_millis(250);
/// How long a stopping server waits for its clients to read their last answers.
const SHUTDOWN_LINGER: Duration = Duration::from_secs(2);

/// How to serve.
#[derive(Debug, Clone)]
pub struct ServeOptions {
    /// The baked map file.
    pub map_path: PathBuf,
    /// Name in the service names `kfmap/<map-name>/...`.
    pub map_name: String,
    /// `server.toml`.
    pub config: ServerConfig,
    /// iceoryx2 prefix of every shared-memory name (separates deployments and tests).
    pub iceoryx_prefix: Option<String>,
    /// Poll instead of sleeping on events: lower latency, one core busy.
    pub spin: bool,
    /// Skip bytechecks of keyframe archives (checksums still verified).
    pub trust: bool,
    /// A tile's share of relocalization over its tile set; `None` for a whole map.
    pub search_share: Option<SearchShare>,
}

/// Why the server could not start or stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// The map file could not be opened.
    #[error("{}", named(path, error))]
    Map {
        /// The file.
        path: PathBuf,
        /// Why.
        error: ArchiveError,
    },
    /// Another server already serves this map name.
    #[error(
        "another kfmap server already serves map {0:?} (a request would reach both); stop it or pick another --map-name"
    )]
    AlreadyServed(String),
    /// `/dev/shm` is too small.
    #[error(
        "/dev/shm has {free_mib} MiB free; kfmap serve needs at least {need_mib} MiB (in a container, raise --shm-size)"
    )]
    SharedMemoryTooSmall {
        /// Free MiB.
        free_mib: u64,
        /// Needed MiB.
        need_mib: u64,
    },
    /// iceoryx2 setup failed.
    #[error(transparent)]
    Transport(#[from] TransportError),
}

/// `error` with the file named once (some archive errors name it already).
fn named(path: &Path, error: &ArchiveError) -> String {
    let text = error.to_string();
    let shown = path.display().to_string();
    if text.contains(&shown) {
        text
    } else {
        format!("{shown}: {text}")
    }
}

/// What a server reports when it is ready.
#[derive(Debug, Clone)]
pub struct ServeInfo {
    /// Map name in service names.
    pub map_name: String,
    /// Keyframes in the map.
    pub keyframes: usize,
    /// Points in the map.
    pub points: usize,
    /// Worker threads.
    pub workers: usize,
    /// Milliseconds from start to ready.
    pub startup_ms: f64,
    /// Cov2cov mode requests without their own get: "approximate" or "exact".
    pub default_mode: &'static str,
}

/// What a server did, returned on shutdown.
#[derive(Debug, Clone)]
pub struct ServeSummary {
    /// Requests answered, by kind code.
    pub figures: Vec<KindFigures>,
    /// Requests refused at shutdown, never started.
    pub refused_at_shutdown: usize,
    /// Seconds served.
    pub uptime_s: f64,
}

/// Checks that `/dev/shm` (when present) has [`MIN_SHM_FREE_BYTES`] free.
pub fn check_shared_memory() -> Result<(), ServeError> {
    let Some(free) = shared_memory_free() else {
        return Ok(());
    };
    if free < MIN_SHM_FREE_BYTES {
        return Err(ServeError::SharedMemoryTooSmall {
            free_mib: free >> 20,
            need_mib: MIN_SHM_FREE_BYTES >> 20,
        });
    }
    Ok(())
}

/// Free bytes of `/dev/shm` (`None` where it cannot be read).
pub(crate) fn shared_memory_free() -> Option<u64> {
    kfmap_geometry::io::free_bytes(Path::new("/dev/shm"))
}

/// Ids of the live iceoryx2 nodes under `config`; dead nodes' resources are removed.
fn live_nodes(node: &Node<Transport>, config: &iceoryx2::config::Config) -> HashSet<u128> {
    node.try_cleanup_dead_nodes();
    let mut alive = HashSet::new();
    let listed = Node::<Transport>::list(config, |state| {
        if let NodeState::Alive(view) = state {
            alive.insert(view.id().value());
        }
        CallbackProgression::Continue
    });
    if let Err(e) = listed {
        warn!(error = ?e, "could not list iceoryx2 nodes; sessions are kept");
    }
    alive
}

/// A listing of live nodes: when it was taken, and the ids.
type Listing = (Instant, Arc<HashSet<u128>>);

/// The last listing per iceoryx2 prefix in this process. A process serving many tiles
/// runs a housekeeping per tile, and a listing reads every node's files on the host:
/// the tiles share one listing per interval (12 tiles listed the host 48 times a
/// second, a tenth of a core on a host of 20 nodes: docs/DESIGN.md#notes-tiles).
static LISTINGS: Mutex<Vec<(Option<String>, Listing)>> = Mutex::new(Vec::new());

/// The live nodes under `prefix`, listed by whichever served map of this process asks
/// first in each housekeeping interval.
fn shared_live_nodes(
    node: &Node<Transport>,
    config: &iceoryx2::config::Config,
    prefix: Option<&str>,
) -> Listing {
    // Held while listing: the others wait for this listing instead of making theirs.
    let mut listings = LISTINGS.lock().unwrap_or_else(PoisonError::into_inner);
    let fresh = |(p, (taken, _)): &&(Option<String>, Listing)| {
        p.as_deref() == prefix && taken.elapsed() < HOUSEKEEPING
    };
    if let Some((_, listing)) = listings.iter().find(fresh) {
        return listing.clone();
    }
    let taken = Instant::now();
    let listing = (taken, Arc::new(live_nodes(node, config)));
    listings.retain(|(p, _)| p.as_deref() != prefix);
    listings.push((prefix.map(str::to_string), listing.clone()));
    listing
}

/// Every request allocates and frees buffers of about the same size (decoded scan,
/// pairings); glibc would hand large ones back to the kernel each time and fault them
/// in again on the next request. Keep them in the process instead.
fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator thresholds; called before any worker runs.
    unsafe {
        const LARGE: libc::c_int = 32 << 20; // glibc's ceiling for the mmap threshold
        libc::mallopt(libc::M_MMAP_THRESHOLD, LARGE);
        libc::mallopt(libc::M_TRIM_THRESHOLD, LARGE);
    }
}

/// Runs the server until SIGINT/SIGTERM (or `stop` is set). `ready` is called once
/// the services are up.
pub fn serve(
    options: &ServeOptions,
    stop: &AtomicBool,
    ready: impl FnOnce(&ServeInfo),
) -> Result<ServeSummary, ServeError> {
    let started = Instant::now();
    check_shared_memory()?;
    keep_freed_memory();
    let mut map =
        ServedMap::open(&options.map_path, options.trust, 0).map_err(|error| ServeError::Map {
            path: options.map_path.clone(),
            error,
        })?;
    map.search_share = options.search_share.clone();
    let slot = MapSlot::new(map);
    let config = iceoryx_config(options.iceoryx_prefix.as_deref())?;
    let node = create_node(&config, "kfmap-server")?;
    let ports = ServerPorts::open(&node, &options.map_name)?;
    let hangup = Arc::new(AtomicBool::new(false));
    if let Err(e) = signal_hook::flag::register(signal_hook::consts::SIGHUP, hangup.clone()) {
        warn!(error = %e, "SIGHUP reload is unavailable");
    }
    let workers = match options.config.server.worker_threads {
        0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
        n => n,
    };
    let queue: FairQueue<Job> = FairQueue::default();
    let context = WorkerContext {
        slot: &slot,
        sessions: &Sessions::default(),
        stats: &Stats::default(),
        limits: Limits::of(&options.config),
        notifier: &ports.notifier,
        map_name: &options.map_name,
        started,
        trust: options.trust,
        budget: Budget::new(BudgetLimits::of(&options.config.server)),
        ports: ClientPorts::new(&ports.rpc, options.config.server.max_clients_per_process),
        unread: &UnreadAnswers::default(),
        largest_answer: Default::default(),
    };
    ready(&announce(options, &slot, workers, started));
    let requests = Requests {
        server: &ports.server,
        listener: &ports.listener,
        spin: options.spin,
    };
    // Made before the workers start: a failure must not leave them running.
    let waitset = WaitSetBuilder::new()
        .create::<Transport>()
        .map_err(iox("create the WaitSet"))?;
    let tick = waitset
        .attach_interval(HOUSEKEEPING)
        .map_err(iox("attach the housekeeping interval"))?;
    let housekeeping = || {
        let (listed, alive) = shared_live_nodes(&node, &config, options.iceoryx_prefix.as_deref());
        context.unread.sweep();
        let dropped = context.sessions.retain_alive(&alive, listed);
        if dropped > 0 {
            info!(dropped, "sessions of dead clients reclaimed");
        }
        if hangup.swap(false, Ordering::Relaxed) {
            // The outcome is logged; the old map stays on failure.
            let _ = context.reload();
        }
    };
    let never_started = std::thread::scope(|scope| {
        for _ in 0..workers {
            scope.spawn(|| leader::work(&context, &queue, &requests));
        }
        wait_for_stop(&waitset, &tick, stop, &hangup, housekeeping);
        info!("shutting down: refusing queued requests, finishing those in flight");
        context.unread.close();
        let left = queue.close();
        let never_started = left.len();
        for job in left {
            context.refuse_shutting_down(job);
        }
        // The leader may be asleep on the listener.
        let _ = ports.wake_leader.notify();
        never_started
    });
    // Requests that arrived while the workers stopped are refused by name too.
    requests.drain(&context, &queue);
    // The last answers live in this process's shared memory: exiting removes them.
    let unread = context.unread.wait_until_read(SHUTDOWN_LINGER);
    if unread > 0 {
        warn!(unread, "exiting with answers their clients have not read");
    }
    Ok(ServeSummary {
        figures: context.stats.figures().to_vec(),
        refused_at_shutdown: never_started + queue.turned_away(),
        uptime_s: started.elapsed().as_secs_f64(),
    })
}

/// The server's iceoryx2 ports on a map's services: the request-response server (one
/// per map name), the request listener, the response notifier, and a notifier on the
/// request event that wakes the leader at shutdown.
struct ServerPorts {
    rpc: Rpc,
    server: RequestServer,
    listener: Listener<Transport>,
    notifier: Notifier<Transport>,
    wake_leader: Notifier<Transport>,
}

impl ServerPorts {
    /// Opens the ports; fails when another server already serves `map_name`.
    fn open(node: &Node<Transport>, map_name: &str) -> Result<Self, ServeError> {
        // A server killed earlier leaves its port behind; free it before counting servers.
        node.try_cleanup_dead_nodes();
        let rpc = open_rpc(node, map_name)?;
        if rpc.dynamic_config().number_of_servers() > 0 {
            return Err(ServeError::AlreadyServed(map_name.to_string()));
        }
        let server = rpc
            .server_builder()
            .initial_max_slice_len(INITIAL_SLICE_LEN)
            .allocation_strategy(ALLOCATION)
            // One answer per request (and fewer chunks to scan when a client dies).
            .max_loaned_responses_per_request(1)
            .create()
            .map_err(|_| ServeError::AlreadyServed(map_name.to_string()))?;
        let listener = open_request_event(node, map_name)?
            .listener_builder()
            .create()
            .map_err(iox("create the request listener"))?;
        let notifier = open_response_event(node, map_name)?
            .notifier_builder()
            .create()
            .map_err(iox("create the response notifier"))?;
        let wake_leader = open_request_event(node, map_name)?
            .notifier_builder()
            .create()
            .map_err(iox("create the shutdown notifier"))?;
        Ok(Self {
            rpc,
            server,
            listener,
            notifier,
            wake_leader,
        })
    }
}

/// What the ready line says: the map served, the workers, the start-up time and the
/// default cov2cov mode (the server's, else the map's); logged as well.
fn announce(options: &ServeOptions, slot: &MapSlot, workers: usize, started: Instant) -> ServeInfo {
    let current = slot.current();
    let exact = match options.config.server.cov2cov_mode {
        Cov2CovMode::MapDefault => current.exact_by_default,
        mode => mode == Cov2CovMode::Exact,
    };
    let info_line = ServeInfo {
        map_name: options.map_name.clone(),
        keyframes: current.keyframes,
        points: current.points,
        workers,
        startup_ms: started.elapsed().as_secs_f64() * 1e3,
        default_mode: if exact { "exact" } else { "approximate" },
    };
    info!(map = %options.map_name, keyframes = info_line.keyframes, points = info_line.points, workers, cov2cov = info_line.default_mode, "serving");
    info_line
}

/// The main thread's loop while the workers serve: housekeeping on every tick (and on
/// SIGHUP), until SIGINT/SIGTERM set `stop` or the WaitSet fails.
fn wait_for_stop(
    waitset: &WaitSet<Transport>,
    tick: &WaitSetGuard<Transport>,
    stop: &AtomicBool,
    hangup: &AtomicBool,
    housekeeping: impl Fn(),
) {
    loop {
        let result = waitset.wait_and_process_once(|id| {
            if id.has_event_from(tick) {
                housekeeping();
            }
            CallbackProgression::Continue
        });
        match result {
            Ok(WaitSetRunResult::AllEventsHandled) if !stop.load(Ordering::Relaxed) => {}
            // Any signal interrupts the wait (SIGCONT after SIGSTOP, SIGWINCH, SIGHUP);
            // only SIGINT and SIGTERM stop the server, seen by the next wait as a
            // termination request. A SIGHUP asks for a reload.
            Ok(WaitSetRunResult::Interrupt) if !stop.load(Ordering::Relaxed) => {
                if hangup.load(Ordering::Relaxed) {
                    housekeeping();
                }
            }
            Ok(_) => break,
            Err(e) => {
                warn!(error = ?e, "WaitSet failed; shutting down");
                break;
            }
        }
    }
}
