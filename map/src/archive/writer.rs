//! Writing a `.kfmap` file keyframe by keyframe, or a batch at a time (memory stays bounded by
//! the keyframes in hand), atomically: a temporary file beside the target, fsync, rename.

use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use rkyv::rancor;
use rkyv::util::AlignedVec;
use xxhash_rust::xxh3::{Xxh3, xxh3_64};

use super::ArchiveError;
use super::header::{HEADER_LEN, Header, SEGMENT_ALIGN};
use super::records::{
    GravityRecord, KeyframeEntry, KeyframeRecord, MapIndex, PlaceEntry, PlaceGridRecord,
};

/// The identity pose as stored.
const IDENTITY: [f64; 7] = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0];
use crate::covis::CovisSnapshot;
use crate::map::{Keyframe, KeyframeMap, KeyframeMapOptions};
use crate::place::{GridBuilder, GridContribution, GridError, GridParams, PlaceGrid};
use kfmap_geometry::geometry::{Pose, pose_to_xyz_quat};
use kfmap_geometry::io::temp_path_beside;

/// Points one keyframe segment may hold: its archive (about 70 bytes a point with tree
/// and covariances) must stay well inside rkyv's 2 GiB relative-pointer reach.
pub const MAX_KEYFRAME_POINTS: usize = 16 << 20;

/// What a finished write produced.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WriteSummary {
    /// Keyframes written.
    pub keyframes: usize,
    /// Points written.
    pub points: u64,
    /// File size, bytes.
    pub bytes: u64,
    /// The place grid's segment, bytes (0 without a grid).
    pub place_bytes: u64,
}

/// A keyframe serialized for a map file: done once and appended to as many files as hold
/// the keyframe (a tile set's tiles and halos), every copy byte-identical.
pub struct SerializedKeyframe {
    bytes: AlignedVec<{ SEGMENT_ALIGN as usize }>,
    /// xxh3-64 of `bytes`.
    checksum: u64,
    point_bytes: u64,
    covariance_bytes: u64,
    has_view_dirs: bool,
}

impl SerializedKeyframe {
    /// `keyframe`'s segment as a map with `options` stores it.
    pub fn new(keyframe: &Keyframe, options: &KeyframeMapOptions) -> Result<Self, ArchiveError> {
        if keyframe.len() > MAX_KEYFRAME_POINTS {
            return Err(ArchiveError::KeyframeTooLarge {
                id: keyframe.id,
                points: keyframe.len(),
                max: MAX_KEYFRAME_POINTS,
            });
        }
        let view = keyframe.view()?;
        let tree = options.serialize_kdtrees.then(|| view.tree.into());
        let record = KeyframeRecord {
            id: keyframe.id,
            points: view.points,
            view_dirs: view.view_dirs,
            covariances: options.serialize_covariances.then_some(view.covariances),
            weights: view.weights,
            tree,
        };
        let bytes = rkyv::api::high::to_bytes_in::<_, rancor::Error>(
            &record,
            AlignedVec::<{ SEGMENT_ALIGN as usize }>::new(),
        )
        .map_err(|e| ArchiveError::Serialize(format!("keyframe {}: {e}", keyframe.id)))?;
        let n = keyframe.len() as u64;
        Ok(Self {
            checksum: xxh3_64(&bytes),
            point_bytes: 12 * n * if record.view_dirs.is_some() { 2 } else { 1 }
                + if record.weights.is_some() { 4 * n } else { 0 },
            covariance_bytes: if record.covariances.is_some() {
                24 * n
            } else {
                0
            },
            has_view_dirs: record.view_dirs.is_some(),
            bytes,
        })
    }

    /// The segment's size, bytes.
    pub fn segment_bytes(&self) -> u64 {
        self.bytes.len() as u64
    }
}

/// Where a map's place grid comes from.
enum PlaceSource {
    /// Built from the keyframes written.
    Built(GridBuilder),
    /// Given ([`MapWriter::use_place_grid`]; a tile's, cut from its whole map's), `None`
    /// until it is.
    Given(Option<Result<PlaceGrid, GridError>>),
}

/// Bytes a writer appends between asking the kernel to start writing them back
/// (`sync_file_range`), so the disk works while the bake computes instead of all at
/// the final fsync.
const WRITEBACK_STEP: u64 = 32 << 20;

