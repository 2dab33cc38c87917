//! Nearest-neighbour searches on a [`TreeRef`]: one descent (nearer child first, the
//! other child only when the incremental box distance can still beat the current
//! bound), three ways of collecting what the leaves offer (and [`Counted`], which
//! counts the work of any of them).

use std::mem::MaybeUninit;

use super::{
    LANES, LEAF_TAG, MAX_DEPTH, PAD_ITEM, PointBlock, TreeRef, point_dist_sq, rank, rank_dist_sq,
    rank_item,
};

/// What a search keeps of the points the leaves offer.
pub(super) trait Collector {
    /// Points farther than this (squared) cannot enter.
    fn bound(&self) -> f32;
    /// A point within the bound.
    fn offer(&mut self, dist_sq: f32, item: u32);
    /// The points of one block (`block`, their coordinates), at least one of them
    /// within the bound (NaN lanes are padding).
    #[inline(always)]
    fn offer_block(&mut self, dist_sq: &[f32; LANES], items: &[u32], _block: &PointBlock) {
        for (&d, &item) in dist_sq.iter().zip(items) {
            if d <= self.bound() {
                self.offer(d, item);
            }
        }
    }
    /// The search reads a node (counted by [`Counted`]).
    #[inline(always)]
    fn visit_node(&mut self) {}
    /// The search computes the distances of one block of points (counted by [`Counted`]).
    #[inline(always)]
    fn scan_block(&mut self) {}
}

/// Another collector, counting the nodes and blocks the search reads.
pub(super) struct Counted<C> {
    pub inner: C,
    pub nodes: usize,
    pub blocks: usize,
}

impl<C: Collector> Collector for Counted<C> {
    fn bound(&self) -> f32 {
        self.inner.bound()
    }

    fn offer(&mut self, dist_sq: f32, item: u32) {
        self.inner.offer(dist_sq, item);
    }

    fn offer_block(&mut self, dist_sq: &[f32; LANES], items: &[u32], block: &PointBlock) {
        self.inner.offer_block(dist_sq, items, block);
    }

    fn visit_node(&mut self) {
        self.nodes += 1;
    }

    fn scan_block(&mut self) {
        self.blocks += 1;
    }
}

/// The single nearest point within an inclusive bound; ties by smaller item.
pub(super) struct Nearest {
    pub dist_sq: f32,
    pub item: u32,
}

impl Nearest {
    pub fn within(bound_sq: f32) -> Self {
        Self {
            dist_sq: bound_sq,
            item: PAD_ITEM,
        }
    }

    pub fn found(&self) -> Option<(u32, f32)> {
        (self.item != PAD_ITEM).then_some((self.item, self.dist_sq))
    }
}

impl Collector for Nearest {
    #[inline(always)]
    fn bound(&self) -> f32 {
        self.dist_sq
    }

    #[inline(always)]
    fn offer(&mut self, dist_sq: f32, item: u32) {
        if dist_sq < self.dist_sq || (dist_sq == self.dist_sq && item < self.item) {
            self.dist_sq = dist_sq;
            self.item = item;
        }
    }

    /// Without a branch per lane: the block's smallest distance, then the smallest
    /// item at that distance.
    #[inline(always)]
    fn offer_block(&mut self, dist_sq: &[f32; LANES], items: &[u32], _block: &PointBlock) {
        let nearest = dist_sq
            .iter()
            .fold(f32::INFINITY, |m, &d| if d < m { d } else { m });
        let item =
            dist_sq.iter().zip(items).fold(
                PAD_ITEM,
                |m, (&d, &i)| if d == nearest { m.min(i) } else { m },
            );
        self.offer(nearest, item);
    }
}

/// [`Nearest`] that also keeps the point's coordinates as the tree stores them: a
/// caller that needs them reads no other array (a cache miss per query in the map
/// server). Only this collector pays for finding the lane.
pub(super) struct NearestAt {
    pub nearest: Nearest,
    pub point: [f32; 3],
}

impl Collector for NearestAt {
    #[inline(always)]
    fn bound(&self) -> f32 {
        self.nearest.bound()
    }

