//! The map's KD-tree over `f32` points: a balanced median-split tree whose nodes,
//! leaf points and item ids are three plain arrays, so a baked map reads it in place
//! from the memory-mapped file exactly as a tree built in this process.
//!
//! Leaves store their points in blocks of [`LANES`], axis by axis, so one block's
//! distances take a few vector instructions; splits fall on multiples of [`LANES`], so
//! with leaves of [`LEAF_SIZE`] only the last block can be part empty. Searches descend nanoflann-style, without recursion:
//! nearer child first, the other child kept on a small stack and visited only when the
//! incremental distance to its cell can still beat the bound. On KITTI 00 (frame 1
//! queried against frame 0, one thread) that answers 1-NN and k = 20 about 1.3x faster
//! than small_gicp (`cargo bench -p kfmap-geometry --bench kdtree`, docs/BENCHMARKS.md).
//!
//! ```
//! use kfmap_geometry::spatial::build_tree;
//!
//! let points = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]];
//! let tree = build_tree(&points).unwrap();
//! assert_eq!(tree.view().nearest_one(&[1.0, 0.5, 0.0]), (1, 0.25));
//! ```

pub(crate) mod build;
mod morton;
mod search;
#[cfg(test)]
mod tests;

use std::num::NonZeroUsize;

use build::BoxTree;
pub use morton::morton_order;
use search::{Counted, KNearest, Nearest, NearestAt, NearestTwo, Within};

/// Points per leaf. On KITTI 00 (frame 1 against frame 0, one thread) leaves of 16
/// (two blocks) answered 1-NN faster than 8 or 32 (`cargo bench --bench kdtree`).
pub const LEAF_SIZE: usize = 16;

/// Points a leaf stores side by side: leaves hold blocks of this many, axis by axis, so
/// one block's distances are computed in a few vector instructions.
pub const LANES: usize = 8;

/// `LANES` leaf-ordered points as `[xs, ys, zs]`. Lanes past the end of a leaf hold NaN,
/// which is within no bound, and the item id [`PAD_ITEM`].
pub type PointBlock = [[f32; LANES]; 3];

/// Item id of an unused lane.
pub const PAD_ITEM: u32 = u32::MAX;

/// First word of a leaf node; a split node holds its axis (0, 1 or 2) there.
const LEAF_TAG: u32 = u32::MAX;

/// Deeper than any balanced tree over `u32` points: a stored tree deeper than this is
/// malformed. It bounds the search's fixed stack (one far child per level).
const MAX_DEPTH: usize = 40;

/// One node in four words. Split: `[axis, right child, low, high]` where the left child
/// follows the node, `low` (f32 bits) is the largest left coordinate and `high` the
/// smallest right coordinate on the axis. Leaf: `[LEAF_TAG, first block, end block,
/// points]`, a range of blocks whose first `points` lanes are used.
pub type NodeWords = [u32; 4];

/// A KD-tree built in this process; item ids are indices into the points it was built
/// from.
#[derive(Debug, Clone)]
pub struct PointTree {
    nodes: Vec<NodeWords>,
    blocks: Vec<PointBlock>,
    items: Vec<u32>,
    len: usize,
}

impl PointTree {
    /// The tree's arrays, for searching or archiving.
    pub fn view(&self) -> TreeRef<'_> {
        TreeRef {
            nodes: &self.nodes,
            blocks: &self.blocks,
            items: &self.items,
            len: self.len,
        }
    }

    /// Number of indexed points.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True for no points (never the case for a built tree).
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

/// A tree's arrays, borrowed from a [`PointTree`] or read in place from a baked map.
#[derive(Debug, Clone, Copy)]
pub struct TreeRef<'a> {
    nodes: &'a [NodeWords],
    blocks: &'a [PointBlock],
    /// One id per lane of `blocks`.
    items: &'a [u32],
    len: usize,
}

/// Why a tree could not be built or read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TreeError {
    /// No points to index.
    #[error("cannot build a KD-tree over zero points")]
    Empty,
    /// A point has a NaN or infinite coordinate.
    #[error("point {0} has a non-finite coordinate; filter invalid points first")]
    NonFinite(usize),
    /// More points than `u32` item ids can name.
    #[error("{0} points exceed the KD-tree limit of {max}", max = u32::MAX)]
    TooManyPoints(usize),
    /// Per-point data given alongside the points has another length.
    #[error("per-point data does not match the points: {0}")]
    MismatchedParts(String),
    /// Stored arrays that do not form a tree.
    #[error("malformed KD-tree: {0}")]
    Malformed(String),
}

