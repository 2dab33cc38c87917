//! Opening a `.kfmap` file: header and index checks, then keyframes that stay in the
//! memory map and are verified the first time they are used.

use std::fs::File;
use std::path::Path;
use std::sync::{Arc, OnceLock};

use memmap2::Mmap;
use nalgebra::{Quaternion, Translation3, UnitQuaternion};
use rkyv::rancor;
use rkyv::rend::{f32_le, u32_le, u64_le};
use xxhash_rust::xxh3::xxh3_64;

use super::ArchiveError;
use super::header::{HEADER_LEN, Header, SEGMENT_ALIGN};
use super::records::{
    ArchivedKeyframeRecord, ArchivedPlaceGridRecord, ArchivedTreeRecord, KeyframeEntry, MapIndex,
    PlaceEntry,
};
use super::writer::MAX_KEYFRAME_POINTS;
use crate::covis::{CovisSnapshot, CovisibilityGraph};
use crate::map::{Keyframe, KeyframeMap, KeyframeMapOptions, KeyframeView, weights_problem};
use crate::place::{GridView, SearchRegion};
use kfmap_geometry::KeyframeId;
use kfmap_geometry::cloud::Aabb;
use kfmap_geometry::cov::{CovOptions, estimate_covariances};
use kfmap_geometry::geometry::{PackedSym3, Pose};
use kfmap_geometry::spatial::{NodeWords, PointBlock, PointTree, TreeRef, build_tree};

/// How to open a map file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OpenOptions {
    /// Skip bytecheck validation of keyframe archives (their checksums are still
    /// verified on first use).
    pub trust: bool,
    /// Approximate cov2cov (zero rebuild: the serving default for baked maps); false
    /// builds a merged submap on first use of each active set.
    pub approximate_cov: bool,
}

impl Default for OpenOptions {
    fn default() -> Self {
        Self {
            trust: false,
            approximate_cov: true,
        }
    }
}

/// A map opened from a file, with what `kfmap inspect` reports.
pub struct OpenedMap {
    /// The map; its keyframes read from the memory map.
    pub map: KeyframeMap,
    /// The file header.
    pub header: Header,
    /// The index (keyframe entries, covisibility, gravity pool).
    pub index: MapIndex,
    /// The place grid of relocalization, when the map has one.
    pub place: Option<BakedPlaceGrid>,
    file: Arc<Mmap>,
}

/// The place grid's segment in the memory map, verified on first use.
pub struct BakedPlaceGrid {
    file: Arc<Mmap>,
    start: usize,
    byte_len: usize,
    checksum: u64,
    trust: bool,
    checked: OnceLock<Result<(), ArchiveError>>,
}

impl std::fmt::Debug for BakedPlaceGrid {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BakedPlaceGrid")
            .field("bytes", &self.byte_len)
            .field("verified", &self.checked.get().map(Result::is_ok))
            .finish()
    }
}

impl BakedPlaceGrid {
    fn new(file: &Arc<Mmap>, entry: &PlaceEntry, trust: bool) -> Self {
        Self {
            file: Arc::clone(file),
            start: HEADER_LEN + entry.offset as usize,
            byte_len: entry.len as usize,
            checksum: entry.checksum,
            trust,
            checked: OnceLock::new(),
        }
    }

    /// Bytes of the segment.
    pub fn byte_len(&self) -> usize {
        self.byte_len
    }

    fn bytes(&self) -> &[u8] {
        &self.file[self.start..self.start + self.byte_len]
    }

    fn check(&self) -> Result<(), ArchiveError> {
        let corrupt = |reason: String| ArchiveError::IndexCorrupt(format!("place grid: {reason}"));
        if xxh3_64(self.bytes()) != self.checksum {
            return Err(corrupt("checksum mismatch".into()));
        }
        if !self.trust {
            rkyv::access::<ArchivedPlaceGridRecord, rancor::Error>(self.bytes())
                .map_err(|e| corrupt(format!("invalid archive: {e}")))?;
        }
        // SAFETY: checksum (and bytecheck unless trusted) passed above, 128-aligned.
        let record = unsafe { rkyv::access_unchecked::<ArchivedPlaceGridRecord>(self.bytes()) };
        view_of(record)
            .map(|_| ())
            .map_err(|e| corrupt(e.to_string()))
    }