    /// Never called by a search, which offers whole blocks (below); a point offered
    /// alone has no coordinates here (NaN).
    fn offer(&mut self, dist_sq: f32, item: u32) {
        self.nearest.offer(dist_sq, item);
        self.point = [f32::NAN; 3];
    }

    #[inline(always)]
    fn offer_block(&mut self, dist_sq: &[f32; LANES], items: &[u32], block: &PointBlock) {
        let before = self.nearest.item;
        self.nearest.offer_block(dist_sq, items, block);
        let taken = self.nearest.item;
        // Items are unique in a tree: a new best is in this block, at one lane.
        if taken != before
            && let Some(lane) = items.iter().position(|&i| i == taken)
        {
            self.point = [block[0][lane], block[1][lane], block[2][lane]];
        }
    }
}

/// The nearest point within an inclusive bound, with its coordinates, and the runner-up
/// (by the same order, (squared distance, item)); a slot not filled ranks as the bound
/// with [`PAD_ITEM`]. The runner-up's distance tells a caller that the nearest stays the
/// nearest for a query moved less than its lead.
pub(super) struct NearestTwo {
    pub first: u64,
    pub second: u64,
    pub point: [f32; 3],
}

impl NearestTwo {
    pub fn within(bound_sq: f32) -> Self {
        Self {
            first: rank(bound_sq, PAD_ITEM),
            second: rank(bound_sq, PAD_ITEM),
            point: [f32::NAN; 3],
        }
    }

    /// Takes `new` (with coordinates `point`) as the nearest or the runner-up.
    #[inline(always)]
    fn take(&mut self, new: u64, point: [f32; 3]) {
        if new < self.first {
            self.second = self.first;
            self.first = new;
            self.point = point;
        } else if new < self.second {
            self.second = new;
        }
    }
}

impl Collector for NearestTwo {
    #[inline(always)]
    fn bound(&self) -> f32 {
        rank_dist_sq(self.second)
    }

    /// Never called by a search, which offers whole blocks (below); a point offered
    /// alone has no coordinates here (NaN).
    fn offer(&mut self, dist_sq: f32, item: u32) {
        self.take(rank(dist_sq, item), [f32::NAN; 3]);
    }

    #[inline(always)]
    fn offer_block(&mut self, dist_sq: &[f32; LANES], items: &[u32], block: &PointBlock) {
        for lane in 0..LANES {
            let d = dist_sq[lane];
            // NaN lanes (padding) compare false.
            if d <= self.bound() {
                let point = [block[0][lane], block[1][lane], block[2][lane]];
                self.take(rank(d, items[lane]), point);
            }
        }
    }
}

/// The `k` nearest points, sorted by (squared distance, item). Slots not yet filled
/// rank as the bound (infinite unless given) with [`PAD_ITEM`].
pub(super) struct KNearest {
    ranks: Vec<u64>,
}

impl KNearest {
    /// The `k` nearest with squared distance at most `bound_sq` (inclusive).
    pub fn within(k: usize, bound_sq: f32) -> Self {
        Self {
            ranks: vec![rank(bound_sq, PAD_ITEM); k],
        }
    }

    pub fn hits(self) -> Vec<(u32, f32)> {
        self.ranks
            .into_iter()
            .map(|r| (rank_item(r), rank_dist_sq(r)))
            .filter(|&(item, _)| item != PAD_ITEM)
            .collect()
    }
}

impl Collector for KNearest {
    #[inline(always)]
    fn bound(&self) -> f32 {
        rank_dist_sq(self.ranks[self.ranks.len() - 1])
    }

    #[inline]
    fn offer(&mut self, dist_sq: f32, item: u32) {
        let new = rank(dist_sq, item);
        let ranks = &mut self.ranks[..];
        let mut at = ranks.len() - 1;
        if new >= ranks[at] {
            return;
        }
        // Shift the worse tail one slot back, dropping the last.
        while at > 0 && ranks[at - 1] > new {
            ranks[at] = ranks[at - 1];
            at -= 1;
        }
        ranks[at] = new;
    }
}