/// A candidate's (squared distance, item) order as one integer: the bits of a
/// non-negative `f32` sort as the number does, so one compare orders by distance and
/// breaks ties by item.
#[inline(always)]
pub(crate) fn rank(dist_sq: f32, item: u32) -> u64 {
    (u64::from(dist_sq.to_bits()) << 32) | u64::from(item)
}

/// The squared distance of a [`rank`].
#[inline(always)]
pub(crate) fn rank_dist_sq(rank: u64) -> f32 {
    f32::from_bits((rank >> 32) as u32)
}

/// The item of a [`rank`].
#[inline(always)]
pub(crate) fn rank_item(rank: u64) -> u32 {
    rank as u32
}

/// The squared distance between a tree's point and a query: what every search
/// computes for each point it scans, so a caller re-measuring a point a search found
/// gets the same bits.
#[inline(always)]
pub fn point_dist_sq(point: &[f32; 3], query: &[f32; 3]) -> f32 {
    let (dx, dy, dz) = (
        point[0] - query[0],
        point[1] - query[1],
        point[2] - query[2],
    );
    dx * dx + dy * dy + dz * dz
}

/// Builds a tree over `points`; item `i` is `points[i]`. The same tree for any thread
/// count.
pub fn build_tree(points: &[[f32; 3]]) -> Result<PointTree, TreeError> {
    build_tree_with_leaf(points, LEAF_SIZE)
}

/// [`build_tree`] with another leaf size (benchmarks compare them).
pub fn build_tree_with_leaf(points: &[[f32; 3]], leaf: usize) -> Result<PointTree, TreeError> {
    if points.is_empty() {
        return Err(TreeError::Empty);
    }
    if points.len() >= PAD_ITEM as usize {
        return Err(TreeError::TooManyPoints(points.len()));
    }
    if let Some(i) = points.iter().position(|p| p.iter().any(|c| !c.is_finite())) {
        return Err(TreeError::NonFinite(i));
    }
    // Splits at a multiple of LANES so nearly every block is full.
    let BoxTree { nodes, order } = BoxTree::build(points, leaf, LANES);
    let mut words = Vec::with_capacity(nodes.len());
    let mut blocks = Vec::with_capacity(points.len() / LANES + nodes.len());
    let mut items = Vec::with_capacity(blocks.capacity() * LANES);
    for (i, n) in nodes.iter().enumerate() {
        if n.is_leaf() {
            let first = blocks.len() as u32;
            for chunk in order[n.start as usize..n.end as usize].chunks(LANES) {
                let mut block = [[f32::NAN; LANES]; 3];
                let mut ids = [PAD_ITEM; LANES];
                for (lane, (id, p)) in chunk.iter().enumerate() {
                    for axis in 0..3 {
                        block[axis][lane] = p[axis];
                    }
                    ids[lane] = *id;
                }
                blocks.push(block);
                items.extend(ids);
            }
            words.push([LEAF_TAG, first, blocks.len() as u32, n.end - n.start]);
            continue;
        }
        let axis = n.axis as usize;
        let low = nodes[i + 1].max[axis];
        let high = nodes[n.right as usize].min[axis];
        words.push([n.axis, n.right, low.to_bits(), high.to_bits()]);
    }
    Ok(PointTree {
        nodes: words,
        blocks,
        items,
        len: points.len(),
    })
}

impl<'a> TreeRef<'a> {
    /// A tree from stored arrays (e.g. a memory-mapped map), checked to be one: every
    /// node reachable once, in depth-first order, leaves covering the blocks in order,
    /// unused lanes padded, item ids a permutation, depth bounded. Searches on it then
    /// never index out of range nor return an id outside `0..len()`.
    pub fn from_parts(
        nodes: &'a [NodeWords],
        blocks: &'a [PointBlock],
        items: &'a [u32],
    ) -> Result<Self, TreeError> {
        let mut tree = Self {
            nodes,
            blocks,
            items,
            len: 0,
        };
        tree.len = tree.check()?;
        Ok(tree)
    }

