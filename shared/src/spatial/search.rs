//! Nearest-neighbour searches on a [`TreeRef`]: one descent (nearer child first, the
//! other child only when the incremental box distance can still beat the current
//! bound), three ways of collecting what the leaves offer.

use super::{LEAF_TAG, TreeRef};

/// Slack on the pruning test: the incremental box distance is a lower bound up to f32
/// rounding, and a point exactly on the bound must still be found (ties by index).
const PRUNE_SLACK: f32 = 1.0 - 1e-6;

/// What a search keeps of the points the leaves offer.
pub(super) trait Collector {
    /// Points farther than this (squared) cannot enter.
    fn bound(&self) -> f32;
    /// A point within the bound.
    fn offer(&mut self, dist_sq: f32, item: u32);
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
            item: u32::MAX,
        }
    }

    pub fn found(&self) -> Option<(u32, f32)> {
        (self.item != u32::MAX).then_some((self.item, self.dist_sq))
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
}

/// The `k` nearest points, sorted by (squared distance, item).
pub(super) struct KNearest {
    pub k: usize,
    pub hits: Vec<(u32, f32)>,
}

impl Collector for KNearest {
    fn bound(&self) -> f32 {
        if self.hits.len() < self.k {
            f32::INFINITY
        } else {
            self.hits[self.k - 1].1
        }
    }

    fn offer(&mut self, dist_sq: f32, item: u32) {
        let before = |h: &(u32, f32)| h.1 < dist_sq || (h.1 == dist_sq && h.0 < item);
        let at = self.hits.partition_point(before);
        if at < self.k {
            if self.hits.len() == self.k {
                self.hits.pop();
            }
            self.hits.insert(at, (item, dist_sq));
        }
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

impl TreeRef<'_> {
    /// Offers every point of the tree that can be within `collector`'s bound.
    #[inline]
    pub(super) fn search<C: Collector>(&self, query: &[f32; 3], collector: &mut C) {
        let mut axis_dist = [0.0f32; 3];
        self.descend(0, query, 0.0, &mut axis_dist, collector);
    }

    /// `min_dist_sq` is a lower bound on the squared distance from `query` to any point
    /// under `node`, the sum of `axis_dist` (per-axis squared gaps to the node's cell).
    fn descend<C: Collector>(
        &self,
        node: usize,
        query: &[f32; 3],
        min_dist_sq: f32,
        axis_dist: &mut [f32; 3],
        collector: &mut C,
    ) {
        let [tag, a, b, c] = self.nodes[node];
        if tag == LEAF_TAG {
            let range = a as usize..b as usize;
            for (p, &item) in self.points[range.clone()].iter().zip(&self.items[range]) {
                let d = (p[0] - query[0]) * (p[0] - query[0])
                    + (p[1] - query[1]) * (p[1] - query[1])
                    + (p[2] - query[2]) * (p[2] - query[2]);
                if d <= collector.bound() {
                    collector.offer(d, item);
                }
            }
            return;
        }
        let axis = tag as usize;
        let (low, high) = (f32::from_bits(b), f32::from_bits(c));
        let v = query[axis];
        let (below, above) = (v - low, v - high);
        // Nearer child first; the gap to the other child's cell along the split axis.
        let (near, far, gap) = if below + above < 0.0 {
            (node + 1, a as usize, above * above)
        } else {
            (a as usize, node + 1, below * below)
        };
        self.descend(near, query, min_dist_sq, axis_dist, collector);
        let saved = axis_dist[axis];
        let far_dist_sq = min_dist_sq + gap - saved;
        if far_dist_sq * PRUNE_SLACK <= collector.bound() {
            axis_dist[axis] = gap;
            self.descend(far, query, far_dist_sq, axis_dist, collector);
            axis_dist[axis] = saved;
        }
    }
}
