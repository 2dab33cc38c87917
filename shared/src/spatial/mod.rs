//! The map's KD-tree over `f32` points: a balanced median-split tree whose nodes,
//! leaf-ordered points and item ids are three plain arrays, so a baked map reads it in
//! place from the memory-mapped file exactly as a tree built in this process.
//!
//! Searches descend nanoflann-style: nearer child first, the other child only when the
//! incremental distance to its cell can still beat the current bound. On KITTI 00
//! (frame 1 queried against frame 0, one thread) that answers 1-NN in about half the
//! time kiddo 6.3's `ImmutableKdTree` takes (`cargo bench -p kfmap-shared --bench kdtree`).
//!
//! ```
//! use kfmap_shared::spatial::build_tree;
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
use search::{KNearest, Nearest, Within};

/// Points per leaf. On KITTI 00 (frame 1 against frame 0, one thread) leaves of 16
/// answered 1-NN faster than 8 or 32 (`cargo bench --bench kdtree`).
pub const LEAF_SIZE: usize = 16;

/// First word of a leaf node; a split node holds its axis (0, 1 or 2) there.
const LEAF_TAG: u32 = u32::MAX;

/// Deeper than any balanced tree over `u32` points: a stored tree deeper than this is
/// malformed (and would recurse without bound).
const MAX_DEPTH: usize = 40;

/// One node in four words. Split: `[axis, right child, low, high]` where the left child
/// follows the node, `low` (f32 bits) is the largest left coordinate and `high` the
/// smallest right coordinate on the axis. Leaf: `[LEAF_TAG, start, end, 0]`, a range of
/// the leaf-ordered points.
pub type NodeWords = [u32; 4];

/// A KD-tree built in this process; item ids are indices into the points it was built
/// from.
#[derive(Debug, Clone)]
pub struct PointTree {
    nodes: Vec<NodeWords>,
    points: Vec<[f32; 3]>,
    items: Vec<u32>,
}

impl PointTree {
    /// The tree's arrays, for searching or archiving.
    pub fn view(&self) -> TreeRef<'_> {
        TreeRef {
            nodes: &self.nodes,
            points: &self.points,
            items: &self.items,
        }
    }

    /// Number of indexed points.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// True for no points (never the case for a built tree).
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }
}

/// A tree's arrays, borrowed from a [`PointTree`] or read in place from a baked map.
#[derive(Debug, Clone, Copy)]
pub struct TreeRef<'a> {
    nodes: &'a [NodeWords],
    points: &'a [[f32; 3]],
    items: &'a [u32],
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
    if points.len() >= u32::MAX as usize {
        return Err(TreeError::TooManyPoints(points.len()));
    }
    if let Some(i) = points.iter().position(|p| p.iter().any(|c| !c.is_finite())) {
        return Err(TreeError::NonFinite(i));
    }
    let BoxTree { nodes, order } = BoxTree::build(points, leaf);
    let words = nodes
        .iter()
        .enumerate()
        .map(|(i, n)| {
            if n.is_leaf() {
                return [LEAF_TAG, n.start, n.end, 0];
            }
            let axis = n.axis as usize;
            let low = nodes[i + 1].max[axis];
            let high = nodes[n.right as usize].min[axis];
            [n.axis, n.right, low.to_bits(), high.to_bits()]
        })
        .collect();
    Ok(PointTree {
        nodes: words,
        points: order.iter().map(|o| o.1).collect(),
        items: order.iter().map(|o| o.0).collect(),
    })
}

impl<'a> TreeRef<'a> {
    /// A tree from stored arrays (e.g. a memory-mapped map), checked to be one: every
    /// node reachable once, in depth-first order, leaves covering the points in order,
    /// items a permutation, depth bounded. Searches on it then never index out of range.
    pub fn from_parts(
        nodes: &'a [NodeWords],
        points: &'a [[f32; 3]],
        items: &'a [u32],
    ) -> Result<Self, TreeError> {
        let tree = Self {
            nodes,
            points,
            items,
        };
        tree.check()?;
        Ok(tree)
    }

    /// Arrays that passed [`TreeRef::from_parts`] before (a memory-mapped map checks
    /// each keyframe once, then reads it many times).
    pub(crate) fn from_checked_parts(
        nodes: &'a [NodeWords],
        points: &'a [[f32; 3]],
        items: &'a [u32],
    ) -> Self {
        Self {
            nodes,
            points,
            items,
        }
    }

    fn check(&self) -> Result<(), TreeError> {
        let malformed = |why: String| Err(TreeError::Malformed(why));
        let n = self.points.len();
        if n == 0 || self.nodes.is_empty() {
            return Err(TreeError::Empty);
        }
        if self.items.len() != n {
            return malformed(format!("{} item ids for {n} points", self.items.len()));
        }
        let mut seen = vec![false; n];
        for &item in self.items {
            match seen.get_mut(item as usize) {
                Some(s) if !*s => *s = true,
                _ => return malformed(format!("item id {item} is out of range or repeated")),
            }
        }
        let mut next_point = 0u32;
        let end = self.check_subtree(0, 0, &mut next_point)?;
        if end != self.nodes.len() || next_point as usize != n {
            return malformed(format!(
                "the nodes reach {end} of {} nodes and {next_point} of {n} points",
                self.nodes.len()
            ));
        }
        Ok(())
    }

    /// Checks the subtree at `node`; returns the index just past it.
    fn check_subtree(
        &self,
        node: usize,
        depth: usize,
        next_point: &mut u32,
    ) -> Result<usize, TreeError> {
        let malformed = |why: String| Err(TreeError::Malformed(why));
        if depth > MAX_DEPTH {
            return malformed(format!("deeper than {MAX_DEPTH} levels"));
        }
        let Some(&[tag, a, b, c]) = self.nodes.get(node) else {
            return malformed(format!("node {node} is missing"));
        };
        if tag == LEAF_TAG {
            if a != *next_point || b <= a || b as usize > self.points.len() {
                return malformed(format!("leaf {node} has a bad point range {a}..{b}"));
            }
            *next_point = b;
            return Ok(node + 1);
        }
        let (low, high) = (f32::from_bits(b), f32::from_bits(c));
        if tag > 2 || low.is_nan() || high.is_nan() {
            return malformed(format!("split node {node} has axis {tag} or a NaN bound"));
        }
        let left_end = self.check_subtree(node + 1, depth + 1, next_point)?;
        if a as usize != left_end {
            return malformed(format!("node {node} links its right child out of order"));
        }
        self.check_subtree(left_end, depth + 1, next_point)
    }

    /// The node array (for archiving).
    pub fn nodes(&self) -> &'a [NodeWords] {
        self.nodes
    }

    /// The points in leaf order (for archiving).
    pub fn points(&self) -> &'a [[f32; 3]] {
        self.points
    }

    /// The item id of each leaf-ordered point (for archiving).
    pub fn items(&self) -> &'a [u32] {
        self.items
    }

    /// Number of indexed points.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// True for no points.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
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

    /// The `n` nearest points, nearest first (ties by item): `(item, squared distance)`.
    pub fn nearest_n(&self, query: &[f32; 3], n: NonZeroUsize) -> Vec<(u32, f32)> {
        let mut best = KNearest {
            k: n.get(),
            hits: Vec::with_capacity(n.get().min(self.len()) + 1),
        };
        self.search(query, &mut best);
        best.hits
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