    /// Arrays that passed [`TreeRef::from_parts`] before, with the point count it found
    /// (a memory-mapped map checks each keyframe once, then reads it many times).
    ///
    /// Nothing is checked here. Arrays that never passed `from_parts` give wrong
    /// neighbours, a panic (an index out of bounds) or a query that never ends (a node
    /// pointing back up the tree), but never undefined behaviour: every access is bounds
    /// checked and the one `unsafe` read in the search only reads slots it wrote.
    pub fn from_checked_parts(
        nodes: &'a [NodeWords],
        blocks: &'a [PointBlock],
        items: &'a [u32],
        len: usize,
    ) -> Self {
        Self {
            nodes,
            blocks,
            items,
            len,
        }
    }

    /// Checks the arrays; returns the number of points.
    fn check(&self) -> Result<usize, TreeError> {
        let malformed = |why: String| Err(TreeError::Malformed(why));
        if self.blocks.is_empty() || self.nodes.is_empty() {
            return Err(TreeError::Empty);
        }
        if self.items.len() != self.blocks.len() * LANES {
            return malformed(format!(
                "{} item ids for {} blocks of {LANES}",
                self.items.len(),
                self.blocks.len()
            ));
        }
        let mut walk = Walk {
            block: 0,
            points: 0,
        };
        let end = self.check_subtree(0, 0, &mut walk)?;
        if end != self.nodes.len() || walk.block != self.blocks.len() {
            return malformed(format!(
                "the nodes reach {end} of {} nodes and {} of {} blocks",
                self.nodes.len(),
                walk.block,
                self.blocks.len()
            ));
        }
        let n = walk.points;
        let mut seen = vec![false; n];
        for &item in self.items.iter().filter(|&&i| i != PAD_ITEM) {
            match seen.get_mut(item as usize) {
                Some(s) if !*s => *s = true,
                _ => return malformed(format!("item id {item} is out of range or repeated")),
            }
        }
        Ok(n)
    }

    /// Checks the subtree at `node`; returns the index just past it.
    fn check_subtree(
        &self,
        node: usize,
        depth: usize,
        walk: &mut Walk,
    ) -> Result<usize, TreeError> {
        let malformed = |why: String| Err(TreeError::Malformed(why));
        if depth > MAX_DEPTH {
            return malformed(format!("deeper than {MAX_DEPTH} levels"));
        }
        let Some(&[tag, a, b, c]) = self.nodes.get(node) else {
            return malformed(format!("node {node} is missing"));
        };
        if tag == LEAF_TAG {
            let (first, end, points) = (a as usize, b as usize, c as usize);
            let lanes = end.saturating_sub(first).saturating_mul(LANES);
            if first != walk.block
                || end > self.blocks.len()
                || points == 0
                || points > lanes
                || points + LANES <= lanes
            {
                return malformed(format!(
                    "leaf {node} has a bad block range {a}..{b} for {c} points"
                ));
            }
            let slots = first * LANES..end * LANES;
            for (slot, &item) in slots.clone().zip(&self.items[slots]) {
                let used = slot - first * LANES < points;
                let [xs, ys, zs] = &self.blocks[slot / LANES];
                let lane = [xs[slot % LANES], ys[slot % LANES], zs[slot % LANES]];
                // A used lane holds a point as build_tree takes it; an unused one
                // must never be within a bound.
                let well_formed = if used {
                    item != PAD_ITEM && lane.iter().all(|c| c.is_finite())
                } else {
                    item == PAD_ITEM && lane.iter().any(|c| c.is_nan())
                };
                if !well_formed {
                    return malformed(format!("leaf {node} has a bad lane {slot}"));
                }
            }
            walk.block = end;
            walk.points += points;
            return Ok(node + 1);
        }
        let (low, high) = (f32::from_bits(b), f32::from_bits(c));
        if tag > 2 || low.is_nan() || high.is_nan() {
            return malformed(format!("split node {node} has axis {tag} or a NaN bound"));
        }
        let left_end = self.check_subtree(node + 1, depth + 1, walk)?;
        if a as usize != left_end {
            return malformed(format!("node {node} links its right child out of order"));
        }
        self.check_subtree(left_end, depth + 1, walk)
    }