/// A map file being written. Dropping it before [`finish`](Self::finish) removes the
/// temporary file: the target path is never left partial.
pub struct MapWriter {
    path: PathBuf,
    tmp: PathBuf,
    file: BufWriter<File>,
    payload: Xxh3,
    offset: u64,
    /// `offset` when writeback was last started.
    written_back: u64,
    options: KeyframeMapOptions,
    index: MapIndex,
    place: PlaceSource,
    /// `finish` fsyncs the file (else the caller makes it durable: [`Self::leave_sync_to_caller`]).
    sync: bool,
    finished: bool,
}

impl MapWriter {
    /// Starts writing a map with `options` to `path`.
    pub fn create(path: &Path, options: &KeyframeMapOptions) -> Result<Self, ArchiveError> {
        Self::create_buffered(path, options, 1 << 20)
    }

    /// As [`Self::create`], buffering `buffer` bytes (a tile set holds hundreds of
    /// writers open at once; segments larger than the buffer bypass it).
    pub fn create_buffered(
        path: &Path,
        options: &KeyframeMapOptions,
        buffer: usize,
    ) -> Result<Self, ArchiveError> {
        let tmp = temp_path_beside(path).map_err(|e| ArchiveError::Io {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
        // Fails early when the options cannot fit in the header.
        Header::new(options_toml(options)?).encode()?;
        let file = File::create(&tmp).map_err(|e| ArchiveError::io(&tmp, &e))?;
        let mut writer = Self {
            path: path.to_path_buf(),
            tmp,
            file: BufWriter::with_capacity(buffer, file),
            payload: Xxh3::new(),
            offset: 0,
            written_back: 0,
            options: *options,
            index: MapIndex {
                map_from_input: IDENTITY,
                ..MapIndex::default()
            },
            place: PlaceSource::Built(GridBuilder::new(&GridParams::default())),
            sync: true,
            finished: false,
        };
        // Placeholder: the real header is written last, when the payload is known.
        writer.write_raw(&[0u8; HEADER_LEN])?;
        Ok(writer)
    }

    fn write_raw(&mut self, bytes: &[u8]) -> Result<(), ArchiveError> {
        self.file
            .write_all(bytes)
            .map_err(|e| ArchiveError::io(&self.path, &e))
    }

    /// Appends payload bytes at the next multiple of `align`; returns their offset.
    fn append(&mut self, bytes: &[u8], align: u64) -> Result<u64, ArchiveError> {
        let pad = (align - self.offset % align) % align;
        let zeros = vec![0u8; pad as usize];
        self.write_raw(&zeros)?;
        self.payload.update(&zeros);
        let at = self.offset + pad;
        self.write_raw(bytes)?;
        self.payload.update(bytes);
        self.offset = at + bytes.len() as u64;
        Ok(at)
    }

    /// Appends one keyframe (ids must ascend); returns its segment's size in bytes.
    pub fn write_keyframe(&mut self, keyframe: &Keyframe) -> Result<u64, ArchiveError> {
        let serialized = SerializedKeyframe::new(keyframe, &self.options)?;
        let place = self.place_contribution(keyframe)?;
        self.commit(keyframe, &serialized, place)
    }

    /// Appends keyframes (ids ascending), each serialized and its part of the place
    /// grid found in parallel; the bytes are appended in order, so the file is the
    /// one [`Self::write_keyframe`] one by one writes.
    pub fn write_keyframes(&mut self, keyframes: &[Keyframe]) -> Result<(), ArchiveError> {
        let prepared: Vec<(SerializedKeyframe, Option<GridContribution>)> = keyframes
            .par_iter()
            .map(|k| {
                Ok((
                    SerializedKeyframe::new(k, &self.options)?,
                    self.place_contribution(k)?,
                ))
            })
            .collect::<Result<_, ArchiveError>>()?;
        for (keyframe, (serialized, place)) in keyframes.iter().zip(prepared) {
            self.commit(keyframe, &serialized, place)?;
        }
        self.start_writeback()
    }

    /// Appends `keyframe` as `serialized` (made with this map's options; ids must
    /// ascend); returns its segment's size in bytes.
    pub fn append_serialized(
        &mut self,
        keyframe: &Keyframe,
        serialized: &SerializedKeyframe,
    ) -> Result<u64, ArchiveError> {
        let place = self.place_contribution(keyframe)?;
        let len = self.commit(keyframe, serialized, place)?;
        self.start_writeback()?;
        Ok(len)
    }

    /// `keyframe`'s part of the place grid this writer builds (none when it is given).
    fn place_contribution(
        &self,
        keyframe: &Keyframe,
    ) -> Result<Option<GridContribution>, ArchiveError> {
        Ok(match &self.place {
            PlaceSource::Built(builder) => Some(builder.contribution(keyframe.map_points()?)),
            PlaceSource::Given(_) => None,
        })
    }

    /// Asks the kernel to start writing back what was appended (Linux; elsewhere the
    /// final fsync does it all) once [`WRITEBACK_STEP`] bytes have piled up.
    fn start_writeback(&mut self) -> Result<(), ArchiveError> {
        if self.offset - self.written_back < WRITEBACK_STEP {
            return Ok(());
        }
        self.write_back()
    }

    /// Asks the kernel to start writing back everything appended so far, without
    /// waiting for it (a tile set's files each grow too little to ask on their own).
    pub fn write_back(&mut self) -> Result<(), ArchiveError> {
        if self.offset == self.written_back {
            return Ok(());
        }
        self.written_back = self.offset;
        self.file
            .flush()
            .map_err(|e| ArchiveError::io(&self.path, &e))?;
        #[cfg(target_os = "linux")]
        {
            use std::os::fd::AsRawFd;
            // SAFETY: the descriptor is this writer's open file; the call only starts
            // writeback of its dirty pages (offset 0, length 0: the whole file).
            unsafe {
                libc::sync_file_range(
                    self.file.get_ref().as_raw_fd(),
                    0,
                    0,
                    libc::SYNC_FILE_RANGE_WRITE,
                );
            }
        }
        Ok(())
    }

    /// Appends a serialized keyframe and enters it in the index.
    fn commit(
        &mut self,
        keyframe: &Keyframe,
        serialized: &SerializedKeyframe,
        place: Option<GridContribution>,
    ) -> Result<u64, ArchiveError> {
        if self
            .index
            .keyframes
            .last()
            .is_some_and(|k| k.id >= keyframe.id)
        {
            return Err(ArchiveError::Serialize(format!(
                "keyframe {} out of order (ids must ascend)",
                keyframe.id
            )));
        }
        let bytes = &serialized.bytes;
        let offset = self.append(bytes, SEGMENT_ALIGN)?;
        if let (Some(place), PlaceSource::Built(builder)) = (place, &mut self.place) {
            builder.add_anchor(keyframe.pose.translation.vector.into());
            builder.add(place);
        }
        let b = &keyframe.bbox;
        self.index.keyframes.push(KeyframeEntry {
            id: keyframe.id,
            timestamp: keyframe.timestamp,
            pose: pose_bits(&keyframe.pose),
            bbox: [b.min[0], b.min[1], b.min[2], b.max[0], b.max[1], b.max[2]],
            points: keyframe.len() as u64,
            offset,
            len: bytes.len() as u64,
            checksum: serialized.checksum,
            point_bytes: serialized.point_bytes,
            covariance_bytes: serialized.covariance_bytes,
            has_view_dirs: serialized.has_view_dirs,
        });
        Ok(bytes.len() as u64)
    }

    /// Records `T_map_input`: how the input poses were moved into the map frame.
    pub fn set_map_from_input(&mut self, pose: &Pose) {
        self.index.map_from_input = pose_to_xyz_quat(pose);
    }

    /// Writes `grid` as the map's place grid instead of one built from the keyframes
    /// (a tile's, cut from its whole map's voxels: `place::MarkedVoxels::cut`); an error is
    /// written as a map without a grid, as a failed build is. Call it, or
    /// [`Self::expect_place_grid`], before the keyframes, so they are not gathered for a
    /// grid never written.
    pub fn use_place_grid(&mut self, grid: Result<PlaceGrid, GridError>) {
        self.place = PlaceSource::Given(Some(grid));
    }

    /// `finish` renames the file into place without an fsync: the caller makes it
    /// durable (a tile set syncs its file system once, before writing its index).
    pub fn leave_sync_to_caller(&mut self) {
        self.sync = false;
    }

    /// The place grid will be given ([`Self::use_place_grid`]) once every keyframe is
    /// written: a streamed tile's is cut from the whole map's, known only then.
    pub fn expect_place_grid(&mut self) {
        if let PlaceSource::Built(_) = self.place {
            self.place = PlaceSource::Given(None);
        }
    }

    /// Writes the index and the header, fsyncs and renames onto the target path.
    pub fn finish(
        mut self,
        next_id: u64,
        covis: &CovisSnapshot,
        gravity_pool: &[GravityRecord],
    ) -> Result<WriteSummary, ArchiveError> {
        self.index.next_id = next_id;
        self.index.covis_keyframes = covis.keyframes.clone();
        self.index.covis_edges = covis.edges.clone();
        self.index.covis_parents = covis.parents.clone();
        self.index.covis_in_tree = covis.in_tree.clone();
        self.index.gravity_pool = gravity_pool.to_vec();
        let place = std::mem::replace(&mut self.place, PlaceSource::Given(None));
        let grid = match place {
            PlaceSource::Built(builder) => builder.finish(&GridParams::default()),
            PlaceSource::Given(Some(given)) => given,
            PlaceSource::Given(None) => {
                return Err(ArchiveError::Serialize(
                    "no place grid was given before finishing (expect_place_grid)".into(),
                ));
            }
        };
        self.index.place = match grid {
            Ok(grid) => Some(self.write_place_grid(&grid)?),
            Err(e) => {
                // The map still serves; only relocalization is refused, naming this.
                tracing::warn!("map written without a place grid (no relocalization): {e}");
                None
            }
        };
        let index = std::mem::take(&mut self.index);
        let bytes = rkyv::to_bytes::<rancor::Error>(&index)
            .map_err(|e| ArchiveError::Serialize(format!("map index: {e}")))?;
        let index_offset = self.append(&bytes, SEGMENT_ALIGN)?;
        let mut header = Header::new(options_toml(&self.options)?);
        header.payload_len = self.offset;
        header.payload_checksum = self.payload.digest();
        header.index_offset = index_offset;
        header.index_len = bytes.len() as u64;
        header.index_checksum = xxh3_64(&bytes);
        let header_bytes = header.encode()?;
        let io = |e: std::io::Error| ArchiveError::io(&self.path, &e);
        self.file.seek(SeekFrom::Start(0)).map_err(io)?;
        self.file.write_all(&header_bytes).map_err(io)?;
        self.file.flush().map_err(io)?;
        if self.sync {
            self.file.get_ref().sync_all().map_err(io)?;
        }
        std::fs::rename(&self.tmp, &self.path).map_err(io)?;
        if let Some(dir) = self
            .path
            .parent()
            .filter(|d| self.sync && !d.as_os_str().is_empty())
        {
            // Persist the rename itself; not every platform can open a directory.
            if let Ok(d) = File::open(dir) {
                let _ = d.sync_all();
            }
        }
        self.finished = true;
        Ok(WriteSummary {
            keyframes: index.keyframes.len(),
            points: index.keyframes.iter().map(|k| k.points).sum(),
            bytes: HEADER_LEN as u64 + self.offset,
            place_bytes: index.place.as_ref().map_or(0, |p| p.len),
        })
    }
}

impl Drop for MapWriter {
    fn drop(&mut self) {
        if !self.finished {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

impl MapWriter {
    fn write_place_grid(&mut self, grid: &PlaceGrid) -> Result<PlaceEntry, ArchiveError> {
        let record = PlaceGridRecord {
            resolution: grid.resolution,
            grid_from_map: grid.grid_from_map,
            origin: grid.origin,
            dims: grid.dims,
            levels: grid.levels,
            region_min: grid.region.min,
            region_max: grid.region.max,
            directory: &grid.levels_data.directory,
            keys: &grid.levels_data.keys,
            entries: &grid.levels_data.entries,
            words: &grid.levels_data.words,
        };
        let bytes = rkyv::api::high::to_bytes_in::<_, rancor::Error>(
            &record,
            AlignedVec::<{ SEGMENT_ALIGN as usize }>::new(),
        )
        .map_err(|e| ArchiveError::Serialize(format!("place grid: {e}")))?;
        let offset = self.append(&bytes, SEGMENT_ALIGN)?;
        Ok(PlaceEntry {
            offset,
            len: bytes.len() as u64,
            checksum: xxh3_64(&bytes),
        })
    }
}

/// x y z qx qy qz qw exactly as held (no re-normalization), so a reopened map answers
/// bit-identically.
fn pose_bits(p: &Pose) -> [f64; 7] {
    let t = p.translation.vector;
    let q = p.rotation.quaternion();
    [t.x, t.y, t.z, q.i, q.j, q.k, q.w]
}

fn options_toml(options: &KeyframeMapOptions) -> Result<String, ArchiveError> {
    toml::to_string(options).map_err(|e| ArchiveError::Serialize(format!("map options: {e}")))
}

/// Writes a whole map (keyframes, covisibility graph, `gravity_pool`) to `path`.
pub fn save_map(
    map: &KeyframeMap,
    gravity_pool: &[GravityRecord],
    path: &Path,
) -> Result<WriteSummary, ArchiveError> {
    let mut writer = MapWriter::create(path, map.options())?;
    for keyframe in map.keyframes() {
        writer.write_keyframe(keyframe)?;
    }
    writer.finish(map.next_id(), &map.covisibility().snapshot(), gravity_pool)
}
