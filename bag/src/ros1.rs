//! ROS 1 bags, format version 2.0 (`rosbag record`), memory-mapped.
//!
//! Written here rather than taken from a crate: the Rust ROS 1 bag readers on crates.io
//! are unmaintained, and the format is small: after the line `#ROSBAG V2.0\n`, records of
//! `header_len u32, header, data_len u32, data`, the header a list of `field_len u32,
//! name=value` fields whose `op` says what the record is:
//!
//! - `0x03` bag header: `index_pos`, `conn_count`, `chunk_count`;
//! - `0x05` chunk: `compression` (`none`, `bz2`, `lz4`) and `size` (uncompressed), its
//!   data the records of the messages (`0x02`: `conn`, `time`) and connections (`0x07`);
//! - `0x04` index data after each chunk: per connection, `(time, offset)` of each of its
//!   messages in the decompressed chunk;
//! - at `index_pos`, the index section: `0x07` connection records (data: the connection
//!   header with `topic`, `type`, `md5sum`, `message_definition`), then `0x06` chunk info
//!   records (`chunk_pos`, times, per-connection counts).
//!
//! Opening reads the index section and the index data records (no decompression); a
//! [`MessageRef`] is the chunk record's position and the message record's offset in the
//! decompressed chunk, and [`Container::read`] decompresses only that chunk (the last one
//! is kept). A bag whose `index_pos` is 0 (a recorder killed before closing it) is read by
//! one linear scan of its chunks instead, which ignores an incomplete last record; a bag
//! whose index section is present but unreadable is scanned too, strictly. Every length
//! is checked against the file before anything is allocated from it.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use memmap2::Mmap;

use crate::chunked::{self, ChunkBytes, Chunked, NOT_IN_CHUNK, Tally};
use crate::raw::{Cursor, RawError, decompress_exact, lz4_exact};
use crate::{BagError, Encoding, Message, MessageRef, ROS1_MAGIC, Topic};

const OP_MESSAGE: u8 = 0x02;
const OP_BAG_HEADER: u8 = 0x03;
const OP_INDEX_DATA: u8 = 0x04;
const OP_CHUNK: u8 = 0x05;
const OP_CHUNK_INFO: u8 = 0x06;
const OP_CONNECTION: u8 = 0x07;
/// A chunk claiming more than this uncompressed is refused rather than allocated.
const MAX_CHUNK_BYTES: u64 = 4 << 30;
const SUPPORTED: &str = "none, bz2, lz4";

/// One record: its header fields and data, where they lie.
struct Record<'a> {
    /// File offset of the record (its `header_len`).
    at: u64,
    fields: Vec<(&'a [u8], &'a [u8])>,
    data: &'a [u8],
    /// File offset (or chunk offset) of `data`.
    data_at: u64,
}

impl<'a> Record<'a> {
    fn field(&self, name: &str) -> Result<&'a [u8], RawError> {
        self.fields
            .iter()
            .find(|(n, _)| *n == name.as_bytes())
            .map(|(_, v)| *v)
            .ok_or_else(|| RawError::new(self.at, format!("a record without its '{name}' field")))
    }

    fn op(&self) -> Result<u8, RawError> {
        match self.field("op")? {
            [op] => Ok(*op),
            _ => Err(RawError::new(self.at, "an 'op' field that is not one byte")),
        }
    }

    fn u32(&self, name: &str) -> Result<u32, RawError> {
        let value = self.field(name)?;
        <[u8; 4]>::try_from(value)
            .map(u32::from_le_bytes)
            .map_err(|_| RawError::new(self.at, format!("field '{name}' is not 4 bytes")))
    }

    fn u64(&self, name: &str) -> Result<u64, RawError> {
        let value = self.field(name)?;
        <[u8; 8]>::try_from(value)
            .map(u64::from_le_bytes)
            .map_err(|_| RawError::new(self.at, format!("field '{name}' is not 8 bytes")))
    }

    /// A `time` field (`u32` seconds, `u32` nanoseconds) in nanoseconds.
    fn time(&self, name: &str) -> Result<u64, RawError> {
        Ok(ros_time(self.u64(name)?))
    }

    fn string(&self, name: &str) -> Result<String, RawError> {
        Ok(String::from_utf8_lossy(self.field(name)?).into_owned())
    }
}

