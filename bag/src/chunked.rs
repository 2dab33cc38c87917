//! What MCAP and ROS 1 bags share: messages live in chunks, each decompressed (or read
//! in place from the memory map) when a message in it is wanted, with the last chunk
//! kept so that sequential reads decompress each chunk once.

use std::ops::Range;
use std::sync::{Arc, Mutex};

use crate::{BagError, Message, MessageRef};

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

/// A container whose messages live in chunks.
pub(crate) trait Chunked: Sync {
    /// The records of the chunk at file offset `locator`.
    fn chunk_bytes(&self, locator: u64) -> Result<ChunkBytes, BagError>;
    /// The message at `at`, from `chunk` (the records of chunk `at.locator`) or, for a
    /// record outside any chunk, from the file.
    fn message(&self, at: &MessageRef, chunk: Option<&ChunkBytes>) -> Result<Message, BagError>;
    /// The chunk [`read`] decompressed last, shared by every reader of the bag.
    fn last_chunk(&self) -> &Mutex<Option<(u64, ChunkBytes)>>;
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
