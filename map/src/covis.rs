//! Covisibility graph between keyframes, as ORB-SLAM2's (docs/DESIGN.md#covisibility) but for
//! point clouds and symmetric: two keyframes are covisible by the number of occupied
//! voxels (map frame) they share. Also the spanning tree and the essential graph.

use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};

use rustc_hash::FxHashMap;
use serde::{Deserialize, Serialize};

use kfmap_geometry::KeyframeId;
use kfmap_geometry::options::{InvalidOption, ensure};

/// Options of the covisibility graph.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct CovisOptions {
    /// Voxel edge, metres (map frame).
    pub voxel_size: f64,
    /// Edges need at least this many shared voxels (else only the strongest is kept).
    pub min_weight: u32,
    /// Covisibility edges of the essential graph need at least this weight.
    pub essential_min_weight: u32,
}

impl Default for CovisOptions {
    fn default() -> Self {
        Self {
            voxel_size: 1.0,
            min_weight: 15,
            essential_min_weight: 100,
        }
    }
}

impl CovisOptions {
    /// Checks every option; the error names the first bad one.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        let v = self.voxel_size;
        ensure(
            v.is_finite() && v >= 0.01,
            "covis-voxel-size",
            v,
            "a finite size >= 0.01 m",
        )?;
        ensure(
            self.min_weight >= 1,
            "covis-min-weight",
            self.min_weight,
            "an integer >= 1",
        )
    }
}

type Voxel = [i64; 3];

/// The graph's edges and spanning tree, without the voxel index (stored in baked maps).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct CovisSnapshot {
    /// Every keyframe of the graph, ascending.
    pub keyframes: Vec<KeyframeId>,
    /// Undirected edges `(a, b, weight)`, `a < b`, ascending.
    pub edges: Vec<(KeyframeId, KeyframeId, u32)>,
    /// Spanning tree `(child, parent)`, ascending.
    pub parents: Vec<(KeyframeId, KeyframeId)>,
    /// Keyframes that joined the spanning tree (roots included), ascending.
    pub in_tree: Vec<KeyframeId>,
}

impl CovisSnapshot {
    /// The part of the graph among `ids` (ascending): the keyframes, edges and tree links
    /// with every end in `ids`. Edge weights count voxels two keyframes share, whoever
    /// else is in the graph, so a tile keeps the whole map's edges among its keyframes
    /// without recounting them.
    pub fn restricted_to(&self, ids: &[KeyframeId]) -> CovisSnapshot {
        let kept = |id: &KeyframeId| ids.binary_search(id).is_ok();
        let listed = |list: &[KeyframeId]| -> Vec<KeyframeId> {
            ids.iter()
                .copied()
                .filter(|id| list.binary_search(id).is_ok())
                .collect()
        };
        // Looked up per keyframe of `ids` (edges ascend by their lower end, tree links by
        // child): a tile's cut costs its own keyframes, not the whole map's edges.
        let mut edges = Vec::new();
        for &a in ids {
            let from = self.edges.partition_point(|e| e.0 < a);
            let to = from + self.edges[from..].partition_point(|e| e.0 == a);
            edges.extend(self.edges[from..to].iter().filter(|e| kept(&e.1)));
        }
        let parents = ids
            .iter()
            .filter_map(|&c| {
                let at = self.parents.partition_point(|l| l.0 < c);
                self.parents
                    .get(at)
                    .filter(|l| l.0 == c && kept(&l.1))
                    .copied()
            })
            .collect();
        CovisSnapshot {
            keyframes: listed(&self.keyframes),
            edges,
            parents,
            in_tree: listed(&self.in_tree),
        }
    }
}

/// The covisibility graph with its inverted voxel index and spanning tree.
#[derive(Debug, Clone, Default)]
pub struct CovisibilityGraph {
    options: CovisOptions,
    voxels: FxHashMap<KeyframeId, Vec<Voxel>>,
    /// Keyframes occupying each voxel, ascending (a Vec: most voxels hold a few ids).
    index: FxHashMap<Voxel, Vec<KeyframeId>>,
    /// Symmetric: `edges[a][b] == edges[b][a]` for every kept edge.
    edges: HashMap<KeyframeId, BTreeMap<KeyframeId, u32>>,
    /// Each keyframe's own fallback: its strongest partner, when none reaches
    /// `min_weight`. An edge below the threshold exists iff it is one end's fallback.
    fallback: HashMap<KeyframeId, KeyframeId>,
    parent: HashMap<KeyframeId, KeyframeId>,
    children: HashMap<KeyframeId, BTreeSet<KeyframeId>>,
    /// Keyframes that joined the tree (a parent, or the first keyframe = root).
    in_tree: HashSet<KeyframeId>,
}