    /// The grid, read in place; verified on the first call.
    pub fn view(&self) -> Result<GridView<'_>, ArchiveError> {
        self.checked
            .get_or_init(|| self.check())
            .as_ref()
            .map_err(Clone::clone)?;
        // SAFETY: check() passed on these bytes; the map is read-only.
        let record = unsafe { rkyv::access_unchecked::<ArchivedPlaceGridRecord>(self.bytes()) };
        Ok(view_of(record).expect("checked above"))
    }
}

fn view_of<'f>(
    r: &'f ArchivedPlaceGridRecord<'_>,
) -> Result<GridView<'f>, crate::place::GridError> {
    let f = |v: &[rkyv::rend::f64_le]| -> Vec<f64> { v.iter().map(|x| x.to_native()).collect() };
    let three = |v: &[rkyv::rend::f64_le; 3]| -> [f64; 3] { v.map(|x| x.to_native()) };
    let rotation = f(&r.grid_from_map);
    GridView::new(
        r.resolution.to_native(),
        [rotation[0], rotation[1], rotation[2], rotation[3]],
        three(&r.origin),
        r.dims.map(|d| d.to_native()),
        r.levels.to_native(),
        native(&r.directory),
        native(&r.keys),
        native(&r.entries),
        native(&r.words),
        SearchRegion {
            min: three(&r.region_min),
            max: three(&r.region_max),
        },
    )
}

impl OpenedMap {
    /// File size, bytes.
    pub fn file_len(&self) -> u64 {
        self.file.len() as u64
    }

    /// Checks the whole-payload checksum (reads every byte).
    pub fn verify_payload(&self) -> Result<(), ArchiveError> {
        let end = HEADER_LEN + self.header.payload_len as usize;
        if xxh3_64(&self.file[HEADER_LEN..end]) != self.header.payload_checksum {
            return Err(ArchiveError::PayloadCorrupt);
        }
        Ok(())
    }

    /// Verifies every keyframe (checksum, archive, lengths) and its tree: each point
    /// must find itself at distance 0. Calls `progress` after each keyframe.
    pub fn verify_keyframes(&self, mut progress: impl FnMut(usize)) -> Result<(), ArchiveError> {
        for (i, k) in self.map.keyframes().enumerate() {
            let view = k.view()?;
            if let Some(bad) = view
                .points
                .iter()
                .position(|p| view.tree.nearest_one(p).1 != 0.0)
            {
                return Err(ArchiveError::KeyframeCorrupt {
                    id: k.id,
                    reason: format!("its KD-tree does not find point {bad}"),
                });
            }
            progress(i + 1);
        }
        Ok(())
    }
}

/// A keyframe's segment in a memory-mapped map file.
pub struct BakedKeyframe {
    file: Arc<Mmap>,
    start: usize,
    byte_len: usize,
    checksum: u64,
    id: KeyframeId,
    points: usize,
    trust: bool,
    covariance: CovOptions,
    /// Verification result, with a tree or covariances the file does not hold.
    prepared: OnceLock<Result<Rebuilt, ArchiveError>>,
}

struct Rebuilt {
    tree: Option<PointTree>,
    covariances: Option<Vec<PackedSym3>>,
}

impl std::fmt::Debug for BakedKeyframe {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BakedKeyframe")
            .field("id", &self.id)
            .field("points", &self.points)
            .field("bytes", &self.byte_len)
            .field("verified", &self.prepared.get().map(Result::is_ok))
            .finish()
    }
}

