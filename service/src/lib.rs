//! Server runtime of kfmap. For now: the server and bake configuration files, their
//! defaults and validation. The request loop arrives with the map server.
//!
//! ```
//! let config = kfmap_service::config::ServerConfig::default();
//! assert_eq!(config.server.max_points_per_request, 1_048_576);
//! ```
#![warn(missing_docs)]

pub mod config;