impl CovisibilityGraph {
    /// An empty graph; `options` must be valid.
    pub fn new(options: CovisOptions) -> Self {
        Self {
            options,
            ..Self::default()
        }
    }

    /// The graph's options.
    pub fn options(&self) -> &CovisOptions {
        &self.options
    }

    /// Number of keyframes.
    pub fn len(&self) -> usize {
        self.edges.len()
    }

    /// True with no keyframes.
    pub fn is_empty(&self) -> bool {
        self.edges.is_empty()
    }

    /// The graph without its voxel index: what a baked map stores.
    pub fn snapshot(&self) -> CovisSnapshot {
        let mut parents: Vec<(KeyframeId, KeyframeId)> =
            self.parent.iter().map(|(&c, &p)| (c, p)).collect();
        parents.sort_unstable();
        let mut in_tree: Vec<KeyframeId> = self.in_tree.iter().copied().collect();
        in_tree.sort_unstable();
        let mut keyframes: Vec<KeyframeId> = self.edges.keys().copied().collect();
        keyframes.sort_unstable();
        CovisSnapshot {
            keyframes,
            edges: self
                .edges()
                .into_iter()
                .map(|((a, b), w)| (a, b, w))
                .collect(),
            parents,
            in_tree,
        }
    }

    /// A graph with the edges and spanning tree of `snapshot` and no voxel index yet:
    /// call [`restore_voxels`](Self::restore_voxels) for every keyframe before changing it.
    pub fn from_snapshot(options: CovisOptions, snapshot: &CovisSnapshot) -> Self {
        let mut graph = Self::new(options);
        for &id in &snapshot.keyframes {
            graph.edges.insert(id, BTreeMap::new());
        }
        for &(a, b, w) in &snapshot.edges {
            graph.edges.entry(a).or_default().insert(b, w);
            graph.edges.entry(b).or_default().insert(a, w);
        }
        // A stored row without a thresholded edge holds its keyframe's fallback, which is
        // the strongest partner overall and hence the row's strongest.
        let threshold = options.min_weight;
        for (&id, row) in &graph.edges {
            if row.values().all(|&w| w < threshold)
                && let Some((&best, _)) = strongest(row)
            {
                graph.fallback.insert(id, best);
            }
        }
        for &(child, parent) in &snapshot.parents {
            graph.attach(child, parent);
        }
        graph.in_tree.extend(snapshot.in_tree.iter().copied());
        graph
    }

    /// Puts keyframe `id`'s voxels back into the index without touching its edges.
    pub fn restore_voxels(
        &mut self,
        id: KeyframeId,
        map_points: impl IntoIterator<Item = [f64; 3]>,
    ) {
        self.drop_voxels(id);
        let mut set: Vec<Voxel> = map_points.into_iter().map(|p| self.voxel_of(&p)).collect();
        set.sort_unstable();
        set.dedup();
        set.shrink_to_fit();
        for v in &set {
            let ids = self.index.entry(*v).or_default();
            if let Err(at) = ids.binary_search(&id) {
                ids.insert(at, id);
            }
        }
        self.voxels.insert(id, set);
    }

    fn voxel_of(&self, p: &[f64; 3]) -> Voxel {
        p.map(|c| (c / self.options.voxel_size).floor() as i64)
    }

    /// Adds keyframe `id` (or replaces its points after a pose change) with its points
    /// in the map frame, then updates its connections.
    pub fn set_keyframe(&mut self, id: KeyframeId, map_points: impl IntoIterator<Item = [f64; 3]>) {
        self.restore_voxels(id, map_points);
        if self.in_tree.is_empty() {
            self.in_tree.insert(id); // The first keyframe is the root.
        }
        self.update_connections(id);
    }

    fn drop_voxels(&mut self, id: KeyframeId) {
        for v in self.voxels.remove(&id).unwrap_or_default() {
            if let Some(ids) = self.index.get_mut(&v) {
                ids.retain(|&k| k != id);
                if ids.is_empty() {
                    self.index.remove(&v);
                }
            }
        }
    }

    /// Shared-voxel counts between `id` and every other keyframe sharing any voxel.
    pub fn shared_voxels(&self, id: KeyframeId) -> BTreeMap<KeyframeId, u32> {
        let mut counts = BTreeMap::new();
        for v in self.voxels.get(&id).into_iter().flatten() {
            for &other in &self.index[v] {
                if other != id {
                    *counts.entry(other).or_insert(0) += 1;
                }
            }
        }
        counts
    }

