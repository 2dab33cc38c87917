//! MCAP files (the rosbag2 default since Iron), memory-mapped.
//!
//! With a summary section (what every finished recording has), topics come from its
//! Schema and Channel records, and their counts and first / last log times from the
//! message indexes each chunk index points at: no chunk is decompressed to open the
//! file, and [`Container::index`] + [`Container::read`] decompress only the chunk that
//! holds the message. Without a summary, or with chunks that carry no message indexes,
//! one streaming pass over the data section (a chunk at a time) counts instead.
//!
//! The record framing is parsed here rather than with the `mcap` crate's readers
//! (whose constants are used): those reserve memory from untrusted length prefixes
//! (strings, records inside a decompressed chunk) and do unchecked offset arithmetic on
//! index fields, and a corrupt file must give an error, never an abort or a panic.
//! Chunks are decompressed into buffers that grow with the bytes really produced.
//! Chunk CRCs are checked when the writer set them; the summary CRC is not needed,
//! since every index field is checked against the file before it is followed.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use mcap::records::op;
use memmap2::Mmap;

use crate::chunked::{self, ChunkBytes, Chunked, NOT_IN_CHUNK, Tally};
use crate::raw::{Cursor, RawError, lz4_exact, zstd_exact};
use crate::{BagError, Encoding, Message, MessageRef, Topic};

/// Footer record: prefix + summary start + summary offset start + summary CRC.
const FOOTER_RECORD_LEN: usize = 9 + 8 + 8 + 4;
/// A chunk claiming more than this uncompressed is refused rather than allocated.
const MAX_CHUNK_BYTES: u64 = 4 << 30;
/// Codecs read, for the error that names an unsupported one.
const SUPPORTED: &str = "none, zstd, lz4";

/// One chunk as the summary indexes it.
#[derive(Debug, Clone)]
struct ChunkIndex {
    /// File offset of the chunk record.
    chunk_start: u64,
    /// Channel id -> file offset of its MessageIndex record for this chunk.
    message_indexes: BTreeMap<u16, u64>,
}

/// An open MCAP file.
pub(crate) struct McapBag {
    path: PathBuf,
    map: Mmap,
    topics: Vec<Topic>,
    /// Channel ids of each topic name.
    channels_of: HashMap<String, Vec<u16>>,
    /// The summary's chunk indexes, when they index every message; `None`: scan.
    chunks: Option<Vec<ChunkIndex>>,
    /// The chunk [`Container::read`] decompressed last (sequential reads hit it).
    last_chunk: Mutex<Option<(u64, ChunkBytes)>>,
}

/// Schema id -> schema name (the message type).
type Schemas = HashMap<u16, String>;
/// Channel id -> (topic, schema id, message encoding).
type Channels = HashMap<u16, (String, u16, String)>;

/// What the summary section holds (the parts kfmap uses).
#[derive(Default)]
struct Summary {
    schemas: Schemas,
    channels: Channels,
    chunk_indexes: Vec<ChunkIndex>,
    /// `message_count` of the Statistics record, if any.
    message_count: Option<u64>,
}

impl McapBag {
    /// Opens `path`: maps it, reads its summary (or scans it once without one).
    pub(crate) fn open(path: &Path) -> Result<Self, BagError> {
        let map = chunked::map_file(path)?;
        let mut bag = McapBag {
            path: path.to_path_buf(),
            map,
            topics: Vec::new(),
            channels_of: HashMap::new(),
            chunks: None,
            last_chunk: Mutex::new(None),
        };
        let summary = bag.read_summary().map_err(|e| bag.bad(e))?;
        let indexed = summary.as_ref().filter(|s| {
            let every_chunk_indexed = s
                .chunk_indexes
                .iter()
                .all(|c| !c.message_indexes.is_empty());
            let no_messages = s.message_count == Some(0);
            !s.channels.is_empty() && !s.chunk_indexes.is_empty() && every_chunk_indexed
                || no_messages
        });
        let (schemas, channels, tallies) = match indexed {
            Some(summary) => {
                let tallies = bag.tally_indexes(summary)?;
                bag.chunks = Some(summary.chunk_indexes.clone());
                (summary.schemas.clone(), summary.channels.clone(), tallies)
            }
            None => bag.scan_for_topics()?,
        };
        bag.build_topics(&schemas, &channels, &tallies);
        Ok(bag)
    }

