//! The iceoryx2 services of a map, built the same way by server and clients (the
//! first process to arrive creates them with these settings).

use iceoryx2::config::Config;
use iceoryx2::node::Node;
use iceoryx2::prelude::{
    AllocationStrategy, CallbackProgression, FileName, NodeBuilder, PortFactory, SemanticString,
    ServiceName, ipc_threadsafe,
};
use iceoryx2::service::port_factory::event::PortFactory as EventFactory;
use iceoryx2::service::port_factory::request_response::PortFactory as RpcFactory;

use super::wire::{RequestHeader, ResponseHeader, WirePairing};
use super::{request_event_name, response_event_name, rpc_service_name};

/// The iceoryx2 service variant of kfmap: thread-safe ports, so a worker pool can
/// answer requests; it interoperates with plain `ipc` clients.
pub type Transport = ipc_threadsafe::Service;

/// The request-response service of a map.
pub type Rpc = RpcFactory<Transport, [f32], RequestHeader, [WirePairing], ResponseHeader>;

/// An event service of a map.
pub type Event = EventFactory<Transport>;

/// Client ports a map's services admit, over all processes.
pub const MAX_CLIENTS: usize = 128;
/// Client ports one process may open through this library (the server's default
/// `max-clients-per-process`): one careless process cannot fill the table.
pub const MAX_CLIENTS_PER_PROCESS: usize = 16;
/// Slice length reserved for a first request or response; larger ones grow the
/// segment once (power-of-two reallocation).
pub const INITIAL_SLICE_LEN: usize = 16 * 1024;

/// Why the services could not be set up.
#[derive(Debug, thiserror::Error)]
pub enum TransportError {
    /// The iceoryx2 prefix is not a valid file name.
    #[error("iceoryx2 prefix {0:?} is not a valid file name (letters, digits, '-', '_', '.')")]
    BadPrefix(String),
    /// The map name makes an invalid service name.
    #[error("map name {0:?} cannot be used in an iceoryx2 service name")]
    BadMapName(String),
    /// iceoryx2's files belong to another unix user.
    #[error(
        "permission denied on {path} (owner uid {owner}, mode {mode:o}): a kfmap server's iceoryx2 files are owner-only, so only the unix user that runs `kfmap serve` can connect to it; run this as uid {owner} (iceoryx2 0.10 has no setting for group access; see README, Access)"
    )]
    PermissionDenied {
        /// The folder this process may not use.
        path: String,
        /// Its owner.
        owner: u32,
        /// Its permission bits.
        mode: u32,
    },
    /// This process holds its share of the map's client ports already.
    #[error(
        "this process (pid {process}) already has {open} kfmap clients of map {map_name:?} open, the most one process may ({MAX_CLIENTS_PER_PROCESS}); drop clients it no longer uses (each Client holds a port until dropped)"
    )]
    TooManyClients {
        /// The map.
        map_name: String,
        /// This process.
        process: u32,
        /// Its ports.
        open: usize,
    },
    /// Every client port of the map's service is taken.
    #[error(
        "all {MAX_CLIENTS} client ports of map {map_name:?} are taken; process {busiest} holds {held} of them"
    )]
    ClientTableFull {
        /// The map.
        map_name: String,
        /// The process holding most ports.
        busiest: u32,
        /// How many it holds.
        held: usize,
    },
    /// iceoryx2 refused.
    #[error("iceoryx2: {what}: {message}")]
    Iceoryx {
        /// The step that failed.
        what: &'static str,
        /// iceoryx2's error.
        message: String,
    },
}

/// Wraps an iceoryx2 error with the step that failed.
pub fn iox<E: std::fmt::Debug>(what: &'static str) -> impl FnOnce(E) -> TransportError {
    move |e| TransportError::Iceoryx {
        what,
        message: format!("{e:?}"),
    }
}

/// iceoryx2's configuration with an optional prefix for every shared-memory name, so
/// parallel tests and deployments never see each other.
pub fn iceoryx_config(prefix: Option<&str>) -> Result<Config, TransportError> {
    let mut config = Config::default();
    if let Some(prefix) = prefix {
        config.global.prefix = FileName::new(prefix.as_bytes())
            .map_err(|_| TransportError::BadPrefix(prefix.to_string()))?;
    }
    Ok(config)
}