/// A ROS `time` (`u32` seconds then `u32` nanoseconds, little-endian) in nanoseconds.
fn ros_time(raw: u64) -> u64 {
    let (sec, nsec) = (raw & 0xffff_ffff, raw >> 32);
    sec * 1_000_000_000 + nsec
}

/// The next record of `c`.
fn next_record<'a>(c: &mut Cursor<'a>) -> Result<Record<'a>, RawError> {
    let at = c.offset();
    let header_len = c.u32("record header length")?;
    let header = c.bytes(u64::from(header_len), "record header")?;
    let data_len = c.u32("record data length")?;
    let data_at = c.offset();
    let data = c.bytes(u64::from(data_len), "record data")?;
    let mut fields = Vec::new();
    let mut h = Cursor::new(header, at + 4);
    while !h.is_empty() {
        let len = h.u32("header field length")?;
        let field_at = h.offset();
        let field = h.bytes(u64::from(len), "header field")?;
        let eq = field
            .iter()
            .position(|&b| b == b'=')
            .ok_or_else(|| RawError::new(field_at, "a header field without '='"))?;
        fields.push((&field[..eq], &field[eq + 1..]));
    }
    Ok(Record {
        at,
        fields,
        data,
        data_at,
    })
}

/// One chunk and where its index data records are.
struct Chunk {
    /// File offset of the chunk record.
    pos: u64,
    /// Connection id -> file offset of its index data record for this chunk.
    indexes: BTreeMap<u32, u64>,
}

/// A connection: its topic and message type.
#[derive(Clone)]
struct Connection {
    topic: String,
    msg_type: String,
}

/// An open ROS 1 bag.
pub(crate) struct Ros1Bag {
    path: PathBuf,
    map: Mmap,
    topics: Vec<Topic>,
    /// Connection ids of each topic name.
    connections_of: HashMap<String, Vec<u32>>,
    /// The chunks and their index data; `None` when the bag is read by scanning.
    chunks: Option<Vec<Chunk>>,
    /// Whether a scan stops quietly at an incomplete last record (unindexed bags).
    lenient_tail: bool,
    /// The chunk [`Container::read`] decompressed last.
    last_chunk: Mutex<Option<(u64, ChunkBytes)>>,
}

/// Connections by id.
type Connections = HashMap<u32, Connection>;
/// Tallies by connection id.
type Tallies = HashMap<u32, Tally>;

/// What a scan meets.
enum Scanned {
    Connection(u32, Connection),
    Message {
        conn: u32,
        time: u64,
        locator: u64,
        offset: u64,
    },
}

impl Ros1Bag {
    /// Opens `path`: maps it and reads its index (or scans it without one).
    pub(crate) fn open(path: &Path) -> Result<Self, BagError> {
        let map = chunked::map_file(path)?;
        let mut bag = Ros1Bag {
            path: path.to_path_buf(),
            map,
            topics: Vec::new(),
            connections_of: HashMap::new(),
            chunks: None,
            lenient_tail: false,
            last_chunk: Mutex::new(None),
        };
        let header = bag.bag_header().map_err(|e| bag.bad(e))?;
        let (connections, tallies) = if header.index_pos == 0 {
            bag.lenient_tail = true;
            bag.scan_for_topics()?
        } else {
            if header.index_pos >= bag.map.len() as u64 {
                return Err(BagError::malformed(
                    &bag.path,
                    bag.map.len() as u64,
                    format!(
                        "the bag header puts the index at byte {}, past the end of the file: truncated",
                        header.index_pos
                    ),
                ));
            }
            match bag.read_index(&header) {
                Ok((connections, chunks, tallies)) => {
                    bag.chunks = Some(chunks);
                    (connections, tallies)
                }
                // An index running past the end of the file (truncated, or a corrupt length)
                // stays an error; any other damage (a wrong record, a missing field): scan.
                Err(e) if e.reason.contains("truncated") => return Err(bag.bad(e)),
                Err(_) => bag.scan_for_topics()?,
            }
        };
        bag.build_topics(&connections, &tallies);
        Ok(bag)
    }

    fn bad(&self, e: RawError) -> BagError {
        BagError::malformed(&self.path, e.offset, e.reason)
    }