    /// The node array (for archiving).
    pub fn nodes(&self) -> &'a [NodeWords] {
        self.nodes
    }

    /// The points in leaf order, a block of lanes at a time (for archiving).
    pub fn blocks(&self) -> &'a [PointBlock] {
        self.blocks
    }

    /// The item id of each lane of [`TreeRef::blocks`] (for archiving).
    pub fn items(&self) -> &'a [u32] {
        self.items
    }

    /// Number of indexed points.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True for no points.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The nearest point: `(item, squared distance)`; ties go to the smaller item.
    #[inline]
    pub fn nearest_one(&self, query: &[f32; 3]) -> (u32, f32) {
        self.nearest_one_within(query, f32::INFINITY)
            .expect("a tree holds at least one point")
    }

    /// The nearest point with squared distance <= `max_dist_sq`, if any.
    #[inline]
    pub fn nearest_one_within(&self, query: &[f32; 3], max_dist_sq: f32) -> Option<(u32, f32)> {
        let mut best = Nearest::within(max_dist_sq);
        self.search(query, &mut best);
        best.found()
    }

    /// [`TreeRef::nearest_one_within`] with the point's coordinates as the tree stores
    /// them: `(item, squared distance, point)`.
    #[inline]
    pub fn nearest_one_within_at(
        &self,
        query: &[f32; 3],
        max_dist_sq: f32,
    ) -> Option<(u32, f32, [f32; 3])> {
        let mut best = NearestAt {
            nearest: Nearest::within(max_dist_sq),
            point: [f32::NAN; 3],
        };
        self.search(query, &mut best);
        best.nearest.found().map(|(item, d)| (item, d, best.point))
    }

    /// [`TreeRef::nearest_one_within_at`] and the squared distance of the runner-up
    /// within `max_dist_sq` (`max_dist_sq` itself when there is none): no point of the
    /// tree but the nearest lies closer to `query` than that.
    #[inline]
    pub fn nearest_two_within_at(
        &self,
        query: &[f32; 3],
        max_dist_sq: f32,
    ) -> (Option<(u32, f32, [f32; 3])>, f32) {
        let mut two = NearestTwo::within(max_dist_sq);
        self.search(query, &mut two);
        let item = rank_item(two.first);
        let nearest = (item != PAD_ITEM).then(|| (item, rank_dist_sq(two.first), two.point));
        (nearest, rank_dist_sq(two.second))
    }

    /// What finding the nearest point costs: the nodes read and the blocks of
    /// [`LANES`] points whose distances are computed (the physical-limit estimate of
    /// `cargo bench --bench kdtree` counts them).
    pub fn nearest_one_cost(&self, query: &[f32; 3]) -> SearchCost {
        let mut counted = Counted {
            inner: Nearest::within(f32::INFINITY),
            nodes: 0,
            blocks: 0,
        };
        self.search(query, &mut counted);
        SearchCost {
            nodes: counted.nodes,
            blocks: counted.blocks,
        }
    }

    /// The `n` nearest points, nearest first (ties by item): `(item, squared distance)`.
    pub fn nearest_n(&self, query: &[f32; 3], n: NonZeroUsize) -> Vec<(u32, f32)> {
        self.nearest_n_within(query, n, f32::INFINITY)
    }

    /// [`TreeRef::nearest_n`] among the points with squared distance <= `max_dist_sq`.
    pub fn nearest_n_within(
        &self,
        query: &[f32; 3],
        n: NonZeroUsize,
        max_dist_sq: f32,
    ) -> Vec<(u32, f32)> {
        let mut best = KNearest::within(n.get().min(self.len()), max_dist_sq);
        self.search(query, &mut best);
        best.hits()
    }

    /// Every point with squared distance <= `radius_sq`, nearest first (ties by item).
    pub fn within(&self, query: &[f32; 3], radius_sq: f32) -> Vec<(u32, f32)> {
        let mut found = Within {
            radius_sq,
            hits: Vec::new(),
        };
        self.search(query, &mut found);
        found.sorted()
    }
}

/// The work of one search (see [`TreeRef::nearest_one_cost`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SearchCost {
    /// Nodes read, leaves included.
    pub nodes: usize,
    /// Blocks of [`LANES`] points whose distances were computed.
    pub blocks: usize,
}

/// Where [`TreeRef::check_subtree`] has got to: the next leaf's first block and the
/// points seen so far.
struct Walk {
    block: usize,
    points: usize,
}