    fn bad(&self, e: RawError) -> BagError {
        BagError::malformed(&self.path, e.offset, e.reason)
    }

    /// Parses the footer and the summary section; `None` when the file has no summary.
    fn read_summary(&self) -> Result<Option<Summary>, RawError> {
        let map = &self.map[..];
        let len = map.len();
        let magic = mcap::MAGIC.len();
        if len < 2 * magic + FOOTER_RECORD_LEN || !map.ends_with(mcap::MAGIC) {
            return Err(RawError::new(
                len as u64,
                "the file ends without the MCAP footer and end magic: truncated \
                 (a killed recorder? `mcap recover` rewrites such a file)",
            ));
        }
        let footer_at = len - magic - FOOTER_RECORD_LEN;
        let mut c = Cursor::new(&map[footer_at..len - magic], footer_at as u64);
        if c.u8("footer opcode")? != op::FOOTER || c.u64("footer length")? != 20 {
            return Err(RawError::new(
                footer_at as u64,
                "no Footer record before the end magic",
            ));
        }
        let summary_start = c.u64("summary start")?;
        if summary_start == 0 {
            return Ok(None);
        }
        if summary_start < magic as u64 || summary_start > footer_at as u64 {
            return Err(RawError::new(
                footer_at as u64,
                format!("the footer puts the summary at byte {summary_start}, outside the file"),
            ));
        }
        // Both bounds checked just above.
        let section = &map[summary_start as usize..footer_at];
        let mut records = Cursor::new(section, summary_start);
        let mut summary = Summary::default();
        while !records.is_empty() {
            let (opcode, mut body) = next_record(&mut records)?;
            match opcode {
                op::SCHEMA => {
                    let id = body.u16("schema id")?;
                    let name = body.string("schema name")?;
                    summary.schemas.insert(id, name);
                }
                op::CHANNEL => {
                    let (id, channel) = parse_channel(&mut body)?;
                    summary.channels.insert(id, channel);
                }
                op::CHUNK_INDEX => summary.chunk_indexes.push(parse_chunk_index(&mut body)?),
                op::STATISTICS => summary.message_count = Some(body.u64("message count")?),
                _ => {}
            }
        }
        Ok(Some(summary))
    }

    /// Counts and first / last log times per channel from the message indexes.
    fn tally_indexes(&self, summary: &Summary) -> Result<HashMap<u16, Tally>, BagError> {
        let mut tallies: HashMap<u16, Tally> = HashMap::new();
        for chunk in &summary.chunk_indexes {
            for (&channel, &at) in &chunk.message_indexes {
                if !summary.channels.contains_key(&channel) {
                    return Err(BagError::malformed(
                        &self.path,
                        at,
                        format!("a message index of channel {channel}, which the summary lacks"),
                    ));
                }
                let tally = tallies.entry(channel).or_default();
                self.message_index(channel, at, |log_time, _| tally.add(log_time))
                    .map_err(|e| self.bad(e))?;
            }
        }
        Ok(tallies)
    }

