//! kfmap's remote client: a [`Client`] whose requests travel as Zenoh queries to the
//! `kfmap gateway` beside a map server on another host (docs/DESIGN.md#notes-remote),
//! with the same calls and errors as one on the server's host; a
//! [`kfmap_client::Tracker`] works over it unchanged. Its own crate so the client
//! library, and the server that hosts its tracker, compile without Zenoh.
//!
//! ```no_run
//! use kfmap_client::ClientOptions;
//! use kfmap_geometry::geometry::Pose;
//!
//! let mut client = kfmap_remote::connect("tcp/10.0.0.5:7447", "site", ClientOptions::default())?;
//! let scan = vec![[1.0f32, 0.0, 0.0]; 1000];
//! let found = client.nearest(&scan, &Pose::identity(), 1)?;
//! println!("{} map points", found.len());
//! # Ok::<(), kfmap_client::ClientError>(())
//! ```
#![warn(missing_docs)]

mod link;
mod options;
mod tiled;

pub use options::{RemoteOptions, zenoh_config};

use kfmap_client::{Client, ClientError, ClientOptions, Connection};

/// Connects to the server of `map_name` on another host through the `kfmap gateway` at
/// `endpoint` (a Zenoh endpoint such as `tcp/10.0.0.5:7447`; several separated by
/// commas); fails with `NoServer` when the gateway announces no live server for the map.
pub fn connect(
    endpoint: &str,
    map_name: &str,
    options: ClientOptions,
) -> Result<Client, ClientError> {
    connect_with(&RemoteOptions::new(endpoint), map_name, options)
}

/// As [`connect`] with every remote option (Zenoh config file for TLS, client id, tile).
pub fn connect_with(
    remote: &RemoteOptions,
    map_name: &str,
    options: ClientOptions,
) -> Result<Client, ClientError> {
    let link = link::ZenohLink::open(map_name, remote)?;
    Ok(Client::over(Connection::over_remote(
        map_name,
        Box::new(link),
        options,
    )))
}