/// A node under `config`.
pub fn create_node(config: &Config, name: &str) -> Result<Node<Transport>, TransportError> {
    let name = name
        .try_into()
        .map_err(|_| TransportError::BadMapName(name.to_string()))?;
    NodeBuilder::new()
        .config(config)
        .name(&name)
        .create::<Transport>()
        .map_err(|e| denied(config).unwrap_or_else(|| iox("create node")(e)))
}

/// The first of iceoryx2's folders this process may not enter or write, as the error
/// that names it (iceoryx2 itself reports only an internal error).
fn denied(config: &Config) -> Option<TransportError> {
    use std::os::unix::ffi::OsStrExt;
    use std::os::unix::fs::MetadataExt;
    let root = std::path::PathBuf::from(config.global.root_path().to_string());
    let dirs = [
        root.clone(),
        root.join("nodes"),
        root.join("services"),
        "/dev/shm".into(),
    ];
    dirs.into_iter().find_map(|dir| {
        let meta = std::fs::metadata(&dir).ok()?;
        let path = std::ffi::CString::new(dir.as_os_str().as_bytes()).ok()?;
        // SAFETY: a valid C string; access(2) only reads it.
        let allowed =
            unsafe { libc::access(path.as_ptr(), libc::R_OK | libc::W_OK | libc::X_OK) } == 0;
        (!allowed).then(|| TransportError::PermissionDenied {
            path: dir.display().to_string(),
            owner: meta.uid(),
            mode: meta.mode() & 0o7777,
        })
    })
}

fn service_name(name: &str, map_name: &str) -> Result<ServiceName, TransportError> {
    ServiceName::new(name).map_err(|_| TransportError::BadMapName(map_name.to_string()))
}

/// Opens or creates the map's request-response service.
pub fn open_rpc(node: &Node<Transport>, map_name: &str) -> Result<Rpc, TransportError> {
    node.service_builder(&service_name(&rpc_service_name(map_name), map_name)?)
        .request_response::<[f32], [WirePairing]>()
        .request_user_header::<RequestHeader>()
        .response_user_header::<ResponseHeader>()
        .max_servers(1)
        .max_clients(MAX_CLIENTS)
        .max_nodes(MAX_CLIENTS + 2)
        // One request in flight and one answer per port: iceoryx2 sizes the server's
        // chunk table by max_clients x these, and scans it whole whenever a dead client's
        // connection is removed (with 4 and 4, 63 dead ports stalled the server 2.5 s).
        .max_active_requests_per_client(1)
        .max_response_buffer_size(1)
        .max_borrowed_responses_per_pending_response(1)
        .open_or_create()
        .map_err(iox("open the request-response service"))
}

/// A client port registered with a map's service, and who owns it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RegisteredClient {
    /// iceoryx2's `UniqueClientId` of the port.
    pub port: u128,
    /// Its node.
    pub node: u128,
    /// The node's process (0 when iceoryx2 cannot tell).
    pub process: u32,
}

/// Every client port of `rpc` now, read from the service's registry.
pub fn registered_clients(rpc: &Rpc) -> Vec<RegisteredClient> {
    let mut found = Vec::new();
    rpc.dynamic_config().list_clients(|details| {
        let process = details
            .node_id
            .pid::<Transport>()
            .map_or(0, |p| p.value() as u32);
        found.push(RegisteredClient {
            port: details.client_id.value(),
            node: details.node_id.value(),
            process,
        });
        CallbackProgression::Continue
    });
    found
}

/// The processes of `rpc`'s server ports now (those iceoryx2 can tell), read from the
/// service's registry.
pub fn server_processes(rpc: &Rpc) -> Vec<u32> {
    let mut found = Vec::new();
    rpc.dynamic_config().list_servers(|details| {
        if let Ok(pid) = details.node_id.pid::<Transport>() {
            found.push(pid.value() as u32);
        }
        CallbackProgression::Continue
    });
    found
}

