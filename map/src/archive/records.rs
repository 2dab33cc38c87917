//! The rkyv record types of a baked map: one archive per keyframe (its own checksum,
//! verified on first use) and one index archive at the end of the file.

use rkyv::with::{InlineAsBox, Map};
use rkyv::{Archive, Deserialize, Serialize};

use kfmap_geometry::geometry::PackedSym3;
use kfmap_geometry::spatial::{NodeWords, PointBlock, TreeRef};

/// One keyframe's local data, archived on its own at a 128-byte aligned offset.
/// Written from borrowed data (no copy of points or tree); read as
/// [`ArchivedKeyframeRecord`].
#[derive(Archive, Serialize)]
pub struct KeyframeRecord<'a> {
    /// Keyframe id (repeated here so a misplaced segment is caught).
    pub id: u64,
    /// Local points.
    #[rkyv(with = InlineAsBox)]
    pub points: &'a [[f32; 3]],
    /// Local view directions.
    #[rkyv(with = Map<InlineAsBox>)]
    pub view_dirs: Option<&'a [[f32; 3]]>,
    /// Local covariances; `None` when the map was baked without them.
    #[rkyv(with = Map<InlineAsBox>)]
    pub covariances: Option<&'a [PackedSym3]>,
    /// Raw points each point stands for (voxel counts), when bake recorded them.
    #[rkyv(with = Map<InlineAsBox>)]
    pub weights: Option<&'a [u32]>,
    /// KD-tree over `points`; `None` when the map was baked without trees.
    pub tree: Option<TreeRecord<'a>>,
}

/// A KD-tree's three arrays (see [`kfmap_geometry::spatial::NodeWords`]), archived as they are
/// so the reader searches them in place.
#[derive(Archive, Serialize)]
pub struct TreeRecord<'a> {
    /// Nodes in depth-first order.
    #[rkyv(with = InlineAsBox)]
    pub nodes: &'a [NodeWords],
    /// Points in leaf order, in blocks of lanes.
    #[rkyv(with = InlineAsBox)]
    pub blocks: &'a [PointBlock],
    /// The keyframe point index of each lane (`PAD_ITEM` for unused lanes).
    #[rkyv(with = InlineAsBox)]
    pub items: &'a [u32],
}

impl<'a> From<TreeRef<'a>> for TreeRecord<'a> {
    fn from(tree: TreeRef<'a>) -> Self {
        Self {
            nodes: tree.nodes(),
            blocks: tree.blocks(),
            items: tree.items(),
        }
    }
}

/// Where a keyframe's segment is and what it holds.
#[derive(Archive, Serialize, Deserialize, Debug, Clone, PartialEq)]
pub struct KeyframeEntry {
    /// Keyframe id.
    pub id: u64,
    /// Seconds.
    pub timestamp: f64,
    /// `T_map_keyframe` as x y z qx qy qz qw.
    pub pose: [f64; 7],
    /// Local bounding box, min then max.
    pub bbox: [f32; 6],
    /// Number of points.
    pub points: u64,
    /// Segment offset from the start of the payload (a multiple of 128).
    pub offset: u64,
    /// Segment length, bytes.
    pub len: u64,
    /// xxh3-64 of the segment bytes.
    pub checksum: u64,
    /// Bytes of points, view directions and weights in the segment.
    pub point_bytes: u64,
    /// Bytes of covariances in the segment.
    pub covariance_bytes: u64,
    /// True when the segment holds view directions.
    pub has_view_dirs: bool,
}

/// The place grid of relocalization ([`crate::place::PlaceGrid`]), archived on its own
/// segment (its own checksum, verified on first use) so opening a map stays O(keyframes).
#[derive(Archive, Serialize)]
pub struct PlaceGridRecord<'a> {
    /// Level-0 voxel edge, metres.
    pub resolution: f64,
    /// `R_grid_map` as qx qy qz qw.
    pub grid_from_map: [f64; 4],
    /// Grid-frame position of voxel (0, 0, 0)'s low corner.
    pub origin: [f64; 3],
    /// Voxels per axis.
    pub dims: [u32; 3],
    /// Levels, level 0 included.
    pub levels: u32,
    /// Searched translations, grid frame: low corner...
    pub region_min: [f64; 3],
    /// ... and high corner.
    pub region_max: [f64; 3],
    /// Per block of the grid (x fastest): its entry, or `0xff` when empty at every
    /// level; empty when the table is used: see [`crate::place::sparse`].
    #[rkyv(with = InlineAsBox)]
    pub directory: &'a [u32],
    /// Block table keys (block coordinates; `u64::MAX` where free), a
    /// power-of-two count: see [`crate::place::sparse`].
    #[rkyv(with = InlineAsBox)]
    pub keys: &'a [u64],
    /// Per table slot: the levels where the block is partly marked (below them it is
    /// empty, above wholly marked) and where their bits are.
    #[rkyv(with = InlineAsBox)]
    pub entries: &'a [u32],
    /// Bits of the partly marked block levels, 8 words (8^3 voxels) each, after a
    /// block of clear and a block of set bits.
    #[rkyv(with = InlineAsBox)]
    pub words: &'a [u64],
}

/// Where the place grid's segment is.
#[derive(Archive, Serialize, Deserialize, Debug, Clone, Copy, PartialEq)]
pub struct PlaceEntry {
    /// Segment offset from the start of the payload (a multiple of 128).
    pub offset: u64,
    /// Segment length, bytes.
    pub len: u64,
    /// xxh3-64 of the segment bytes.
    pub checksum: u64,
}

/// One keyframe's accelerometer statistics (the gravity pool).
#[derive(Archive, Serialize, Deserialize, Debug, Clone, Copy, PartialEq)]
pub struct GravityRecord {
    /// Keyframe id.
    pub keyframe: u64,
    /// Mean specific force in the body frame, m/s^2.
    pub mean_acc: [f64; 3],
    /// Spread of the accelerometer norm, m/s^2.
    pub std: f64,
    /// Samples averaged.
    pub samples: u64,
}

/// The map index: keyframe entries, covisibility graph, gravity pool.
#[derive(Archive, Serialize, Deserialize, Debug, Clone, PartialEq, Default)]
pub struct MapIndex {
    /// Id the next inserted keyframe gets.
    pub next_id: u64,
    /// Keyframes, ascending id.
    pub keyframes: Vec<KeyframeEntry>,
    /// Covisibility: every keyframe of the graph.
    pub covis_keyframes: Vec<u64>,
    /// Covisibility edges `(a, b, weight)`, `a < b`.
    pub covis_edges: Vec<(u64, u64, u32)>,
    /// Spanning tree `(child, parent)`.
    pub covis_parents: Vec<(u64, u64)>,
    /// Keyframes in the spanning tree.
    pub covis_in_tree: Vec<u64>,
    /// Per-keyframe accelerometer statistics.
    pub gravity_pool: Vec<GravityRecord>,
    /// `T_map_input` (x y z qx qy qz qw): how bake moved the input poses into the map
    /// frame (the gravity levelling); identity when it kept them.
    pub map_from_input: [f64; 7],
    /// The place grid's segment; `None` when the map has none (relocalization refused).
    pub place: Option<PlaceEntry>,
}
