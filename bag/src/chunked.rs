//! What MCAP and ROS 1 bags share: a read-only memory map of the file, messages that
//! live in chunks, each decompressed (or read in place from the map) when a message in
//! it is wanted, with the last chunk kept so that sequential reads decompress each
//! chunk once; topics built from the channels (MCAP) or connections (ROS 1) recorded on
//! them, with their messages tallied.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::hash::Hash;
use std::ops::Range;
use std::path::Path;
use std::sync::{Arc, Mutex};

use memmap2::Mmap;

use crate::raw::{Cursor, RawError};
use crate::{BagError, Container, Message, MessageRef, Topic};

/// Maps the bag file at `path` read-only.
pub(crate) fn map_file(path: &Path) -> Result<Mmap, BagError> {
    let file = File::open(path).map_err(|e| BagError::os(path, e))?;
    // SAFETY: the file is opened read-only and mapped privately; it is never written
    // through the map. Another process truncating or rewriting it while it is open
    // is the accepted risk (as for kfmap's own maps): recorders write new files and
    // do not modify finished ones.
    unsafe { Mmap::map(&file) }.map_err(|e| BagError::os(path, e))
}

/// A cursor from file offset `at` of `map` to the end of the file.
pub(crate) fn cursor_at(map: &[u8], at: u64) -> Result<Cursor<'_>, RawError> {
    if at >= map.len() as u64 {
        return Err(RawError::new(
            at,
            format!(
                "an index points past the end of the file ({} bytes): truncated",
                map.len()
            ),
        ));
    }
    // Checked just above.
    Ok(Cursor::new(&map[at as usize..], at))
}

/// A cursor at the message `at`: in `chunk` (the records of the chunk at `at.locator`)
/// at `at.offset`, offsets then counting from the chunk's records, or, outside chunks,
/// in `map` at `at.locator`. `path` names the bag in errors.
pub(crate) fn message_cursor<'a>(
    map: &'a [u8],
    path: &Path,
    at: &MessageRef,
    chunk: Option<&'a ChunkBytes>,
) -> Result<Cursor<'a>, BagError> {
    let Some(chunk) = chunk else {
        return cursor_at(map, at.locator)
            .map_err(|e| BagError::malformed(path, e.offset, e.reason));
    };
    let bytes = chunk.bytes(map);
    if at.offset >= bytes.len() as u64 {
        return Err(BagError::malformed(
            path,
            at.locator,
            format!(
                "a message index offset {} past the chunk's {} bytes",
                at.offset,
                bytes.len()
            ),
        ));
    }
    // Checked just above.
    Ok(Cursor::new(&bytes[at.offset as usize..], at.offset))
}

/// The messages of one channel (MCAP) or connection (ROS 1): how many, and the first
/// and last log time (ns).
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Tally {
    pub(crate) count: u64,
    pub(crate) first: Option<u64>,
    pub(crate) last: Option<u64>,
}

impl Tally {
    /// Counts a message logged at `log_time`.
    pub(crate) fn add(&mut self, log_time: u64) {
        self.count += 1;
        self.first = Some(self.first.map_or(log_time, |f| f.min(log_time)));
        self.last = Some(self.last.map_or(log_time, |l| l.max(log_time)));
    }
}

/// The topics of a bag's `channels` (MCAP channels or ROS 1 connections by id, each
/// described as the [`Topic`] it records, with no messages counted yet), sorted by
/// name, with the ids recorded on each. A topic recorded on several channels is one
/// topic, typed by its lowest id, holding every id's messages (`tallies`).
pub(crate) fn topics_of<Id: Copy + Ord + Hash>(
    mut channels: Vec<(Id, Topic)>,
    tallies: &HashMap<Id, Tally>,
) -> (Vec<Topic>, HashMap<String, Vec<Id>>) {
    channels.sort_unstable_by_key(|(id, _)| *id);
    let mut topics: BTreeMap<String, Topic> = BTreeMap::new();
    let mut ids_of: HashMap<String, Vec<Id>> = HashMap::new();
    for (id, channel) in channels {
        let tally = tallies.get(&id).copied().unwrap_or_default();
        ids_of.entry(channel.name.clone()).or_default().push(id);
        let topic = topics.entry(channel.name.clone()).or_insert(channel);
        topic.count += tally.count;
        topic.first_ns = merged(topic.first_ns, tally.first, u64::min);
        topic.last_ns = merged(topic.last_ns, tally.last, u64::max);
    }
    (topics.into_values().collect(), ids_of)
}