    fn bag_header(&self) -> Result<BagHeader, RawError> {
        let mut c = chunked::cursor_at(&self.map, ROS1_MAGIC.len() as u64)?;
        let record = next_record(&mut c)?;
        if record.op()? != OP_BAG_HEADER {
            return Err(RawError::new(
                record.at,
                "the first record is not the bag header",
            ));
        }
        Ok(BagHeader {
            index_pos: record.u64("index_pos")?,
            conn_count: record.u32("conn_count")?,
            chunk_count: record.u32("chunk_count")?,
            end: c.offset(),
        })
    }

    /// The index section and the index data records after each chunk.
    fn read_index(
        &self,
        header: &BagHeader,
    ) -> Result<(Connections, Vec<Chunk>, Tallies), RawError> {
        let mut c = chunked::cursor_at(&self.map, header.index_pos)?;
        let mut connections = HashMap::new();
        for _ in 0..header.conn_count {
            let record = next_record(&mut c)?;
            if record.op()? != OP_CONNECTION {
                return Err(RawError::new(
                    record.at,
                    "not a connection record in the index section",
                ));
            }
            let (id, connection) = parse_connection(&record)?;
            connections.insert(id, connection);
        }
        let mut chunks = Vec::new();
        let mut tallies: HashMap<u32, Tally> = HashMap::new();
        for _ in 0..header.chunk_count {
            let info = next_record(&mut c)?;
            if info.op()? != OP_CHUNK_INFO {
                return Err(RawError::new(
                    info.at,
                    "not a chunk info record in the index section",
                ));
            }
            let pos = info.u64("chunk_pos")?;
            if pos < header.end || pos >= header.index_pos {
                return Err(RawError::new(
                    info.at,
                    format!("a chunk position {pos} outside the data section"),
                ));
            }
            // The chunk record, then its index data records.
            let mut after = chunked::cursor_at(&self.map, pos)?;
            let chunk = next_record(&mut after)?;
            if chunk.op()? != OP_CHUNK {
                return Err(RawError::new(pos, "a chunk info points at no chunk"));
            }
            let mut indexes = BTreeMap::new();
            while after.offset() < header.index_pos {
                let mut peek = after.clone();
                let record = next_record(&mut peek)?;
                if record.op()? != OP_INDEX_DATA {
                    break;
                }
                let conn = record.u32("conn")?;
                if !connections.contains_key(&conn) {
                    return Err(RawError::new(
                        record.at,
                        format!("index data of connection {conn}, which the index lacks"),
                    ));
                }
                let tally = tallies.entry(conn).or_default();
                index_entries(&record, |time, _| tally.add(time))?;
                indexes.insert(conn, record.at);
                after = peek;
            }
            chunks.push(Chunk { pos, indexes });
        }
        Ok((connections, chunks, tallies))
    }

    /// Without a usable index: one pass over the records for connections and tallies.
    fn scan_for_topics(&self) -> Result<(Connections, Tallies), BagError> {
        let mut connections = HashMap::new();
        let mut tallies: HashMap<u32, Tally> = HashMap::new();
        self.scan(|item| match item {
            Scanned::Connection(id, c) => {
                connections.insert(id, c);
            }
            Scanned::Message { conn, time, .. } => tallies.entry(conn).or_default().add(time),
        })?;
        if let Some(conn) = tallies.keys().find(|c| !connections.contains_key(c)) {
            return Err(BagError::malformed(
                &self.path,
                0,
                format!("messages on connection {conn}, which no connection record defines"),
            ));
        }
        Ok((connections, tallies))
    }

