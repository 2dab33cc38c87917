//! The active set of a query: nearest-neighbour and cov2cov lookups, either in the
//! merged submap (exact mode) or keyframe by keyframe (approximate mode).

use std::num::NonZeroUsize;
use std::sync::Arc;

use nalgebra::{Matrix3, Point3, Vector3};
use rayon::prelude::*;

use super::{Keyframe, KeyframeMapOptions, KeyframeView, MapError};
use crate::archive::ArchiveError;
use kfmap_geometry::KeyframeId;
use kfmap_geometry::cloud::{
    Aabb, CloudError, PointCloud, grid_position, unit_or_zero, voxel_groups,
};
use kfmap_geometry::cov::estimate_covariances;
use kfmap_geometry::geometry::{
    PackedSym3, Pose, pack_sym3, to_point, to_vec3, transform_point, unpack_sym3,
};
use kfmap_geometry::spatial::{PointTree, TreeRef, build_tree, point_dist_sq};

/// The active keyframes' points concatenated in ascending id order, in the map frame,
/// with a tree and covariances of their own (neighbours may come from any keyframe).
/// With `fuse_voxel_size` set, points of several keyframes in one map-frame voxel are
/// first fused into one (see [`MergedSubmap::build`]).
#[derive(Debug)]
pub struct MergedSubmap {
    /// Keyframes merged, ascending.
    pub ids: Vec<KeyframeId>,
    /// Map-frame points.
    pub points: Vec<[f32; 3]>,
    /// Index into `ids` of each point's keyframe.
    pub origin_keyframe: Vec<u32>,
    /// Local index of each point in its keyframe.
    pub origin_index: Vec<u32>,
    /// Map-frame view directions (zero where a keyframe has none).
    pub view_dirs: Vec<[f32; 3]>,
    /// Covariances computed on the merged cloud, map frame.
    pub covariances: Vec<PackedSym3>,
    /// KD-tree over `points`.
    pub tree: PointTree,
}

/// The concatenated points before their tree and covariances: one entry per point.
#[derive(Default)]
struct Concatenated {
    points: Vec<[f32; 3]>,
    origin_keyframe: Vec<u32>,
    origin_index: Vec<u32>,
    view_dirs: Vec<[f32; 3]>,
    weights: Vec<u32>,
}