    /// Recomputes every edge of `id` from the voxel index: edges with weight >= the
    /// threshold, or the single strongest when none qualifies; mirrored on both ends.
    /// Every keyframe whose shared-voxel count with `id` changed gets its own fallback
    /// recomputed too, so an edge below the threshold survives as long as it is either
    /// end's strongest (the graph equals one built from scratch).
    /// The first time `id` gets an edge to a keyframe of the spanning tree it joins the
    /// tree under the strongest such neighbour.
    pub fn update_connections(&mut self, id: KeyframeId) {
        let counts = self.shared_voxels(id);
        let previous = self.detach_edges(id);
        let threshold = self.options.min_weight;
        let mut row: BTreeMap<KeyframeId, u32> = counts
            .iter()
            .filter(|&(_, &w)| w >= threshold)
            .map(|(&k, &w)| (k, w))
            .collect();
        match strongest(&counts).filter(|_| row.is_empty()) {
            Some((&k, &w)) => {
                row.insert(k, w);
                self.fallback.insert(id, k);
            }
            None => {
                self.fallback.remove(&id);
            }
        }
        for (&other, &w) in &row {
            self.edges.entry(other).or_default().insert(id, w);
        }
        self.edges.insert(id, row);
        // Old partners (their count with `id` may have dropped) and new ones (it may have
        // risen): their fallbacks depend on it; everyone else's counts are unchanged.
        let affected: BTreeSet<KeyframeId> =
            previous.keys().chain(counts.keys()).copied().collect();
        for other in affected {
            self.refresh_fallback(other);
        }
        if !self.in_tree.contains(&id) {
            // Only under a keyframe already in the tree: an outsider has no subtree, so
            // attaching it can never close a cycle.
            let in_tree: BTreeMap<KeyframeId, u32> = self.edges[&id]
                .iter()
                .filter(|(k, _)| self.in_tree.contains(k))
                .map(|(&k, &w)| (k, w))
                .collect();
            if let Some((&best, _)) = strongest(&in_tree) {
                self.attach(id, best);
            }
        }
    }

    /// Removes `id`'s row and its mirror entries; returns the row.
    fn detach_edges(&mut self, id: KeyframeId) -> BTreeMap<KeyframeId, u32> {
        let row = self.edges.remove(&id).unwrap_or_default();
        for other in row.keys() {
            if let Some(other_row) = self.edges.get_mut(other) {
                other_row.remove(&id);
            }
        }
        row
    }

    /// Recomputes keyframe `id`'s own fallback after one of its counts changed: drops the
    /// old fallback edge unless the other end still wants it, adds the new one.
    fn refresh_fallback(&mut self, id: KeyframeId) {
        let threshold = self.options.min_weight;
        let Some(row) = self.edges.get(&id) else {
            return; // Removed, or not added yet.
        };
        // Every partner at or above the threshold already has an edge, so a thresholded
        // edge in the row settles it without recounting.
        let wanted = if row.values().any(|&w| w >= threshold) {
            None
        } else {
            let counts = self.shared_voxels(id);
            strongest(&counts)
                .filter(|&(_, &w)| w < threshold)
                .map(|(&k, &w)| (k, w))
        };
        let old = self.fallback.get(&id).copied();
        if let Some(old) = old.filter(|&o| Some(o) != wanted.map(|(k, _)| k)) {
            let kept = self.weight(id, old) >= threshold || self.fallback.get(&old) == Some(&id);
            if !kept {
                self.unlink(id, old);
            }
        }
        match wanted {
            Some((k, w)) => {
                self.fallback.insert(id, k);
                self.edges.entry(id).or_default().insert(k, w);
                self.edges.entry(k).or_default().insert(id, w);
            }
            None => {
                self.fallback.remove(&id);
            }
        }
    }

    fn unlink(&mut self, a: KeyframeId, b: KeyframeId) {
        for (x, y) in [(a, b), (b, a)] {
            if let Some(row) = self.edges.get_mut(&x) {
                row.remove(&y);
            }
        }
    }

    fn attach(&mut self, child: KeyframeId, parent: KeyframeId) {
        self.parent.insert(child, parent);
        self.children.entry(parent).or_default().insert(child);
        self.in_tree.insert(child);
    }