/// An archived type holding exactly the bits of a native one.
///
/// # Safety
/// Same size, alignment and bit pattern: rend's `*_le` types hold the little-endian
/// bits in 4 aligned bytes, and this crate only builds on little-endian targets.
unsafe trait SameBits {
    type Native;
}
// SAFETY: see the trait.
unsafe impl SameBits for f32_le {
    type Native = f32;
}
// SAFETY: see the trait.
unsafe impl SameBits for u32_le {
    type Native = u32;
}
// SAFETY: see the trait (8 aligned bytes).
unsafe impl SameBits for u64_le {
    type Native = u64;
}
// SAFETY: arrays of same-bits elements have the same layout.
unsafe impl<T: SameBits, const N: usize> SameBits for [T; N] {
    type Native = [T::Native; N];
}

/// An archived slice read as native values, in place.
fn native<T: SameBits>(v: &[T]) -> &[T::Native] {
    const {
        assert!(size_of::<T>() == size_of::<T::Native>());
        assert!(align_of::<T>() == align_of::<T::Native>());
    }
    // SAFETY: same size, alignment and bit pattern (`SameBits`).
    unsafe { std::slice::from_raw_parts(v.as_ptr().cast::<T::Native>(), v.len()) }
}

/// An archived tree's arrays, not yet checked.
fn tree_parts<'f>(t: &'f ArchivedTreeRecord<'_>) -> (&'f [NodeWords], &'f [PointBlock], &'f [u32]) {
    (native(&t.nodes), native(&t.blocks), native(&t.items))
}

impl BakedKeyframe {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.points
    }

    /// True for no points (never the case in a valid file).
    pub fn is_empty(&self) -> bool {
        self.points == 0
    }

    fn bytes(&self) -> &[u8] {
        &self.file[self.start..self.start + self.byte_len]
    }

    fn corrupt(&self, reason: impl Into<String>) -> ArchiveError {
        ArchiveError::KeyframeCorrupt {
            id: self.id,
            reason: reason.into(),
        }
    }

    fn prepare(&self) -> Result<Rebuilt, ArchiveError> {
        let bytes = self.bytes();
        if xxh3_64(bytes) != self.checksum {
            return Err(self.corrupt("checksum mismatch"));
        }
        let record: &ArchivedKeyframeRecord = if self.trust {
            // SAFETY: the bytes are exactly what the writer produced (checksum above),
            // at a 128-byte aligned offset (checked when the index was read).
            unsafe { rkyv::access_unchecked::<ArchivedKeyframeRecord>(bytes) }
        } else {
            rkyv::access::<ArchivedKeyframeRecord, rancor::Error>(bytes)
                .map_err(|e| self.corrupt(format!("invalid archive: {e}")))?
        };
        let n = self.points;
        if record.id.to_native() != self.id || record.points.len() != n {
            return Err(self.corrupt("segment does not match its index entry"));
        }
        let bad_len = |len: usize| len != n;
        if record.view_dirs.as_ref().is_some_and(|v| bad_len(v.len()))
            || record
                .covariances
                .as_ref()
                .is_some_and(|c| bad_len(c.len()))
        {
            return Err(self.corrupt("attribute lengths differ from the point count"));
        }
        if let Some(problem) = record
            .weights
            .as_ref()
            .and_then(|w| weights_problem(native(w), n))
        {
            return Err(self.corrupt(problem));
        }
        let points = native(&record.points);
        if let Some(t) = record.tree.as_ref() {
            let (nodes, blocks, items) = tree_parts(t);
            let tree = TreeRef::from_parts(nodes, blocks, items)
                .map_err(|e| self.corrupt(e.to_string()))?;
            if tree.len() != n {
                let why = format!(
                    "its KD-tree indexes {} points, the keyframe {n}",
                    tree.len()
                );
                return Err(self.corrupt(why));
            }
        }
        Ok(Rebuilt {
            tree: match record.tree.as_ref() {
                Some(_) => None,
                None => Some(build_tree(points).map_err(|e| self.corrupt(e.to_string()))?),
            },
            covariances: match record.covariances.as_ref() {
                Some(_) => None,
                None => Some(estimate_covariances(points, &self.covariance).values),
            },
        })
    }

    /// The keyframe's data, read in place; verified on the first call.
    pub fn view(&self) -> Result<KeyframeView<'_>, ArchiveError> {
        let rebuilt = self
            .prepared
            .get_or_init(|| self.prepare())
            .as_ref()
            .map_err(Clone::clone)?;
        // SAFETY: prepare() succeeded, so these bytes passed their checksum (and bytecheck
        // unless trusted) at an aligned offset; the map is read-only.
        let record = unsafe { rkyv::access_unchecked::<ArchivedKeyframeRecord>(self.bytes()) };
        let covariances = match (record.covariances.as_ref(), &rebuilt.covariances) {
            (Some(c), _) => native(c),
            (None, Some(c)) => c.as_slice(),
            (None, None) => unreachable!("prepare() rebuilds missing covariances"),
        };
        let tree = match (record.tree.as_ref(), &rebuilt.tree) {
            (Some(t), _) => {
                let (nodes, blocks, items) = tree_parts(t);
                TreeRef::from_checked_parts(nodes, blocks, items, record.points.len())
            }
            (None, Some(t)) => t.view(),
            (None, None) => unreachable!("prepare() rebuilds a missing tree"),
        };
        Ok(KeyframeView {
            points: native(&record.points),
            view_dirs: record.view_dirs.as_ref().map(|v| native(v)),
            covariances,
            weights: record.weights.as_ref().map(|w| native(w)),
            tree,
        })
    }
}