impl Concatenated {
    fn of(frames: &[ActiveFrame<'_>]) -> Self {
        let mut all = Self::default();
        for (slot, f) in frames.iter().enumerate() {
            for (i, p) in f.view.points.iter().enumerate() {
                // The same arithmetic as `grid_position`, which fusion keys by.
                all.points.push(to_point(&transform_point(&f.pose, p)));
                all.origin_keyframe.push(slot as u32);
                all.origin_index.push(i as u32);
                let v = f
                    .view
                    .view_dirs
                    .map_or([0.0; 3], |v| to_point(&(f.pose.rotation * to_vec3(&v[i]))));
                all.view_dirs.push(v);
                all.weights.push(f.view.weights.map_or(1, |w| w[i]));
            }
        }
        all
    }

    /// One point per occupied map-frame voxel: the weighted centroid of its points (so
    /// keyframes voxelized on the same grid, with their voxel counts as weights, fuse
    /// into exactly the voxelization of their merged raw scans). The fused point keeps
    /// the origin of its heaviest member (ties: the first) and the weighted mean view
    /// direction.
    fn fused(self, frames: &[ActiveFrame<'_>], voxel_size: f64) -> Result<Self, CloudError> {
        // Keyed from the local points exactly as bake keyed them, not from the f32 map
        // points, so a point on a voxel boundary cannot change voxel.
        let groups = voxel_groups(self.points.len(), voxel_size, |i| {
            let f = &frames[self.origin_keyframe[i] as usize];
            grid_position(&f.view.points[self.origin_index[i] as usize], Some(&f.pose))
        })?;
        let mut out = Self::default();
        for group in groups.chunk_by(|a, b| a.0 == b.0) {
            let members = || group.iter().map(|&(_, i)| i as usize);
            let weight = |i: usize| f64::from(self.weights[i]);
            let total: f64 = members().map(weight).sum();
            let weighted_mean = |values: &[[f32; 3]]| {
                members().fold([0.0f64; 3], |acc, i| {
                    std::array::from_fn(|a| acc[a] + weight(i) * f64::from(values[i][a]))
                })
            };
            let heaviest = members()
                .max_by(|&a, &b| self.weights[a].cmp(&self.weights[b]).then(b.cmp(&a)))
                .expect("a voxel group is never empty");
            out.points
                .push(weighted_mean(&self.points).map(|c| (c / total) as f32));
            out.origin_keyframe.push(self.origin_keyframe[heaviest]);
            out.origin_index.push(self.origin_index[heaviest]);
            out.view_dirs
                .push(unit_or_zero(weighted_mean(&self.view_dirs)));
            out.weights.push(total.min(f64::from(u32::MAX)) as u32);
        }
        Ok(out)
    }
}

impl MergedSubmap {
    /// Merges the active keyframes (ascending id); fuses overlapping points when the
    /// map's `fuse_voxel_size` is set.
    pub fn build(
        frames: &[ActiveFrame<'_>],
        options: &KeyframeMapOptions,
    ) -> Result<Self, MapError> {
        let mut all = Concatenated::of(frames);
        if options.fuse_voxel_size > 0.0 {
            all = all.fused(frames, options.fuse_voxel_size)?;
        }
        Ok(Self {
            ids: frames.iter().map(|f| f.id).collect(),
            tree: build_tree(&all.points)?,
            covariances: estimate_covariances(&all.points, &options.covariance).values,
            points: all.points,
            origin_keyframe: all.origin_keyframe,
            origin_index: all.origin_index,
            view_dirs: all.view_dirs,
        })
    }
}

/// An active keyframe: its pose (and inverse) and its verified local data.
#[derive(Clone, Copy)]
pub struct ActiveFrame<'a> {
    /// Keyframe id.
    pub id: KeyframeId,
    /// `T_map_keyframe`.
    pub pose: Pose,
    /// `T_keyframe_map`, to move queries into the keyframe.
    local_from_map: Pose,
    /// Rotation of `pose` as a matrix, for rotating covariances and view directions.
    rotation: Matrix3<f64>,
    /// Local bounding box.
    bbox: Aabb,
    /// Local points, view directions, covariances and tree.
    pub view: KeyframeView<'a>,
}

impl<'a> ActiveFrame<'a> {
    /// Verifies a baked keyframe on its first use.
    pub(super) fn new(k: &'a Keyframe) -> Result<Self, ArchiveError> {
        Ok(Self {
            id: k.id,
            pose: k.pose,
            local_from_map: k.pose.inverse(),
            rotation: k.pose.rotation.to_rotation_matrix().into_inner(),
            bbox: k.bbox,
            view: k.view()?,
        })
    }
}

/// A map point found for a query: map frame, squared distance (m^2), origin.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapHit {
    /// The map point, map frame.
    pub point: [f32; 3],
    /// Squared distance to the query, m^2.
    pub dist_sq: f32,
    /// Keyframe holding the point.
    pub keyframe: KeyframeId,
    /// Index of the point in that keyframe.
    pub local_index: u32,
}

/// One GICP correspondence: query point `query_index` paired with a map point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pairing {
    /// Index of the scan point.
    pub query_index: u32,
    /// Keyframe of the map point.
    pub keyframe: KeyframeId,
    /// Index of the map point in its keyframe.
    pub local_index: u32,
    /// The map point, map frame.
    pub map_point: [f32; 3],
    /// Squared distance between the transformed scan point and the map point, m^2.
    pub dist_sq: f32,
    /// `(C_map + R C_query R^T)^-1`, packed, 1/m^2, map frame.
    pub information: PackedSym3,
}

