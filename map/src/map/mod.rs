//! The keyframe map, as MOLA `KeyframePointCloudMap` (docs/DESIGN.md#keyframe-map):
//! keyframes with local trees and covariances, active-set selection, nearest-neighbour
//! and cov2cov queries in exact (merged submap) or approximate (per-keyframe) mode,
//! eviction, and a covisibility graph kept up to date.

mod active;
mod keyframe;
mod options;

use std::collections::BTreeMap;
use std::sync::Arc;

pub use active::{
    ActiveFrame, ActiveSet, MapHit, MergedSubmap, NearestMemo, NearestMemos, Pairing,
};
pub(crate) use keyframe::weights_problem;
pub use keyframe::{HeapKeyframe, Keyframe, KeyframeDecider, KeyframeView};
pub use options::{ActiveSetMode, Cov2CovMode, KeyframeMapOptions};

use crate::archive::ArchiveError;
use crate::covis::CovisibilityGraph;
use crate::select::{SelectionOptions, rank, select_active};
use kfmap_geometry::KeyframeId;
use kfmap_geometry::cloud::{CloudError, PointCloud};
use kfmap_geometry::geometry::{Pose, translation_distance};
use kfmap_geometry::options::InvalidOption;
use kfmap_geometry::spatial::TreeError;