    /// Removes keyframe `id`: its voxels, its edges on both ends (a neighbour that loses
    /// its fallback edge gets one to its next strongest partner), and its tree node;
    /// its children are re-parented greedily (ORB-SLAM2 `SetBadFlag`): repeatedly the
    /// child with the strongest edge to a candidate (the removed keyframe's parent,
    /// then every re-attached child) joins that candidate; the rest join the removed
    /// keyframe's parent (or become roots when it had none).
    pub fn remove_keyframe(&mut self, id: KeyframeId) {
        self.drop_voxels(id);
        let previous = self.detach_edges(id);
        self.fallback.remove(&id);
        // A neighbour whose only edge was to `id` falls back on its next strongest
        // partner; done before re-parenting so that the children see the true graph.
        for &other in previous.keys() {
            self.refresh_fallback(other);
        }
        let parent = self.parent.remove(&id);
        if let Some(siblings) = parent.and_then(|p| self.children.get_mut(&p)) {
            siblings.remove(&id);
        }
        self.in_tree.remove(&id);
        let mut orphans: BTreeSet<KeyframeId> = self.children.remove(&id).unwrap_or_default();
        for c in &orphans {
            self.parent.remove(c);
        }
        let mut candidates: BTreeSet<KeyframeId> = parent.into_iter().collect();
        loop {
            // Strongest (child, candidate) edge; ties: lower child id, then lower candidate id.
            let mut best: Option<(u32, KeyframeId, KeyframeId)> = None;
            for &c in &orphans {
                for (&n, &w) in self.edges.get(&c).into_iter().flatten() {
                    if candidates.contains(&n) && best.is_none_or(|(bw, _, _)| w > bw) {
                        best = Some((w, c, n));
                    }
                }
            }
            let Some((_, child, new_parent)) = best else {
                break;
            };
            self.attach(child, new_parent);
            orphans.remove(&child);
            candidates.insert(child);
        }
        for c in orphans {
            match parent {
                Some(p) => self.attach(c, p),
                None => {
                    self.in_tree.insert(c); // Root removed: its unattached children become roots.
                }
            }
        }
    }

    /// Edge weight between two keyframes (0 when not connected).
    pub fn weight(&self, a: KeyframeId, b: KeyframeId) -> u32 {
        self.edges
            .get(&a)
            .and_then(|row| row.get(&b))
            .copied()
            .unwrap_or(0)
    }

    /// Neighbours of `id` by weight, descending (ties: lower id first).
    pub fn ordered_neighbours(&self, id: KeyframeId) -> Vec<(KeyframeId, u32)> {
        let mut row: Vec<(KeyframeId, u32)> = self
            .edges
            .get(&id)
            .into_iter()
            .flatten()
            .map(|(&k, &w)| (k, w))
            .collect();
        row.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
        row
    }

    /// The `n` best covisible keyframes of `id`.
    pub fn best_covisible(&self, id: KeyframeId, n: usize) -> Vec<KeyframeId> {
        self.ordered_neighbours(id)
            .into_iter()
            .take(n)
            .map(|(k, _)| k)
            .collect()
    }

    /// Neighbours of `id` with weight >= `w`, strongest first (all of them when all
    /// qualify).
    pub fn covisible_by_weight(&self, id: KeyframeId, w: u32) -> Vec<KeyframeId> {
        self.ordered_neighbours(id)
            .into_iter()
            .take_while(|&(_, weight)| weight >= w)
            .map(|(k, _)| k)
            .collect()
    }

    /// Parent of `id` in the spanning tree.
    pub fn parent(&self, id: KeyframeId) -> Option<KeyframeId> {
        self.parent.get(&id).copied()
    }

    /// Children of `id` in the spanning tree, ascending.
    pub fn children(&self, id: KeyframeId) -> Vec<KeyframeId> {
        self.children
            .get(&id)
            .map(|c| c.iter().copied().collect())
            .unwrap_or_default()
    }

    /// Undirected edges `(a, b)`, `a < b`: the spanning tree plus covisibility edges
    /// with weight >= `essential_min_weight`.
    pub fn essential_graph(&self) -> BTreeSet<(KeyframeId, KeyframeId)> {
        let ordered = |a: KeyframeId, b: KeyframeId| (a.min(b), a.max(b));
        let mut out: BTreeSet<(KeyframeId, KeyframeId)> =
            self.parent.iter().map(|(&c, &p)| ordered(c, p)).collect();
        for (&a, row) in &self.edges {
            out.extend(
                row.iter()
                    .filter(|&(_, &w)| w >= self.options.essential_min_weight)
                    .map(|(&b, _)| ordered(a, b)),
            );
        }
        out
    }

    /// Every stored undirected edge with its weight, `a < b`.
    pub fn edges(&self) -> BTreeMap<(KeyframeId, KeyframeId), u32> {
        let mut out = BTreeMap::new();
        for (&a, row) in &self.edges {
            for (&b, &w) in row {
                out.insert((a.min(b), a.max(b)), w);
            }
        }
        out
    }
}

/// Highest weight; ties: lowest id.
fn strongest(row: &BTreeMap<KeyframeId, u32>) -> Option<(&KeyframeId, &u32)> {
    row.iter().max_by(|a, b| a.1.cmp(b.1).then(b.0.cmp(a.0)))
}

#[cfg(test)]
mod tests;