/// Orders hits by distance, then keyframe id, then local index (deterministic ties).
fn hit_order(a: &MapHit, b: &MapHit) -> std::cmp::Ordering {
    rank_order(
        (a.dist_sq, a.keyframe, a.local_index),
        (b.dist_sq, b.keyframe, b.local_index),
    )
}

/// [`hit_order`] on (squared distance, keyframe id, local index), for a candidate whose
/// hit is not built yet.
fn rank_order(a: (f32, KeyframeId, u32), b: (f32, KeyframeId, u32)) -> std::cmp::Ordering {
    a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2))
}

/// The keyframes answering one query, with the merged submap in exact mode.
pub struct ActiveSet<'a> {
    options: &'a KeyframeMapOptions,
    frames: Vec<ActiveFrame<'a>>,
    ids: Vec<KeyframeId>,
    merged: Option<Arc<MergedSubmap>>,
}

impl<'a> ActiveSet<'a> {
    pub(super) fn new(
        options: &'a KeyframeMapOptions,
        frames: Vec<ActiveFrame<'a>>,
        merged: Option<Arc<MergedSubmap>>,
    ) -> Self {
        let ids = frames.iter().map(|f| f.id).collect();
        Self {
            options,
            frames,
            ids,
            merged,
        }
    }

    /// Active keyframe ids, ascending.
    pub fn ids(&self) -> &[KeyframeId] {
        &self.ids
    }

    /// The merged submap (exact mode).
    pub fn merged(&self) -> Option<&MergedSubmap> {
        self.merged.as_deref()
    }

    /// Nearest point of the merged submap within `max_dist_sq` (inclusive): its merged
    /// index and the hit.
    fn merged_nearest(m: &MergedSubmap, p: &[f32; 3], max_dist_sq: f32) -> Option<(usize, MapHit)> {
        let (item, dist_sq) = m.tree.view().nearest_one_within(p, max_dist_sq)?;
        Some((item as usize, Self::merged_hit(m, item, dist_sq)))
    }

    fn merged_hit(m: &MergedSubmap, item: u32, dist_sq: f32) -> MapHit {
        let i = item as usize;
        MapHit {
            point: m.points[i],
            dist_sq,
            keyframe: m.ids[m.origin_keyframe[i] as usize],
            local_index: m.origin_index[i],
        }
    }

    /// The query (map frame) in a keyframe's local frame.
    fn local_query(f: &ActiveFrame, p: &[f32; 3]) -> [f32; 3] {
        to_point(&(f.local_from_map * Point3::from(to_vec3(p))).coords)
    }

    fn local_hit(f: &ActiveFrame, item: u32, dist_sq: f32) -> MapHit {
        Self::hit_at(f, item, dist_sq, &f.view.points[item as usize])
    }

    /// The hit of keyframe `f`'s point `item`, at `local` (its local coordinates).
    fn hit_at(f: &ActiveFrame, item: u32, dist_sq: f32, local: &[f32; 3]) -> MapHit {
        MapHit {
            point: to_point(&(f.pose * Point3::from(to_vec3(local))).coords),
            dist_sq,
            keyframe: f.id,
            local_index: item,
        }
    }

    /// The nearest map point to `p` (map frame).
    pub fn nearest_one(&self, p: &[f32; 3]) -> Option<MapHit> {
        self.nearest_one_within(p, f32::INFINITY)
    }

    /// [`Self::nearest_one`] when it lies within `max_dist_sq` (inclusive): the search
    /// stops at that distance, so a point with nothing near costs little.
    pub fn nearest_one_within(&self, p: &[f32; 3], max_dist_sq: f32) -> Option<MapHit> {
        match &self.merged {
            Some(m) => Self::merged_nearest(m, p, max_dist_sq).map(|(_, hit)| hit),
            None => self.nearest_in_frames(p, max_dist_sq).map(|(_, hit)| hit),
        }
    }