    /// Calls `visit(log_time, offset)` for every entry of the MessageIndex record at
    /// file offset `at`, which must index `channel`.
    fn message_index(
        &self,
        channel: u16,
        at: u64,
        mut visit: impl FnMut(u64, u64),
    ) -> Result<(), RawError> {
        let mut c = chunked::cursor_at(&self.map, at)?;
        let (opcode, mut body) = next_record(&mut c)?;
        if opcode != op::MESSAGE_INDEX {
            return Err(RawError::new(
                at,
                "the chunk index points at no MessageIndex record",
            ));
        }
        if body.u16("message index channel")? != channel {
            return Err(RawError::new(
                at,
                "a message index of another channel than its chunk index says",
            ));
        }
        let entries_len = body.u32("message index length")?;
        let mut entries = Cursor::new(
            body.bytes(u64::from(entries_len), "message index entries")?,
            body.offset(),
        );
        while !entries.is_empty() {
            let log_time = entries.u64("message index log time")?;
            let offset = entries.u64("message index offset")?;
            visit(log_time, offset);
        }
        Ok(())
    }

    /// Without a usable summary: one pass over the data section for the schemas,
    /// channels and per-channel tallies.
    fn scan_for_topics(&self) -> Result<(Schemas, Channels, HashMap<u16, Tally>), BagError> {
        let mut schemas = HashMap::new();
        let mut channels = HashMap::new();
        let mut tallies: HashMap<u16, Tally> = HashMap::new();
        self.scan(|item| match item {
            Scanned::Schema(id, name) => {
                schemas.insert(id, name);
            }
            Scanned::Channel(id, channel) => {
                channels.insert(id, channel);
            }
            Scanned::Message {
                channel, log_time, ..
            } => {
                tallies.entry(channel).or_default().add(log_time);
            }
        })?;
        if let Some(channel) = tallies.keys().find(|c| !channels.contains_key(c)) {
            return Err(BagError::malformed(
                &self.path,
                0,
                format!("messages on channel {channel}, which no Channel record defines"),
            ));
        }
        Ok((schemas, channels, tallies))
    }

    /// Walks the data section in file order, chunks decompressed one at a time.
    fn scan(&self, mut visit: impl FnMut(Scanned)) -> Result<(), BagError> {
        let magic = mcap::MAGIC.len();
        let mut records = Cursor::new(&self.map[magic..], magic as u64);
        while !records.is_empty() {
            let record_at = records.offset();
            let (opcode, mut body) = next_record(&mut records).map_err(|e| self.bad(e))?;
            match opcode {
                op::DATA_END | op::FOOTER => break,
                op::CHUNK => {
                    let chunk = self.chunk_bytes(record_at)?;
                    let bytes = chunk.bytes(&self.map);
                    let mut inner = Cursor::new(bytes, record_at);
                    while !inner.is_empty() {
                        let offset = inner.pos() as u64;
                        let (opcode, mut body) = next_record(&mut inner).map_err(|e| {
                            BagError::malformed(
                                &self.path,
                                record_at,
                                format!(
                                    "in the chunk at this byte, record at {offset}: {}",
                                    e.reason
                                ),
                            )
                        })?;
                        scan_record(opcode, &mut body, record_at, offset, &mut visit).map_err(
                            |e| {
                                BagError::malformed(
                                    &self.path,
                                    record_at,
                                    format!(
                                        "in the chunk at this byte, record at {offset}: {}",
                                        e.reason
                                    ),
                                )
                            },
                        )?;
                    }
                }
                _ => scan_record(opcode, &mut body, record_at, NOT_IN_CHUNK, &mut visit)
                    .map_err(|e| self.bad(e))?,
            }
        }
        Ok(())
    }

    /// The topics of the bag's channels ([`chunked::topics_of`]), typed by their
    /// schemas and message encodings.
    fn build_topics(
        &mut self,
        schemas: &Schemas,
        channels: &Channels,
        tallies: &HashMap<u16, Tally>,
    ) {
        let described = channels
            .iter()
            .map(|(&id, (name, schema_id, encoding))| {
                let schema = schemas.get(schema_id).cloned().unwrap_or_default();
                let (msg_type, encoding) = match encoding.as_str() {
                    "cdr" => (schema, Encoding::Cdr),
                    "ros1" => (schema, Encoding::Ros1),
                    // Listed, but typed so that no PointCloud2 / Imu check accepts it:
                    // kfmap decodes CDR and ROS 1 messages only.
                    other => (format!("{schema} [{other} encoded]"), Encoding::Cdr),
                };
                let topic = Topic {
                    name: name.clone(),
                    msg_type,
                    encoding,
                    count: 0,
                    first_ns: None,
                    last_ns: None,
                };
                (id, topic)
            })
            .collect();
        (self.topics, self.channels_of) = chunked::topics_of(described, tallies);
    }
}

