//! Server runtime of kfmap (`kfmap serve`): its configuration file and the map server
//! that answers clients over iceoryx2.
//!
//! ```
//! let config = kfmap_service::config::ServerConfig::default();
//! assert_eq!(config.server.max_points_per_request, 1_048_576);
//! ```
#![warn(missing_docs)]

pub mod config;
pub mod server;