    /// Approximate mode: the nearest point over the active keyframes within
    /// `max_dist_sq`, with its frame. The keyframe taken nearest to `p` is searched
    /// first; each later search is bounded by the best hit so far and skipped when the
    /// keyframe's box is farther than that (ties still resolve by [`hit_order`]).
    fn nearest_in_frames(
        &self,
        p: &[f32; 3],
        max_dist_sq: f32,
    ) -> Option<(&ActiveFrame<'a>, MapHit)> {
        // The best so far as (frame, item, squared distance, local point): its map-frame
        // hit is built once, at the end.
        let mut best: Option<(&ActiveFrame<'a>, u32, f32, [f32; 3])> = None;
        let mut bound = max_dist_sq;
        for f in self.frames_nearest_first(p) {
            let query = Self::local_query(f, p);
            if f.bbox.dist_sq(&query) > bound {
                continue;
            }
            let Some((item, dist_sq, local)) = f.view.tree.nearest_one_within_at(&query, bound)
            else {
                continue;
            };
            let better = best.is_none_or(|(b, b_item, b_dist, _)| {
                rank_order((dist_sq, f.id, item), (b_dist, b.id, b_item)).is_lt()
            });
            if better {
                bound = dist_sq;
                best = Some((f, item, dist_sq, local));
            }
        }
        best.map(|(f, item, dist_sq, local)| (f, Self::hit_at(f, item, dist_sq, &local)))
    }

    /// The active keyframes, the one taken nearest to `p` first (scans are densest near
    /// the sensor: it likely holds `p`'s nearest points, whose distance then bounds the
    /// searches in the others), the rest in id order.
    fn frames_nearest_first(&self, p: &[f32; 3]) -> impl Iterator<Item = &ActiveFrame<'a>> {
        self.slots_nearest_first(p).map(|i| &self.frames[i])
    }