    /// Walks every record after the bag header in file order, chunks decompressed one
    /// at a time.
    fn scan(&self, mut visit: impl FnMut(Scanned)) -> Result<(), BagError> {
        let header = self.bag_header().map_err(|e| self.bad(e))?;
        let mut c = chunked::cursor_at(&self.map, header.end).map_err(|e| self.bad(e))?;
        while !c.is_empty() {
            let record = match next_record(&mut c) {
                Ok(record) => record,
                // A killed recorder leaves its last record incomplete: read up to it.
                Err(_) if self.lenient_tail => break,
                Err(e) => return Err(self.bad(e)),
            };
            let op = record.op().map_err(|e| self.bad(e))?;
            if op == OP_CHUNK {
                let chunk = match self.chunk_bytes(record.at) {
                    Ok(chunk) => chunk,
                    Err(BagError::Malformed { .. }) if self.lenient_tail && c.is_empty() => break,
                    Err(e) => return Err(e),
                };
                let bytes = chunk.bytes(&self.map);
                let mut inner = Cursor::new(bytes, 0);
                while !inner.is_empty() {
                    let offset = inner.pos() as u64;
                    let in_chunk = |e: RawError| {
                        BagError::malformed(
                            &self.path,
                            record.at,
                            format!(
                                "in the chunk at this byte, record at {offset}: {}",
                                e.reason
                            ),
                        )
                    };
                    let inner_record = next_record(&mut inner).map_err(in_chunk)?;
                    scan_record(&inner_record, record.at, offset, &mut visit).map_err(in_chunk)?;
                }
            } else {
                scan_record(&record, record.at, NOT_IN_CHUNK, &mut visit)
                    .map_err(|e| self.bad(e))?;
            }
        }
        Ok(())
    }

    /// The topics of the bag's connections ([`chunked::topics_of`]).
    fn build_topics(&mut self, connections: &Connections, tallies: &Tallies) {
        let described = connections
            .iter()
            .map(|(&id, connection)| {
                let topic = Topic {
                    name: connection.topic.clone(),
                    msg_type: connection.msg_type.clone(),
                    encoding: Encoding::Ros1,
                    count: 0,
                    first_ns: None,
                    last_ns: None,
                };
                (id, topic)
            })
            .collect();
        (self.topics, self.connections_of) = chunked::topics_of(described, tallies);
    }
}

/// What the bag header record says.
struct BagHeader {
    index_pos: u64,
    conn_count: u32,
    chunk_count: u32,
    /// File offset just past the bag header record.
    end: u64,
}

/// A connection record's id and connection (topic from its header, type from the
/// connection header in its data).
fn parse_connection(record: &Record<'_>) -> Result<(u32, Connection), RawError> {
    let id = record.u32("conn")?;
    let topic = record.string("topic")?;
    // The data is a header of its own: `topic`, `type`, `md5sum`, `message_definition`.
    let mut data = Cursor::new(record.data, record.data_at);
    let mut msg_type = None;
    while !data.is_empty() {
        let len = data.u32("connection header field length")?;
        let field = data.bytes(u64::from(len), "connection header field")?;
        if let Some(value) = field.strip_prefix(b"type=") {
            msg_type = Some(String::from_utf8_lossy(value).into_owned());
        }
    }
    let msg_type =
        msg_type.ok_or_else(|| RawError::new(record.at, "a connection without its 'type'"))?;
    Ok((id, Connection { topic, msg_type }))
}

/// Calls `visit(time, offset)` for each entry of an index data record (version 1).
fn index_entries(record: &Record<'_>, mut visit: impl FnMut(u64, u64)) -> Result<(), RawError> {
    if record.u32("ver")? != 1 {
        return Err(RawError::new(
            record.at,
            "index data of a version other than 1",
        ));
    }
    let count = u64::from(record.u32("count")?);
    if count.saturating_mul(12) != record.data.len() as u64 {
        return Err(RawError::new(
            record.at,
            format!(
                "index data of {count} entries in {} bytes",
                record.data.len()
            ),
        ));
    }
    let mut entries = Cursor::new(record.data, record.data_at);
    for _ in 0..count {
        let time = ros_time(entries.u64("index time")?);
        let offset = entries.u32("index offset")?;
        visit(time, u64::from(offset));
    }
    Ok(())
}

fn scan_record(
    record: &Record<'_>,
    locator: u64,
    offset: u64,
    visit: &mut impl FnMut(Scanned),
) -> Result<(), RawError> {
    match record.op()? {
        OP_CONNECTION => {
            let (id, connection) = parse_connection(record)?;
            visit(Scanned::Connection(id, connection));
        }
        OP_MESSAGE => visit(Scanned::Message {
            conn: record.u32("conn")?,
            time: record.time("time")?,
            locator: if offset == NOT_IN_CHUNK {
                record.at
            } else {
                locator
            },
            offset,
        }),
        _ => {}
    }
    Ok(())
}

impl Chunked for Ros1Bag {
    fn chunked_topics(&self) -> &[Topic] {
        &self.topics
    }

