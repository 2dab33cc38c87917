//! Who sent a request: iceoryx2 stamps every request with the sending port's
//! `UniqueClientId`, which a client cannot forge; the service's registry maps that port
//! to its node and the node to its process. Sessions are keyed by that node, so a
//! `client_node` written into the header must agree with it.

use std::collections::HashMap;
use std::sync::Mutex;

use iceoryx2::identifiers::UniqueClientId;
use iceoryx2::prelude::{CallbackProgression, PortFactory};
use kfmap_shared::protocol::transport::{Rpc, Transport};

/// The node and process behind a client port.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Owner {
    /// iceoryx2 node id.
    pub node: u128,
    /// Process id (0 when iceoryx2 cannot tell).
    pub process: u32,
}

/// Client ports seen so far, by port id.
pub struct ClientPorts<'a> {
    rpc: &'a Rpc,
    known: Mutex<HashMap<u128, Owner>>,
}

impl<'a> ClientPorts<'a> {
    /// Reads the registry of `rpc`.
    pub fn new(rpc: &'a Rpc) -> Self {
        Self {
            rpc,
            known: Mutex::new(HashMap::new()),
        }
    }

    /// The owner of `port`, looked up in the service's registry on first sight
    /// (`None`: the port is not registered, e.g. it was closed since it sent).
    pub fn owner(&self, port: UniqueClientId) -> Option<Owner> {
        let id = port.value();
        if let Some(owner) = self.lock().get(&id) {
            return Some(*owner);
        }
        let mut found = HashMap::new();
        self.rpc.dynamic_config().list_clients(|details| {
            let process = details
                .node_id
                .pid::<Transport>()
                .map_or(0, |p| p.value() as u32);
            found.insert(
                details.client_id.value(),
                Owner {
                    node: details.node_id.value(),
                    process,
                },
            );
            CallbackProgression::Continue
        });
        let mut known = self.lock();
        // The registry is the truth: ports gone from it are forgotten.
        *known = found;
        known.get(&id).copied()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<u128, Owner>> {
        self.known.lock().unwrap_or_else(|e| e.into_inner())
    }
}