    /// [`Self::frames_nearest_first`] as indices into the active frames.
    fn slots_nearest_first(&self, p: &[f32; 3]) -> impl Iterator<Item = usize> + use<'_> {
        let origin_dist_sq =
            |f: &ActiveFrame| (f.pose.translation.vector - to_vec3(p)).norm_squared();
        let first = (0..self.frames.len()).min_by(|&a, &b| {
            origin_dist_sq(&self.frames[a]).total_cmp(&origin_dist_sq(&self.frames[b]))
        });
        first
            .into_iter()
            .chain((0..self.frames.len()).filter(move |&i| Some(i) != first))
    }

    /// Approximate mode: the nearest point over the active keyframes within `bound_sq`
    /// (as [`Self::nearest_in_frames`], ties alike) and the squared distance of the
    /// runner-up over them all (`bound_sq` when there is none). Each keyframe's search
    /// is bounded by the runner-up so far.
    fn two_nearest_in_frames(&self, p: &[f32; 3], bound_sq: f32) -> (Option<FrameHit>, f32) {
        let mut best: Option<FrameHit> = None;
        let mut second = bound_sq;
        for slot in self.slots_nearest_first(p) {
            let f = &self.frames[slot];
            let query = Self::local_query(f, p);
            if f.bbox.dist_sq(&query) > second {
                continue;
            }
            let (nearest, runner_up) = f.view.tree.nearest_two_within_at(&query, second);
            second = second.min(runner_up);
            let Some((item, dist_sq, local)) = nearest else {
                continue;
            };
            let new = (slot, item, dist_sq, local);
            match best {
                Some(b) if !rank_order(self.rank_key(&new), self.rank_key(&b)).is_lt() => {
                    second = second.min(dist_sq);
                }
                _ => {
                    if let Some(b) = best {
                        second = second.min(b.2);
                    }
                    best = Some(new);
                }
            }
        }
        (best, second)
    }

    /// A found point's [`rank_order`] key: (squared distance, keyframe id, item).
    fn rank_key(&self, hit: &FrameHit) -> (f32, KeyframeId, u32) {
        (hit.2, self.frames[hit.0].id, hit.1)
    }

    /// Approximate mode: the `k` nearest points over the active keyframes, nearest
    /// first. As [`Self::nearest_in_frames`] for one: each keyframe after the first is
    /// searched within the `k`-th distance found so far (inclusive) and skipped when its
    /// box lies beyond it, so the answer is the merged per-keyframe k-NN's.
    fn nearest_k_in_frames(&self, p: &[f32; 3], k: NonZeroUsize, max_dist_sq: f32) -> Vec<MapHit> {
        let mut hits: Vec<MapHit> = Vec::new();
        let mut bound = max_dist_sq;
        for f in self.frames_nearest_first(p) {
            let query = Self::local_query(f, p);
            if f.bbox.dist_sq(&query) > bound {
                continue;
            }
            let found = f.view.tree.nearest_n_within(&query, k, bound);
            hits.extend(found.into_iter().map(|(i, d)| Self::local_hit(f, i, d)));
            hits.sort_by(hit_order);
            hits.truncate(k.get());
            if hits.len() == k.get() {
                bound = hits[k.get() - 1].dist_sq;
            }
        }
        hits
    }

    /// Runs `search` (returning `(item, squared distance)`) on the merged tree, or on
    /// every active keyframe's tree with `p` moved into its frame; hits nearest first.
    fn gather(
        &self,
        p: &[f32; 3],
        search: impl Fn(TreeRef<'_>, &[f32; 3]) -> Vec<(u32, f32)>,
    ) -> Vec<MapHit> {
        let mut hits: Vec<MapHit> = match &self.merged {
            Some(m) => search(m.tree.view(), p)
                .into_iter()
                .map(|(i, d)| Self::merged_hit(m, i, d))
                .collect(),
            None => self
                .frames
                .iter()
                .flat_map(|f| {
                    search(f.view.tree, &Self::local_query(f, p))
                        .into_iter()
                        .map(move |(i, d)| Self::local_hit(f, i, d))
                })
                .collect(),
        };
        hits.sort_by(hit_order);
        hits
    }

    /// The `k` nearest map points to `p`, nearest first.
    pub fn nearest_k(&self, p: &[f32; 3], k: usize) -> Vec<MapHit> {
        self.nearest_k_within(p, k, f32::INFINITY)
    }

    /// [`Self::nearest_k`]'s points within `max_dist_sq` (inclusive): every search stops
    /// at that distance.
    pub fn nearest_k_within(&self, p: &[f32; 3], k: usize, max_dist_sq: f32) -> Vec<MapHit> {
        let Some(n) = NonZeroUsize::new(k) else {
            return Vec::new();
        };
        // A tracker's explained-structure queries ask for k = 1 on every adopted scan:
        // the 1-NN search, which keeps no list.
        if k == 1 {
            return self
                .nearest_one_within(p, max_dist_sq)
                .into_iter()
                .collect();
        }
        if self.merged.is_none() {
            return self.nearest_k_in_frames(p, n, max_dist_sq);
        }
        let mut hits = self.gather(p, |tree, q| tree.nearest_n_within(q, n, max_dist_sq));
        hits.truncate(k);
        hits
    }

    /// Every map point within `radius` metres of `p` (inclusive), nearest first.
    pub fn within_radius(&self, p: &[f32; 3], radius: f64) -> Vec<MapHit> {
        let r2 = (radius * radius) as f32;
        self.gather(p, |tree, q| tree.within(q, r2))
    }

    /// GICP correspondences for `scan` (sensor frame) at `pose` (`T_map_sensor`): for
    /// each scan point its nearest map point within `max_pair_dist` metres, passing the
    /// view-direction filter, with the information matrix `(C_map + R C_q R^T)^-1`.
    /// Query covariances are estimated from the scan unless given. Sorted by query
    /// index; the same for any thread count.
    pub fn cov2cov(
        &self,
        scan: &PointCloud,
        pose: &Pose,
        max_pair_dist: f64,
        query_covariances: Option<&[PackedSym3]>,
    ) -> Result<Vec<Pairing>, MapError> {
        self.cov2cov_remembering(scan, pose, max_pair_dist, query_covariances, None)
    }

    /// [`Self::cov2cov`], the same pairings, with `memo` remembering each scan point's
    /// nearest map point and how far its runner-up lay: in approximate mode a point
    /// that moved less than that gap since the memo's search (the iterations of one
    /// registration) is paired without a search (see [`NearestMemo`]).
    pub fn cov2cov_remembering(
        &self,
        scan: &PointCloud,
        pose: &Pose,
        max_pair_dist: f64,
        query_covariances: Option<&[PackedSym3]>,
        memo: Option<&mut NearestMemo>,
    ) -> Result<Vec<Pairing>, MapError> {
        scan.validate()?;
        let estimated;
        let covs: &[PackedSym3] = match query_covariances {
            Some(c) if c.len() != scan.len() => {
                return Err(MapError::CovarianceCount {
                    given: c.len(),
                    points: scan.len(),
                });
            }
            Some(c) => c,
            None => {
                estimated = estimate_covariances(&scan.points, &self.options.covariance).values;
                &estimated
            }
        };
        let options = self.options;
        let max_sq = (max_pair_dist * max_pair_dist) as f32;
        let cos_limit = options.max_view_angle_deg.to_radians().cos();
        let filter = options.view_filter_active() && scan.view_dirs.is_some();
        let rotation = pose.rotation.to_rotation_matrix().into_inner();
        let map_point =
            |i: usize| to_point(&(pose * Point3::from(to_vec3(&scan.points[i]))).coords);
        let pair = |i: usize, (hit, map_cov, map_view): (MapHit, Matrix3<f64>, Vector3<f64>)| {
            if filter {
                let vq = pose.rotation * to_vec3(&scan.view_dirs.as_ref()?[i]);
                // A missing vector (norm^2 < 0.25) never rejects.
                if vq.norm_squared() >= 0.25
                    && map_view.norm_squared() >= 0.25
                    && vq.dot(&map_view) < cos_limit
                {
                    return None;
                }
            }
            let combined: Matrix3<f64> =
                map_cov + rotation * unpack_sym3(&covs[i]) * rotation.transpose();
            let information = combined.try_inverse()?;
            Some(Pairing {
                query_index: i as u32,
                keyframe: hit.keyframe,
                local_index: hit.local_index,
                map_point: hit.point,
                dist_sq: hit.dist_sq,
                information: pack_sym3(&information),
            })
        };
        let pairings = match memo.filter(|_| self.merged.is_none()) {
            None => (0..scan.len())
                .into_par_iter()
                .filter_map(|i| pair(i, self.nearest_with_attributes(&map_point(i), max_sq)?))
                .collect(),
            Some(memo) => {
                memo.follow(&self.ids, scan.len());
                memo.entries
                    .par_iter_mut()
                    .enumerate()
                    .filter_map(|(i, entry)| {
                        pair(i, self.nearest_remembered(&map_point(i), max_sq, entry)?)
                    })
                    .collect()
            }
        };
        Ok(pairings)
    }

    /// The nearest map point within `max_dist_sq` with its attributes (as
    /// [`Self::nearest_with_attributes`] in approximate mode): recalled from `entry`
    /// when its certificate still holds at `p`, else searched and remembered there.
    fn nearest_remembered(
        &self,
        p: &[f32; 3],
        max_dist_sq: f32,
        entry: &mut Remembered,
    ) -> Option<(MapHit, Matrix3<f64>, Vector3<f64>)> {
        let found = match self.recall(entry, p, max_dist_sq) {
            Ok(answer) => {
                entry.recalled = true;
                answer
            }
            Err(known_within) => {
                let reach = max_dist_sq.sqrt();
                let bound = known_within.map_or(reach, |k| k.min(reach));
                let (nearest, runner_up_sq) = self.two_nearest_in_frames(p, bound * bound);
                *entry = Remembered {
                    query: *p,
                    nearest: nearest.map(|(slot, item, _, local)| (slot as u32, item, local)),
                    clear: runner_up_sq.sqrt(),
                    clear_by_point: runner_up_sq < bound * bound,
                    recalled: false,
                };
                nearest.filter(|h| h.2 <= max_dist_sq)
            }
        }?;
        let (slot, item, dist_sq, local) = found;
        let f = &self.frames[slot];
        let hit = Self::hit_at(f, item, dist_sq, &local);
        let (cov, view) = Self::attributes(f, item);
        Some((hit, cov, view))
    }

    /// What `entry` certifies at `p`: `Ok(answer)` (the nearest within `max_dist_sq`,
    /// or none) when the remembered nearest is closer to `p` than every other map point
    /// can be (`clear` less how far `p` moved from the remembered query, less
    /// [`MEMO_MARGIN_M`] for rounding). Else `Err`: a search is needed, and `Some(d)`
    /// when two map points (the remembered nearest and its runner-up) are known to lie
    /// within `d` metres of `p`, so a search bounded by `d` finds what an unbounded one
    /// would.
    fn recall(
        &self,
        entry: &Remembered,
        p: &[f32; 3],
        max_dist_sq: f32,
    ) -> Result<Option<FrameHit>, Option<f32>> {
        let moved = (to_vec3(p) - to_vec3(&entry.query)).norm();
        // Every map point but the remembered nearest lies at least this far from `p`.
        let others_beyond = f64::from(entry.clear) - moved - MEMO_MARGIN_M;
        let Some((slot, item, local)) = entry.nearest else {
            return if others_beyond > f64::from(max_dist_sq).sqrt() {
                Ok(None)
            } else {
                Err(None)
            };
        };
        let slot = slot as usize;
        let f = self.frames.get(slot).ok_or(None)?;
        // The distance exactly as a search computes it.
        let dist_sq = point_dist_sq(&local, &Self::local_query(f, p));
        let dist = f64::from(dist_sq).sqrt();
        if dist < others_beyond {
            return Ok((dist_sq <= max_dist_sq).then_some((slot, item, dist_sq, local)));
        }
        Err(entry.clear_by_point.then(|| {
            let runner_up = f64::from(entry.clear) + moved;
            (dist.max(runner_up) + MEMO_MARGIN_M) as f32
        }))
    }

    /// Map-frame covariance and view direction of keyframe `f`'s point `item`.
    fn attributes(f: &ActiveFrame, item: u32) -> (Matrix3<f64>, Vector3<f64>) {
        let local_cov = unpack_sym3(&f.view.covariances[item as usize]);
        let view = f.view.view_dirs.map_or(Vector3::zeros(), |v| {
            f.rotation * to_vec3(&v[item as usize])
        });
        (f.rotation * local_cov * f.rotation.transpose(), view)
    }

    /// Nearest map point within `max_dist_sq` (inclusive) with its covariance and view
    /// direction, both in the map frame.
    fn nearest_with_attributes(
        &self,
        p: &[f32; 3],
        max_dist_sq: f32,
    ) -> Option<(MapHit, Matrix3<f64>, Vector3<f64>)> {
        if let Some(m) = &self.merged {
            let (i, hit) = Self::merged_nearest(m, p, max_dist_sq)?;
            return Some((
                hit,
                unpack_sym3(&m.covariances[i]),
                to_vec3(&m.view_dirs[i]),
            ));
        }
        let (f, hit) = self.nearest_in_frames(p, max_dist_sq)?;
        let (cov, view) = Self::attributes(f, hit.local_index);
        Some((hit, cov, view))
    }
}