/// Every point within an inclusive squared radius, unsorted until [`Within::sorted`].
pub(super) struct Within {
    pub radius_sq: f32,
    pub hits: Vec<(u32, f32)>,
}

impl Within {
    pub fn sorted(mut self) -> Vec<(u32, f32)> {
        self.hits
            .sort_unstable_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
        self.hits
    }
}

impl Collector for Within {
    fn bound(&self) -> f32 {
        self.radius_sq
    }

    fn offer(&mut self, dist_sq: f32, item: u32) {
        self.hits.push((item, dist_sq));
    }
}

/// A subtree still to visit: its node, a lower bound on the squared distance from the
/// query to its points, and the per-axis squared gaps to its cell that sum to it.
#[derive(Debug, Clone, Copy)]
struct Pending {
    node: u32,
    min_dist_sq: f32,
    axis_dist: [f32; 3],
}

impl TreeRef<'_> {
    /// Offers every point of the tree that can be within `collector`'s bound: down the
    /// nearer children to a leaf, the farther ones kept on a stack and visited while
    /// their cell can still beat the bound.
    #[inline]
    pub(super) fn search<C: Collector>(&self, query: &[f32; 3], collector: &mut C) {
        // A checked tree is at most MAX_DEPTH deep; the stack holds one far child per
        // level of the current path. Left uninitialized: zeroing it costs more than a
        // short search.
        let mut stack = [const { MaybeUninit::<Pending>::uninit() }; MAX_DEPTH + 1];
        let mut pending = 0;
        let mut next = Pending {
            node: 0,
            min_dist_sq: 0.0,
            axis_dist: [0.0; 3],
        };
        loop {
            let Pending {
                mut node,
                min_dist_sq,
                axis_dist,
            } = next;
            while min_dist_sq <= collector.bound() {
                collector.visit_node();
                let [tag, a, b, c] = self.nodes[node as usize];
                if tag == LEAF_TAG {
                    for block in a as usize..b as usize {
                        self.scan_block(block, query, collector);
                    }
                    break;
                }
                let axis = tag as usize;
                let (low, high) = (f32::from_bits(b), f32::from_bits(c));
                let v = query[axis];
                let (below, above) = (v - low, v - high);
                // Nearer child first; the gap to the other child's cell along the axis.
                let (near, far, gap) = if below + above < 0.0 {
                    (node + 1, a, above * above)
                } else {
                    (a, node + 1, below * below)
                };
                let mut far_axis_dist = axis_dist;
                far_axis_dist[axis] = gap;
                // Summed in the order a point's distance is, from per-axis terms no
                // larger than that point's: never above it, even after rounding.
                let [gx, gy, gz] = far_axis_dist;
                let far_dist_sq = gx + gy + gz;
                if far_dist_sq <= collector.bound() {
                    stack[pending].write(Pending {
                        node: far,
                        min_dist_sq: far_dist_sq,
                        axis_dist: far_axis_dist,
                    });
                    pending += 1;
                }
                node = near;
            }
            if pending == 0 {
                return;
            }
            pending -= 1;
            // SAFETY: every slot below `pending` was written by a push above (the
            // bounds-checked `write`: at most one far child per level, MAX_DEPTH levels).
            next = unsafe { stack[pending].assume_init_read() };
        }
    }

    /// Offers the points of one block within the bound. The distances are computed for
    /// all lanes at once (the loop vectorizes); most blocks offer nothing.
    #[inline(always)]
    fn scan_block<C: Collector>(&self, block: usize, query: &[f32; 3], collector: &mut C) {
        collector.scan_block();
        let [xs, ys, zs] = &self.blocks[block];
        let mut dist_sq = [0.0f32; LANES];
        for lane in 0..LANES {
            dist_sq[lane] = point_dist_sq(&[xs[lane], ys[lane], zs[lane]], query);
        }
        let bound = collector.bound();
        // NaN lanes (padding) compare false.
        if !dist_sq.iter().fold(false, |any, &d| any | (d <= bound)) {
            return;
        }
        collector.offer_block(
            &dist_sq,
            &self.items[block * LANES..][..LANES],
            &self.blocks[block],
        );
    }
}
