//! Server runtime of kfmap: the server and bake configuration files, the baking
//! pipeline (`kfmap bake`), dataset scan ranges (`--scans`), and the map server
//! (`kfmap serve`).
//!
//! ```
//! let config = kfmap_service::config::ServerConfig::default();
//! assert_eq!(config.server.max_points_per_request, 1_048_576);
//! ```
#![warn(missing_docs)]

pub mod bake;
pub mod config;
pub mod gravity;
pub mod scan_range;
pub mod server;