/// A point of an active keyframe found for a query: (slot in the active frames, item,
/// squared distance, the point in the keyframe's frame).
type FrameHit = (usize, u32, f32, [f32; 3]);

/// A point is recalled only when its nearest leads every other map point by more than
/// this, for rounding: the distances compared are computed in `f32` in the keyframes'
/// frames, from queries rounded there (points 128 m from a keyframe's origin round to
/// 4 um, their distances to about 7 um), so ties and near-ties are always searched.
const MEMO_MARGIN_M: f64 = 1e-4;

/// Each scan point's last search in approximate mode, index by index, for
/// [`ActiveSet::cov2cov_remembering`]: the query, its nearest map point and `clear`,
/// the distance within which no other map point lay. When the point is queried again
/// at `p`, moved `m` from that query, every other map point lies at least
/// `clear - m` from `p`; if the nearest is closer than that (by [`MEMO_MARGIN_M`]) it
/// is still the nearest and no search is needed. The answers are exactly a search's.
/// A registration's iterations move a point millimetres while its runner-up lies
/// centimetres behind, so most of them are recalled. Entries belong to one active set:
/// another one clears them.
#[derive(Debug, Default)]
pub struct NearestMemo {
    ids: Vec<KeyframeId>,
    entries: Vec<Remembered>,
}

