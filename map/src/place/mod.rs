//! Global relocalization's parts: where in the map a scan with no pose
//! guess was taken.
//!
//! - [`level`]: the scan's up direction from its floor-like planes (when no IMU gives it);
//! - [`grid`]: the map's coarse occupancy grid with dilated levels, baked into the map;
//! - [`sparse`]: the grid's levels as blocks found through a hash table;
//! - [`search`]: branch and bound over yaw and translation on that grid;
//! - [`relocalize`]: levelling, search, verification by registration, the verdict;
//! - [`pinning`]: whether the scans pin a place or it slides (tracker and verdict).
//!
//! Chosen by measurement on `balm_os0` (map of scans 0-115, the 61 revisit scans
//! 116-176): Scan Context descriptors (20 x 60, per scan or per virtual view of the
//! merged map) put the right place first for 15-29 of 61 scans and among the best 20
//! for 23-40; the branch-and-bound search over a 1 m grid puts it first for 59 and
//! among its best 3 for all 61 (`examples/place_search.rs`).

pub mod grid;
pub mod level;
pub mod pinning;
pub mod relocalize;
pub mod search;
pub mod sparse;

pub use grid::{
    GridBuilder, GridContribution, GridError, GridParams, GridView, LevelBlocks, MarkedVoxels,
    PlaceGrid, SearchRegion,
};
pub use level::{estimate_map_up, estimate_up, levelling};
pub use relocalize::{
    Ground, Pinning, PlaceStep, Proposal, Relocalization, RelocalizeParams, RelocalizeStatus,
    ScanUp, Scored, ScoredPlace, another_place, decide, off_ground, own_up, propose, score_places,
    score_stage, thinned_scan, thinning_stride, verification_selection,
};
pub use search::{Columns, OwnedColumns, PeerBest, Placement, SearchOutcome, SearchParams, search};

#[cfg(test)]
pub(crate) mod tests;
