//! Client library of kfmap: connecting to a map server over iceoryx2, querying
//! nearest neighbours and cov2cov correspondences, localizing, publishing IMU windows.
//!
//! The protocol and the client arrive with the map-server issue; this crate exists now
//! so that the workspace layout (ARCHITECTURE section 2) is in place from the start.
#![warn(missing_docs)]
