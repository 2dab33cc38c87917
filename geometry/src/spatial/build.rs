//! The balanced median-split KD-tree both searches share: nodes in depth-first order
//! over a permuted copy of the points, with each node's bounding box.

/// Subtrees larger than this are built on two threads.
const PARALLEL_BUILD: usize = 8192;

/// One node of a [`BoxTree`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct BoxNode {
    pub min: [f32; 3],
    pub max: [f32; 3],
    /// Range of the node's points in [`BoxTree::order`].
    pub start: u32,
    pub end: u32,
    /// Index of the second child; the first child follows the node. 0 for leaves.
    pub right: u32,
    /// The split axis (widest extent of the box); meaningless for leaves.
    pub axis: u32,
}

impl BoxNode {
    pub fn is_leaf(&self) -> bool {
        self.right == 0
    }
}

/// Nodes plus the points in leaf order with their input indices.
pub(crate) struct BoxTree {
    pub nodes: Vec<BoxNode>,
    pub order: Vec<(u32, [f32; 3])>,
}

impl BoxTree {
    /// Splits at the median of the widest axis (ties by input index, so the tree is the
    /// same for any thread count) until a node holds at most `leaf` points. The left
    /// side of a split gets the median rounded up to a multiple of `align` when that
    /// leaves points on the right, so leaves fill blocks of `align` points.
    pub fn build(points: &[[f32; 3]], leaf: usize, align: usize) -> Self {
        let mut order: Vec<(u32, [f32; 3])> = points
            .iter()
            .enumerate()
            .map(|(i, p)| (i as u32, *p))
            .collect();
        let nodes = build(&mut order, 0, leaf.max(1), align.max(1));
        Self { nodes, order }
    }
}

fn bounds(items: &[(u32, [f32; 3])]) -> ([f32; 3], [f32; 3]) {
    let mut min = [f32::INFINITY; 3];
    let mut max = [f32::NEG_INFINITY; 3];
    for (_, p) in items {
        for a in 0..3 {
            min[a] = min[a].min(p[a]);
            max[a] = max[a].max(p[a]);
        }
    }
    (min, max)
}

/// Builds the subtree over `items` (whose first point has global slot `offset`) in
/// depth-first order; `right` links are relative to the returned vector's start.
fn build(items: &mut [(u32, [f32; 3])], offset: usize, leaf: usize, align: usize) -> Vec<BoxNode> {
    let (min, max) = bounds(items);
    let axis = (0..3)
        .max_by(|&a, &b| (max[a] - min[a]).total_cmp(&(max[b] - min[b])))
        .unwrap_or(0);
    let mut nodes = vec![BoxNode {
        min,
        max,
        start: offset as u32,
        end: (offset + items.len()) as u32,
        right: 0,
        axis: axis as u32,
    }];
    if items.len() <= leaf {
        return nodes;
    }
    let half = items.len() / 2;
    let mid = match half.next_multiple_of(align) {
        aligned if aligned < items.len() => aligned,
        _ => half,
    };
    items.select_nth_unstable_by(mid, |a, b| {
        a.1[axis].total_cmp(&b.1[axis]).then(a.0.cmp(&b.0))
    });
    let (left, right) = items.split_at_mut(mid);
    let (left_nodes, right_nodes) = if mid >= PARALLEL_BUILD {
        rayon::join(
            || build(left, offset, leaf, align),
            || build(right, offset + mid, leaf, align),
        )
    } else {
        (
            build(left, offset, leaf, align),
            build(right, offset + mid, leaf, align),
        )
    };
    let shift = |base: usize, mut n: BoxNode| {
        if n.right != 0 {
            n.right += base as u32;
        }
        n
    };
    let right_start = 1 + left_nodes.len();
    nodes[0].right = right_start as u32;
    nodes.extend(left_nodes.into_iter().map(|n| shift(1, n)));
    nodes.extend(right_nodes.into_iter().map(|n| shift(right_start, n)));
    nodes
}