fn index_error(reason: impl Into<String>) -> ArchiveError {
    ArchiveError::IndexCorrupt(reason.into())
}

/// The pose of an entry, exactly as written.
fn entry_pose(e: &KeyframeEntry) -> Result<Pose, ArchiveError> {
    let [x, y, z, qx, qy, qz, qw] = e.pose;
    let q = Quaternion::new(qw, qx, qy, qz);
    if e.pose.iter().any(|v| !v.is_finite()) || (q.norm() - 1.0).abs() > 1e-6 {
        return Err(index_error(format!(
            "keyframe {} has an invalid pose",
            e.id
        )));
    }
    Ok(Pose::from_parts(
        Translation3::new(x, y, z),
        UnitQuaternion::new_unchecked(q),
    ))
}

/// Checks the index entries against the payload: ascending ids, aligned segments
/// inside the payload before the index, sane sizes, poses and bounding boxes.
fn check_index(index: &MapIndex, index_offset: u64) -> Result<(), ArchiveError> {
    if let Some(place) = &index.place {
        let end = place.offset.checked_add(place.len);
        if place.offset % SEGMENT_ALIGN != 0 || end.is_none_or(|end| end > index_offset) {
            return Err(index_error("place grid segment is out of bounds"));
        }
    }
    let mut previous: Option<KeyframeId> = None;
    for e in &index.keyframes {
        if previous.is_some_and(|p| p >= e.id) {
            return Err(index_error("keyframe ids are not ascending"));
        }
        previous = Some(e.id);
        let end = e.offset.checked_add(e.len);
        if e.offset % SEGMENT_ALIGN != 0 || end.is_none_or(|end| end > index_offset) {
            return Err(index_error(format!(
                "keyframe {} segment is out of bounds",
                e.id
            )));
        }
        if e.points == 0 || e.points > MAX_KEYFRAME_POINTS as u64 {
            return Err(index_error(format!(
                "keyframe {} has {} points",
                e.id, e.points
            )));
        }
        if e.bbox.iter().any(|v| !v.is_finite()) || !e.timestamp.is_finite() {
            return Err(index_error(format!(
                "keyframe {} has a non-finite field",
                e.id
            )));
        }
        entry_pose(e)?;
    }
    if previous.is_some_and(|p| index.next_id <= p) {
        return Err(index_error("next keyframe id is not above every id"));
    }
    let known = |id: &u64| index.keyframes.binary_search_by_key(id, |e| e.id).is_ok();
    let edges_known = index
        .covis_edges
        .iter()
        .all(|(a, b, _)| known(a) && known(b));
    let tree_known = index
        .covis_parents
        .iter()
        .all(|(c, p)| known(c) && known(p));
    if !edges_known || !tree_known || !index.covis_keyframes.iter().all(known) {
        return Err(index_error("covisibility graph names unknown keyframes"));
    }
    Ok(())
}