/// One scan point's last search (see [`NearestMemo`]).
#[derive(Debug, Clone, Copy)]
struct Remembered {
    /// The query searched, map frame.
    query: [f32; 3],
    /// Its nearest map point as (active-frame slot, item, local point), if one lay
    /// within the search's bound.
    nearest: Option<(u32, u32, [f32; 3])>,
    /// No map point but `nearest` lies closer to `query` than this, metres: the
    /// runner-up's distance, or the search's bound.
    clear: f32,
    /// True when `clear` is a map point's distance, false when it is the search's bound.
    clear_by_point: bool,
    /// True when the last pairing recalled this entry instead of searching.
    recalled: bool,
}

// The size `NearestMemos::MAX_POINTS` budgets for.
const _: () = assert!(std::mem::size_of::<Remembered>() <= 44);

/// An entry that certifies nothing.
const FORGOTTEN: Remembered = Remembered {
    query: [0.0; 3],
    nearest: None,
    clear: 0.0,
    clear_by_point: false,
    recalled: false,
};

impl NearestMemo {
    /// Points the memo holds entries for.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// True before the memo served any scan.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Scan points the last pairing recalled without a search.
    pub fn recalled(&self) -> usize {
        self.entries.iter().filter(|e| e.recalled).count()
    }

    /// Entries for `points` scan points on the active set `ids`: all forgotten when
    /// the set changed (slots name its frames).
    fn follow(&mut self, ids: &[KeyframeId], points: usize) {
        if self.ids != ids {
            self.ids = ids.to_vec();
            self.entries.clear();
        }
        self.entries.resize(points, FORGOTTEN);
    }
}