/// Why a map operation failed.
#[derive(Debug, thiserror::Error)]
pub enum MapError {
    /// An option is out of range.
    #[error(transparent)]
    Options(#[from] InvalidOption),
    /// No keyframe has this id (never existed, removed or evicted).
    #[error("no keyframe with id {0}")]
    UnknownKeyframe(KeyframeId),
    /// The cloud is unusable (non-finite point, attribute lengths).
    #[error("bad cloud: {0}")]
    Cloud(#[from] CloudError),
    /// The cloud is empty or could not be indexed.
    #[error("bad cloud: {0}")]
    Tree(#[from] TreeError),
    /// A baked keyframe failed verification, or the map file is unusable.
    #[error(transparent)]
    Archive(#[from] ArchiveError),
    /// A keyframe id below the next free id (ids are never reused).
    #[error("keyframe id {0} is already used or below the next free id")]
    IdTaken(KeyframeId),
    /// The map has no keyframes to answer from.
    #[error("the map has no keyframes")]
    Empty,
    /// Given query covariances do not match the scan.
    #[error("{given} query covariances given for a scan of {points} points")]
    CovarianceCount {
        /// Covariances given.
        given: usize,
        /// Points in the scan.
        points: usize,
    },
}

/// A keyframe point-cloud map.
#[derive(Debug, Clone)]
pub struct KeyframeMap {
    options: KeyframeMapOptions,
    keyframes: BTreeMap<KeyframeId, Keyframe>,
    next_id: KeyframeId,
    covis: CovisibilityGraph,
    evicted: Vec<KeyframeId>,
    /// Exact mode: the merged submap of the last active set.
    merged: Option<Arc<MergedSubmap>>,
    merged_rebuilds: usize,
    /// False for a map opened from a file until its first change: the covisibility
    /// voxel index is rebuilt from the points only when a change needs it.
    covis_index_ready: bool,
}

impl KeyframeMap {
    /// An empty map with validated options.
    pub fn new(options: KeyframeMapOptions) -> Result<Self, MapError> {
        options.validate()?;
        Ok(Self {
            options,
            keyframes: BTreeMap::new(),
            next_id: 0,
            covis: CovisibilityGraph::new(options.covisibility),
            evicted: Vec::new(),
            merged: None,
            merged_rebuilds: 0,
            covis_index_ready: true,
        })
    }

    /// A map from loaded parts (a baked file): the covisibility graph has its edges and
    /// spanning tree but no voxel index yet.
    pub(crate) fn from_parts(
        options: KeyframeMapOptions,
        keyframes: Vec<Keyframe>,
        next_id: KeyframeId,
        covis: CovisibilityGraph,
    ) -> Self {
        Self {
            options,
            keyframes: keyframes.into_iter().map(|k| (k.id, k)).collect(),
            next_id,
            covis,
            evicted: Vec::new(),
            merged: None,
            merged_rebuilds: 0,
            covis_index_ready: false,
        }
    }

    /// Id the next inserted keyframe gets.
    pub fn next_id(&self) -> KeyframeId {
        self.next_id
    }

    /// Switches between exact (merged submap) and approximate (per-keyframe) cov2cov.
    pub fn set_approximate_cov(&mut self, approximate: bool) {
        self.options.approximate_cov = approximate;
        self.merged = None;
    }

    /// Total points over all keyframes.
    pub fn point_count(&self) -> usize {
        self.keyframes.values().map(Keyframe::len).sum()
    }

    /// Rebuilds the covisibility voxel index of a loaded map before its first change.
    fn ensure_covis_index(&mut self) -> Result<(), MapError> {
        if !self.covis_index_ready {
            for k in self.keyframes.values() {
                self.covis.restore_voxels(k.id, k.map_points()?);
            }
            self.covis_index_ready = true;
        }
        Ok(())
    }

    /// The map's options.
    pub fn options(&self) -> &KeyframeMapOptions {
        &self.options
    }

    /// Number of keyframes.
    pub fn len(&self) -> usize {
        self.keyframes.len()
    }

    /// True with no keyframes.
    pub fn is_empty(&self) -> bool {
        self.keyframes.is_empty()
    }

    /// A keyframe by id.
    pub fn keyframe(&self, id: KeyframeId) -> Option<&Keyframe> {
        self.keyframes.get(&id)
    }

    /// All keyframes, ascending id.
    pub fn keyframes(&self) -> impl Iterator<Item = &Keyframe> {
        self.keyframes.values()
    }

    /// The covisibility graph.
    pub fn covisibility(&self) -> &CovisibilityGraph {
        &self.covis
    }

    /// Times a merged submap was built (exact mode), for cache checks.
    pub fn merged_rebuilds(&self) -> usize {
        self.merged_rebuilds
    }

    /// Inserts a keyframe: `cloud` in the keyframe-local frame (with optional local view
    /// directions), `pose` = `T_map_keyframe`. Builds its tree and covariances; first
    /// evicts keyframes farther than `remove_frames_farther_than` from `pose`.
    pub fn insert(
        &mut self,
        cloud: PointCloud,
        pose: Pose,
        timestamp: f64,
    ) -> Result<KeyframeId, MapError> {
        cloud.validate()?;
        self.ensure_covis_index()?;
        let id = self.next_id;
        let keyframe = Keyframe::build(id, pose, timestamp, cloud, &self.options.covariance)?;
        if self.options.remove_frames_farther_than > 0.0 {
            let far: Vec<KeyframeId> = self
                .keyframes
                .values()
                .filter(|k| {
                    translation_distance(&k.pose, &pose) > self.options.remove_frames_farther_than
                })
                .map(|k| k.id)
                .collect();
            for old in far {
                self.remove(old)?;
                self.evicted.push(old);
            }
        }
        self.next_id += 1;
        self.insert_built(keyframe)?;
        Ok(id)
    }

    /// Adds a keyframe built elsewhere (e.g. [`Keyframe::from_parts`]), keeping its id,
    /// which must be at least [`next_id`](Self::next_id). No eviction.
    pub fn insert_keyframe(&mut self, keyframe: Keyframe) -> Result<KeyframeId, MapError> {
        if keyframe.id < self.next_id {
            return Err(MapError::IdTaken(keyframe.id));
        }
        self.ensure_covis_index()?;
        let id = keyframe.id;
        self.next_id = id + 1;
        self.insert_built(keyframe)?;
        Ok(id)
    }

    fn insert_built(&mut self, keyframe: Keyframe) -> Result<(), MapError> {
        self.covis.set_keyframe(keyframe.id, keyframe.map_points()?);
        self.keyframes.insert(keyframe.id, keyframe);
        Ok(())
    }

    /// Ids evicted since the last call.
    pub fn drain_evicted(&mut self) -> Vec<KeyframeId> {
        std::mem::take(&mut self.evicted)
    }

    fn invalidate(&mut self, id: KeyframeId) {
        if self.merged.as_ref().is_some_and(|m| m.ids.contains(&id)) {
            self.merged = None;
        }
    }

    /// Moves a keyframe; only caches in the map frame are invalidated (local tree and
    /// covariances stay).
    pub fn set_pose(&mut self, id: KeyframeId, pose: Pose) -> Result<(), MapError> {
        self.ensure_covis_index()?;
        let keyframe = self
            .keyframes
            .get_mut(&id)
            .ok_or(MapError::UnknownKeyframe(id))?;
        keyframe.pose = pose;
        let points = keyframe.map_points()?;
        self.covis.set_keyframe(id, points);
        self.invalidate(id);
        Ok(())
    }

    /// Removes a keyframe.
    pub fn remove(&mut self, id: KeyframeId) -> Result<Keyframe, MapError> {
        self.ensure_covis_index()?;
        let keyframe = self
            .keyframes
            .remove(&id)
            .ok_or(MapError::UnknownKeyframe(id))?;
        self.covis.remove_keyframe(id);
        self.invalidate(id);
        Ok(keyframe)
    }

    /// Left-multiplies every pose by `t` (`T_new_map = t * T_map`).
    pub fn transform_all(&mut self, t: &Pose) -> Result<(), MapError> {
        let ids: Vec<KeyframeId> = self.keyframes.keys().copied().collect();
        for id in ids {
            let pose = t * self.keyframes[&id].pose;
            self.set_pose(id, pose)?;
        }
        self.merged = None;
        Ok(())
    }

    /// Copies every keyframe of `other` into this map with pose `t * pose` and fresh ids
    /// (ascending in `other`'s order); returns the new ids.
    pub fn merge(&mut self, other: &KeyframeMap, t: &Pose) -> Result<Vec<KeyframeId>, MapError> {
        self.ensure_covis_index()?;
        let mut ids = Vec::with_capacity(other.len());
        for k in other.keyframes.values() {
            let mut copy = k.clone();
            copy.id = self.next_id;
            copy.pose = t * k.pose;
            self.next_id += 1;
            ids.push(copy.id);
            self.insert_built(copy)?;
        }
        Ok(ids)
    }

    /// The active keyframes for a query at `pose`, ascending id.
    pub fn select(&self, pose: &Pose) -> Vec<KeyframeId> {
        self.select_with(pose, &self.options.selection)
    }

    /// As [`Self::select`] with `selection` in place of the map's own options (the
    /// active-set mode stays the map's).
    pub fn select_with(&self, pose: &Pose, selection: &SelectionOptions) -> Vec<KeyframeId> {
        let poses = self.keyframe_poses();
        let mut ids = match self.options.active_set {
            ActiveSetMode::Distance => select_active(&poses, pose, selection),
            ActiveSetMode::Covisibility => match rank(&poses, pose, selection).first() {
                None => Vec::new(),
                Some(nearest) => {
                    let more = selection.max_search_keyframes - 1;
                    std::iter::once(nearest.id)
                        .chain(self.covis.best_covisible(nearest.id, more))
                        .collect()
                }
            },
        };
        ids.sort_unstable();
        ids
    }

    /// The `count` keyframes whose positions are nearest `pose`'s, ascending id: the map
    /// around a place whichever way its keyframes faced (what a scan's structure is
    /// checked against), where the active set keeps the few a registration needs.
    pub fn surroundings(&self, pose: &Pose, count: usize) -> Vec<KeyframeId> {
        let by_position = SelectionOptions::by_position(count);
        let mut ids = select_active(&self.keyframe_poses(), pose, &by_position);
        ids.sort_unstable();
        ids
    }

    /// Every keyframe's id and pose, what selection ranks.
    fn keyframe_poses(&self) -> Vec<(KeyframeId, Pose)> {
        self.keyframes.values().map(|k| (k.id, k.pose)).collect()
    }

    /// The active set for a query at `pose`: in exact mode its merged submap is built,
    /// or reused when the set is unchanged.
    pub fn activate(&mut self, pose: &Pose) -> Result<ActiveSet<'_>, MapError> {
        let ids = self.select(pose);
        self.activate_ids(ids)
    }

    /// The active set made of exactly `ids` (ascending, existing).
    pub fn activate_ids(&mut self, ids: Vec<KeyframeId>) -> Result<ActiveSet<'_>, MapError> {
        let exact = !self.options.approximate_cov;
        let mut cache = self.merged.take();
        let before = cache.clone();
        // A first pass refreshes the map's own cache; the set it returns is dropped so
        // the cache and the counter can be stored.
        let refreshed = self
            .activate_cached(ids.clone(), &mut cache, exact)
            .map(drop);
        if !same_submap(&before, &cache) {
            self.merged_rebuilds += 1;
        }
        self.merged = cache.clone();
        refreshed?;
        self.activate_cached(ids, &mut cache, exact)
    }

    /// As [`Self::activate_ids`] on a shared map: the merged submap (exact mode) is
    /// cached by the caller, one cache per map-server client session.
    pub fn activate_cached(
        &self,
        mut ids: Vec<KeyframeId>,
        cache: &mut Option<Arc<MergedSubmap>>,
        exact: bool,
    ) -> Result<ActiveSet<'_>, MapError> {
        ids.sort_unstable();
        ids.dedup();
        if ids.is_empty() {
            return Err(MapError::Empty);
        }
        if let Some(&missing) = ids.iter().find(|id| !self.keyframes.contains_key(id)) {
            return Err(MapError::UnknownKeyframe(missing));
        }
        let frames = ids
            .iter()
            .map(|id| ActiveFrame::new(&self.keyframes[id]))
            .collect::<Result<Vec<_>, _>>()?;
        if !exact {
            return Ok(ActiveSet::new(&self.options, frames, None));
        }
        if cache.as_ref().is_none_or(|m| m.ids != ids) {
            if frames.iter().any(|f| self.keyframes[&f.id].is_baked()) {
                // Baked maps serve approximate mode without rebuilds; say what this costs.
                tracing::info!(keyframes = ?ids, "exact mode: building the merged submap (tree + covariances) of a new active set");
            }
            *cache = Some(Arc::new(MergedSubmap::build(&frames, &self.options)?));
        }
        Ok(ActiveSet::new(&self.options, frames, cache.clone()))
    }
}

/// True when both caches hold the same submap (or both none).
fn same_submap(a: &Option<Arc<MergedSubmap>>, b: &Option<Arc<MergedSubmap>>) -> bool {
    match (a, b) {
        (Some(a), Some(b)) => Arc::ptr_eq(a, b),
        (None, None) => true,
        _ => false,
    }
}

#[cfg(test)]
pub(crate) mod tests;