/// Opens a map file: memory-maps it read-only, checks the header and the index, and
/// returns a map whose keyframes are read in place. No tree or covariance is built
/// when the file holds them.
///
/// The file must not be modified while it is open (kfmap writes maps by rename, which
/// never modifies an open file).
pub fn open_map(path: &Path, options: OpenOptions) -> Result<OpenedMap, ArchiveError> {
    let io = |e: std::io::Error| ArchiveError::io(path, &e);
    let meta = std::fs::metadata(path).map_err(io)?;
    if !meta.is_file() {
        return Err(ArchiveError::NotAFile(path.to_path_buf()));
    }
    if meta.len() == 0 {
        return Err(ArchiveError::EmptyFile(path.to_path_buf()));
    }
    let file = File::open(path).map_err(io)?;
    // SAFETY: a read-only private mapping; see the note above on concurrent writers.
    let mmap = Arc::new(unsafe { Mmap::map(&file) }.map_err(io)?);
    let header = Header::decode(&mmap)?;
    let expected = (HEADER_LEN as u64).saturating_add(header.payload_len);
    if (mmap.len() as u64) < expected {
        return Err(ArchiveError::Truncated {
            expected,
            actual: mmap.len() as u64,
        });
    }
    if (mmap.len() as u64) > expected {
        return Err(index_error(format!(
            "{} unexpected bytes after the payload",
            mmap.len() as u64 - expected
        )));
    }
    let index_end = header.index_offset.checked_add(header.index_len);
    if header.index_offset % SEGMENT_ALIGN != 0
        || index_end.is_none_or(|end| end > header.payload_len)
    {
        return Err(index_error("index location is outside the payload"));
    }
    let start = HEADER_LEN + header.index_offset as usize;
    let index_bytes = &mmap[start..start + header.index_len as usize];
    if xxh3_64(index_bytes) != header.index_checksum {
        return Err(index_error("checksum mismatch"));
    }
    let index = rkyv::from_bytes::<MapIndex, rancor::Error>(index_bytes)
        .map_err(|e| index_error(format!("invalid archive: {e}")))?;
    check_index(&index, header.index_offset)?;
    let mut map_options: KeyframeMapOptions = toml::from_str(&header.options_toml)
        .map_err(|e| ArchiveError::BadOptions(e.message().to_owned()))?;
    map_options
        .validate()
        .map_err(|e| ArchiveError::BadOptions(e.to_string()))?;
    map_options.approximate_cov = options.approximate_cov;
    let keyframes = index
        .keyframes
        .iter()
        .map(|e| {
            let [x0, y0, z0, x1, y1, z1] = e.bbox;
            let data = BakedKeyframe {
                file: Arc::clone(&mmap),
                start: HEADER_LEN + e.offset as usize,
                byte_len: e.len as usize,
                checksum: e.checksum,
                id: e.id,
                points: e.points as usize,
                trust: options.trust,
                covariance: map_options.covariance,
                prepared: OnceLock::new(),
            };
            let bbox = Aabb {
                min: [x0, y0, z0],
                max: [x1, y1, z1],
            };
            Ok(Keyframe::baked(
                e.id,
                entry_pose(e)?,
                e.timestamp,
                bbox,
                data,
            ))
        })
        .collect::<Result<Vec<_>, ArchiveError>>()?;
    let covis = CovisibilityGraph::from_snapshot(
        map_options.covisibility,
        &CovisSnapshot {
            keyframes: index.covis_keyframes.clone(),
            edges: index.covis_edges.clone(),
            parents: index.covis_parents.clone(),
            in_tree: index.covis_in_tree.clone(),
        },
    );
    let map = KeyframeMap::from_parts(map_options, keyframes, index.next_id, covis);
    let place = index
        .place
        .map(|e| BakedPlaceGrid::new(&mmap, &e, options.trust));
    Ok(OpenedMap {
        map,
        header,
        index,
        place,
        file: mmap,
    })
}