/// What a scan of the data section meets.
enum Scanned {
    Schema(u16, String),
    Channel(u16, (String, u16, String)),
    Message {
        channel: u16,
        log_time: u64,
        /// `MessageRef::locator` and `offset` of it.
        locator: u64,
        offset: u64,
    },
}

fn scan_record(
    opcode: u8,
    body: &mut Cursor<'_>,
    locator: u64,
    offset: u64,
    visit: &mut impl FnMut(Scanned),
) -> Result<(), RawError> {
    match opcode {
        op::SCHEMA => {
            let id = body.u16("schema id")?;
            visit(Scanned::Schema(id, body.string("schema name")?));
        }
        op::CHANNEL => {
            let (id, channel) = parse_channel(body)?;
            visit(Scanned::Channel(id, channel));
        }
        op::MESSAGE => {
            let channel = body.u16("message channel")?;
            let _sequence = body.u32("message sequence")?;
            let log_time = body.u64("message log time")?;
            visit(Scanned::Message {
                channel,
                log_time,
                locator,
                offset,
            });
        }
        _ => {}
    }
    Ok(())
}

/// The next record of `c`: its opcode and a cursor over its body.
fn next_record<'a>(c: &mut Cursor<'a>) -> Result<(u8, Cursor<'a>), RawError> {
    let at = c.offset();
    let opcode = c.u8("record opcode")?;
    let len = c.u64("record length")?;
    let body_at = c.offset();
    let body = c.bytes(len, "record").map_err(|e| {
        RawError::new(
            at,
            format!(
                "a record (opcode {opcode:#04x}) of {len} bytes: {}",
                e.reason
            ),
        )
    })?;
    Ok((opcode, Cursor::new(body, body_at)))
}

fn parse_channel(body: &mut Cursor<'_>) -> Result<(u16, (String, u16, String)), RawError> {
    let id = body.u16("channel id")?;
    let schema_id = body.u16("channel schema id")?;
    let topic = body.string("channel topic")?;
    let encoding = body.string("channel message encoding")?;
    Ok((id, (topic, schema_id, encoding)))
}

fn parse_chunk_index(body: &mut Cursor<'_>) -> Result<ChunkIndex, RawError> {
    let _start = body.u64("chunk index start time")?;
    let _end = body.u64("chunk index end time")?;
    let chunk_start = body.u64("chunk index chunk offset")?;
    let _chunk_length = body.u64("chunk index chunk length")?;
    let map_len = body.u32("chunk index message index offsets")?;
    let mut entries = Cursor::new(
        body.bytes(u64::from(map_len), "message index offsets")?,
        body.offset(),
    );
    let mut message_indexes = BTreeMap::new();
    while !entries.is_empty() {
        let channel = entries.u16("message index channel")?;
        let offset = entries.u64("message index offset")?;
        message_indexes.insert(channel, offset);
    }
    Ok(ChunkIndex {
        chunk_start,
        message_indexes,
    })
}

impl Chunked for McapBag {
    fn chunked_topics(&self) -> &[Topic] {
        &self.topics
    }