/// A client's memos, one per scan size it pairs (a tracker pairs a coarse and a fine
/// copy of each scan, each over several iterations), the most recent first; at most
/// [`NearestMemos::KEPT`].
#[derive(Debug, Default)]
pub struct NearestMemos {
    memos: Vec<NearestMemo>,
}

impl NearestMemos {
    /// Memos kept at most.
    pub const KEPT: usize = 2;

    /// Scans of more points are paired without a memo: about 11 MB each at most (44
    /// bytes a point), where a tracker's scans hold tens of thousands.
    pub const MAX_POINTS: usize = 1 << 18;

    /// The memo of scans of `points` points: the one last used for that size, else a
    /// new one replacing the least recently used; `None` above [`Self::MAX_POINTS`].
    pub fn for_points(&mut self, points: usize) -> Option<&mut NearestMemo> {
        if points > Self::MAX_POINTS {
            return None;
        }
        let at = match self.memos.iter().position(|m| m.len() == points) {
            Some(at) => at,
            None => {
                if self.memos.len() >= Self::KEPT {
                    self.memos.pop();
                }
                self.memos.push(NearestMemo::default());
                self.memos.len() - 1
            }
        };
        let memo = self.memos.remove(at);
        self.memos.insert(0, memo);
        Some(&mut self.memos[0])
    }

    /// Forgets everything (the map was reloaded).
    pub fn clear(&mut self) {
        self.memos.clear();
    }
}