    fn message_refs(&self, topic: &Topic) -> Result<Vec<MessageRef>, BagError> {
        let Some(ids) = self.connections_of.get(&topic.name) else {
            return Ok(Vec::new());
        };
        let mut refs = Vec::with_capacity(topic.count.min(1 << 24) as usize);
        match &self.chunks {
            Some(chunks) => {
                for chunk in chunks {
                    for id in ids {
                        let Some(&at) = chunk.indexes.get(id) else {
                            continue;
                        };
                        let read = chunked::cursor_at(&self.map, at).and_then(|mut c| {
                            let record = next_record(&mut c)?;
                            index_entries(&record, |log_time_ns, offset| {
                                refs.push(MessageRef {
                                    log_time_ns,
                                    locator: chunk.pos,
                                    offset,
                                })
                            })
                        });
                        read.map_err(|e| self.bad(e))?;
                    }
                }
            }
            None => self.scan(|item| {
                if let Scanned::Message {
                    conn,
                    time,
                    locator,
                    offset,
                } = item
                    && ids.contains(&conn)
                {
                    refs.push(MessageRef {
                        log_time_ns: time,
                        locator,
                        offset,
                    });
                }
            })?,
        }
        Ok(refs)
    }

    /// The records of the chunk whose record starts at file offset `at`.
    fn chunk_bytes(&self, at: u64) -> Result<ChunkBytes, BagError> {
        let bad = |e: RawError| self.bad(e);
        let mut c = chunked::cursor_at(&self.map, at).map_err(bad)?;
        let record = next_record(&mut c).map_err(bad)?;
        if record.op().map_err(bad)? != OP_CHUNK {
            return Err(BagError::malformed(
                &self.path,
                at,
                "an index points at no chunk record",
            ));
        }
        let compression = record.string("compression").map_err(bad)?;
        let size = u64::from(record.u32("size").map_err(bad)?);
        let data = record.data;
        if size > MAX_CHUNK_BYTES {
            return Err(BagError::malformed(
                &self.path,
                at,
                format!("a chunk of {size} bytes uncompressed"),
            ));
        }
        let decoded = match compression.as_str() {
            "none" => {
                if size != data.len() as u64 {
                    return Err(BagError::malformed(
                        &self.path,
                        at,
                        format!(
                            "an uncompressed chunk of {} bytes whose header says {size}",
                            data.len()
                        ),
                    ));
                }
                // `data` lies in the map at `data_at`.
                let start = record.data_at as usize;
                return Ok(ChunkBytes::Mapped(start..start + data.len()));
            }
            "bz2" => decompress_exact(bzip2::read::BzDecoder::new(data), size, 64 << 20),
            "lz4" => lz4_exact(data, size, 64 << 20),
            _ => {
                return Err(BagError::Codec {
                    path: self.path.clone(),
                    offset: at,
                    codec: compression,
                    supported: SUPPORTED,
                });
            }
        };
        let decoded = decoded.map_err(|reason| {
            BagError::malformed(&self.path, at, format!("{compression} chunk: {reason}"))
        })?;
        Ok(ChunkBytes::Owned(decoded.into()))
    }

    /// The message at `at`, from `chunk` (the records of chunk `at.locator`) or, outside
    /// chunks, from the map.
    fn message(&self, at: &MessageRef, chunk: Option<&ChunkBytes>) -> Result<Message, BagError> {
        let mut c = chunked::message_cursor(&self.map, &self.path, at, chunk)?;
        let parsed = next_record(&mut c).and_then(|record| {
            if record.op()? != OP_MESSAGE {
                return Err(RawError::new(
                    at.offset,
                    "an index offset that points at no message record",
                ));
            }
            Ok(Message {
                log_time_ns: record.time("time")?,
                data: record.data.to_vec(),
            })
        });
        parsed.map_err(|e| match chunk {
            None => self.bad(e),
            Some(_) => BagError::malformed(
                &self.path,
                at.locator,
                format!(
                    "in the chunk at this byte, offset {} of its records: {}",
                    e.offset, e.reason
                ),
            ),
        })
    }

    fn last_chunk(&self) -> &Mutex<Option<(u64, ChunkBytes)>> {
        &self.last_chunk
    }
}