    fn message_refs(&self, topic: &Topic) -> Result<Vec<MessageRef>, BagError> {
        let Some(ids) = self.channels_of.get(&topic.name) else {
            return Ok(Vec::new());
        };
        let mut refs = Vec::with_capacity(topic.count.min(1 << 24) as usize);
        match &self.chunks {
            Some(chunks) => {
                for chunk in chunks {
                    for id in ids {
                        if let Some(&at) = chunk.message_indexes.get(id) {
                            self.message_index(*id, at, |log_time_ns, offset| {
                                refs.push(MessageRef {
                                    log_time_ns,
                                    locator: chunk.chunk_start,
                                    offset,
                                })
                            })
                            .map_err(|e| self.bad(e))?;
                        }
                    }
                }
            }
            None => self.scan(|item| {
                if let Scanned::Message {
                    channel,
                    log_time,
                    locator,
                    offset,
                } = item
                    && ids.contains(&channel)
                {
                    refs.push(MessageRef {
                        log_time_ns: log_time,
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
        let (opcode, mut body) = next_record(&mut c).map_err(bad)?;
        if opcode != op::CHUNK {
            return Err(BagError::malformed(
                &self.path,
                at,
                "an index points at no Chunk record",
            ));
        }
        let _start_time = body.u64("chunk start time").map_err(bad)?;
        let _end_time = body.u64("chunk end time").map_err(bad)?;
        let uncompressed_size = body.u64("chunk uncompressed size").map_err(bad)?;
        let crc = body.u32("chunk CRC").map_err(bad)?;
        let compression = body.string("chunk compression").map_err(bad)?;
        let compressed_size = body.u64("chunk compressed size").map_err(bad)?;
        let data_at = body.offset();
        let data = body.bytes(compressed_size, "chunk records").map_err(bad)?;
        if uncompressed_size > MAX_CHUNK_BYTES {
            return Err(BagError::malformed(
                &self.path,
                at,
                format!(
                    "a chunk of {uncompressed_size} bytes uncompressed; kfmap reads chunks up to {MAX_CHUNK_BYTES}"
                ),
            ));
        }
        let chunk = match compression.as_str() {
            "" => {
                if uncompressed_size != compressed_size {
                    return Err(BagError::malformed(
                        &self.path,
                        at,
                        "an uncompressed chunk whose two sizes differ",
                    ));
                }
                // `data` lies inside the map at `data_at`.
                let start = data_at as usize;
                ChunkBytes::Mapped(start..start + data.len())
            }
            "zstd" | "lz4" => {
                let decode = if compression == "zstd" {
                    zstd_exact
                } else {
                    lz4_exact
                };
                let decoded = decode(data, uncompressed_size, 64 << 20).map_err(|reason| {
                    BagError::malformed(&self.path, at, format!("{compression} chunk: {reason}"))
                })?;
                ChunkBytes::Owned(decoded.into())
            }
            _ => {
                return Err(BagError::Codec {
                    path: self.path.clone(),
                    offset: at,
                    codec: compression,
                    supported: SUPPORTED,
                });
            }
        };
        if crc != 0 {
            let computed = crc32fast::hash(chunk.bytes(&self.map));
            if computed != crc {
                return Err(BagError::malformed(
                    &self.path,
                    at,
                    format!(
                        "chunk CRC mismatch (stored {crc:08x}, computed {computed:08x}): corrupt"
                    ),
                ));
            }
        }
        Ok(chunk)
    }

    /// The message at `at`, from `chunk` (the records of the chunk `at.locator`) or,
    /// outside chunks, from the map.
    fn message(&self, at: &MessageRef, chunk: Option<&ChunkBytes>) -> Result<Message, BagError> {
        let mut c = chunked::message_cursor(&self.map, &self.path, at, chunk)?;
        let parsed = (|| {
            let (opcode, mut body) = next_record(&mut c)?;
            if opcode != op::MESSAGE {
                return Err(RawError::new(
                    at.offset,
                    "an index that points at no Message record",
                ));
            }
            let _channel = body.u16("message channel")?;
            let _sequence = body.u32("message sequence")?;
            let log_time_ns = body.u64("message log time")?;
            let _publish_time = body.u64("message publish time")?;
            let rest = body.remaining() as u64;
            let data = body.bytes(rest, "message data")?.to_vec();
            Ok(Message { log_time_ns, data })
        })();
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