/// Ports per process among `clients`.
pub fn ports_per_process(clients: &[RegisteredClient]) -> std::collections::HashMap<u32, usize> {
    let mut counts = std::collections::HashMap::new();
    for c in clients {
        *counts.entry(c.process).or_default() += 1;
    }
    counts
}

/// Why a new client port cannot be opened, when it is a kfmap limit: `process` holds
/// [`MAX_CLIENTS_PER_PROCESS`] ports already, or the table is full (named with the
/// process holding most). `None` while there is room.
pub fn no_room_for_client(rpc: &Rpc, map_name: &str, process: u32) -> Option<TransportError> {
    let clients = registered_clients(rpc);
    let counts = ports_per_process(&clients);
    let open = counts.get(&process).copied().unwrap_or(0);
    if open >= MAX_CLIENTS_PER_PROCESS {
        return Some(TransportError::TooManyClients {
            map_name: map_name.to_string(),
            process,
            open,
        });
    }
    if clients.len() < MAX_CLIENTS {
        return None;
    }
    let (busiest, held) = counts.into_iter().max_by_key(|&(_, n)| n)?;
    Some(TransportError::ClientTableFull {
        map_name: map_name.to_string(),
        busiest,
        held,
    })
}

/// Opens or creates the event service clients signal after a request.
pub fn open_request_event(node: &Node<Transport>, map_name: &str) -> Result<Event, TransportError> {
    open_event(node, &request_event_name(map_name), map_name)
}

/// Opens or creates the event service the server signals after a response.
pub fn open_response_event(
    node: &Node<Transport>,
    map_name: &str,
) -> Result<Event, TransportError> {
    open_event(node, &response_event_name(map_name), map_name)
}

fn open_event(node: &Node<Transport>, name: &str, map_name: &str) -> Result<Event, TransportError> {
    node.service_builder(&service_name(name, map_name)?)
        .event()
        .max_listeners(MAX_CLIENTS + 2)
        .max_notifiers(MAX_CLIENTS + 2)
        .max_nodes(MAX_CLIENTS + 2)
        .open_or_create()
        .map_err(iox("open an event service"))
}

/// The allocation strategy of both directions.
pub const ALLOCATION: AllocationStrategy = AllocationStrategy::PowerOfTwo;

/// Every file iceoryx2 made under `prefix`: shared memory in `/dev/shm`, sockets and
/// service records under its root path (two folder levels deep).
pub fn prefix_files(config: &Config, prefix: &str) -> Vec<std::path::PathBuf> {
    fn walk(
        dir: &std::path::Path,
        prefix: &str,
        depth: usize,
        found: &mut Vec<std::path::PathBuf>,
    ) {
        let Ok(entries) = std::fs::read_dir(dir) else {
            return;
        };
        for e in entries.flatten() {
            let path = e.path();
            if e.file_name().to_string_lossy().starts_with(prefix) {
                found.push(path);
            } else if depth > 0 && path.is_dir() {
                walk(&path, prefix, depth - 1, found);
            }
        }
    }
    let mut found = Vec::new();
    walk(std::path::Path::new("/dev/shm"), prefix, 0, &mut found);
    let root = config.global.root_path().to_string();
    walk(std::path::Path::new(&root), prefix, 2, &mut found);
    found
}

/// Removes every file iceoryx2 made under `prefix` ([`prefix_files`]): what a killed
/// process leaves behind. A deepest-level folder emptied by it (a dead node's own
/// record folder) goes too, never the shared `nodes/` or `services/` folders other
/// processes may be writing into. Only for prefixes no live process uses.
pub fn remove_prefix_files(config: &Config, prefix: &str) {
    let root = std::path::PathBuf::from(config.global.root_path().to_string());
    for file in prefix_files(config, prefix) {
        if std::fs::remove_file(&file).is_err() {
            continue;
        }
        let Some(folder) = file.parent() else {
            continue;
        };
        if folder.parent().and_then(|p| p.parent()) == Some(root.as_path()) {
            // Only succeeds when nothing else is left in it.
            let _ = std::fs::remove_dir(folder);
        }
    }
}