/// `pick` of two optional times; either one when the other is missing.
fn merged(a: Option<u64>, b: Option<u64>, pick: fn(u64, u64) -> u64) -> Option<u64> {
    match (a, b) {
        (Some(a), Some(b)) => Some(pick(a, b)),
        (a, b) => a.or(b),
    }
}

/// The `offset` of a message record that lies outside any chunk.
pub(crate) const NOT_IN_CHUNK: u64 = u64::MAX;

/// A chunk's records, decompressed or in place.
#[derive(Clone)]
pub(crate) enum ChunkBytes {
    /// An uncompressed chunk: this range of the map.
    Mapped(Range<usize>),
    /// A decompressed chunk.
    Owned(Arc<[u8]>),
}

impl ChunkBytes {
    /// The records, given the map the ranges were cut from.
    pub(crate) fn bytes<'a>(&'a self, map: &'a [u8]) -> &'a [u8] {
        match self {
            ChunkBytes::Mapped(range) => &map[range.clone()],
            ChunkBytes::Owned(bytes) => bytes,
        }
    }
}

/// A container whose messages live in chunks: it is a [`Container`] through the
/// chunk caches of [`stream`] and [`read`].
pub(crate) trait Chunked: Send + Sync {
    /// Every topic, sorted by name.
    fn chunked_topics(&self) -> &[Topic];
    /// Where every message of `topic` lies, in any order.
    fn message_refs(&self, topic: &Topic) -> Result<Vec<MessageRef>, BagError>;
    /// The records of the chunk at file offset `locator`.
    fn chunk_bytes(&self, locator: u64) -> Result<ChunkBytes, BagError>;
    /// The message at `at`, from `chunk` (the records of chunk `at.locator`) or, for a
    /// record outside any chunk, from the file.
    fn message(&self, at: &MessageRef, chunk: Option<&ChunkBytes>) -> Result<Message, BagError>;
    /// The chunk [`read`] decompressed last, shared by every reader of the bag.
    fn last_chunk(&self) -> &Mutex<Option<(u64, ChunkBytes)>>;
}

impl<C: Chunked> Container for C {
    fn topics(&self) -> &[Topic] {
        self.chunked_topics()
    }

    fn messages<'a>(
        &'a self,
        topic: &Topic,
    ) -> Result<Box<dyn Iterator<Item = Result<Message, BagError>> + Send + 'a>, BagError> {
        Ok(stream(self, self.index(topic)?))
    }

    fn index(&self, topic: &Topic) -> Result<Vec<MessageRef>, BagError> {
        let mut refs = self.message_refs(topic)?;
        // Log-time order; ties in file order.
        refs.sort_unstable_by_key(|r| (r.log_time_ns, r.locator, r.offset));
        Ok(refs)
    }

    fn read(&self, at: &MessageRef) -> Result<Message, BagError> {
        read(self, at)
    }
}

/// The messages at `refs`, in order, through a one-chunk cache private to the stream
/// (memory: one chunk, plus the refs at 24 bytes a message); ends after an error.
pub(crate) fn stream<'a, C: Chunked>(
    bag: &'a C,
    refs: Vec<MessageRef>,
) -> Box<dyn Iterator<Item = Result<Message, BagError>> + Send + 'a> {
    let mut chunk: Option<(u64, ChunkBytes)> = None;
    let mut failed = false;
    Box::new(refs.into_iter().map_while(move |at| {
        if failed {
            return None;
        }
        let result = if at.offset == NOT_IN_CHUNK {
            bag.message(&at, None)
        } else {
            let cached = match &chunk {
                Some((locator, bytes)) if *locator == at.locator => Ok(bytes.clone()),
                _ => bag.chunk_bytes(at.locator),
            };
            cached.and_then(|bytes| {
                let message = bag.message(&at, Some(&bytes));
                chunk = Some((at.locator, bytes));
                message
            })
        };
        failed = result.is_err();
        Some(result)
    }))
}

/// The message at `at`, its chunk through the bag's shared one-chunk cache.
pub(crate) fn read<C: Chunked>(bag: &C, at: &MessageRef) -> Result<Message, BagError> {
    if at.offset == NOT_IN_CHUNK {
        return bag.message(at, None);
    }
    let lock = || bag.last_chunk().lock().unwrap_or_else(|e| e.into_inner());
    let cached = lock()
        .as_ref()
        .filter(|(locator, _)| *locator == at.locator)
        .map(|(_, chunk)| chunk.clone());
    let chunk = match cached {
        Some(chunk) => chunk,
        None => {
            // Decompressed without the lock: readers of other chunks need not wait.
            let chunk = bag.chunk_bytes(at.locator)?;
            *lock() = Some((at.locator, chunk.clone()));
            chunk
        }
    };
    bag.message(at, Some(&chunk))
}
