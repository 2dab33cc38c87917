//! rosbag2 SQLite databases (`.db3`, the rosbag2 default before Iron).
//!
//! Two tables matter: `topics(id, name, type, serialization_format, ...)` and
//! `messages(id, topic_id, timestamp, data)`. The database is opened read-only and, when
//! its path can be written as a plain URI, `immutable` (no locks, no journal: bags are
//! finished files; a `-wal` file left beside it by a killed recorder is ignored).
//!
//! Topics, counts and first / last timestamps come from one `GROUP BY` at open. A
//! message's [`MessageRef`] is its row id; [`Container::messages`] lists the row ids of
//! the topic in `(timestamp, id)` order and fetches one row at a time, so memory holds
//! one message (plus 24 bytes a message for the list).

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard};

use rusqlite::{Connection, OpenFlags, OptionalExtension};

use crate::{BagError, Container, Encoding, Message, MessageRef, Topic};

/// `topics` id, name, type, serialization format; message count, first, last timestamp.
type TopicRow = (i64, String, String, String, i64, Option<i64>, Option<i64>);

/// An open rosbag2 SQLite database.
pub(crate) struct SqliteBag {
    path: PathBuf,
    /// `Connection` is `Send` but not `Sync`: one statement at a time.
    conn: Mutex<Connection>,
    topics: Vec<Topic>,
    /// Row ids in `topics` of each topic name (normally one).
    topic_ids: HashMap<String, Vec<i64>>,
}

impl SqliteBag {
    /// Opens the database at `path` read-only and lists its topics.
    pub(crate) fn open(path: &Path) -> Result<Self, BagError> {
        check_not_truncated(path)?;
        let flags = OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX;
        let conn = match immutable_uri(path) {
            Some(uri) => Connection::open_with_flags(uri, flags | OpenFlags::SQLITE_OPEN_URI),
            None => Connection::open_with_flags(path, flags),
        }
        .map_err(|e| sql_error(path, "opening", e))?;
        let mut bag = SqliteBag {
            path: path.to_path_buf(),
            conn: Mutex::new(conn),
            topics: Vec::new(),
            topic_ids: HashMap::new(),
        };
        bag.list_topics()?;
        Ok(bag)
    }

    fn conn(&self) -> MutexGuard<'_, Connection> {
        // A panic elsewhere while holding the lock leaves the connection usable.
        self.conn.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn list_topics(&mut self) -> Result<(), BagError> {
        let rows: Vec<TopicRow> = {
            let conn = self.conn();
            let mut statement = conn
                .prepare(
                    "SELECT t.id, t.name, t.type, t.serialization_format, \
                            COUNT(m.id), MIN(m.timestamp), MAX(m.timestamp) \
                     FROM topics t LEFT JOIN messages m ON m.topic_id = t.id \
                     GROUP BY t.id ORDER BY t.id",
                )
                .map_err(|e| self.error("reading the topics and messages tables", e))?;
            statement
                .query_map([], |r| {
                    Ok((
                        r.get(0)?,
                        r.get(1)?,
                        r.get(2)?,
                        r.get(3)?,
                        r.get(4)?,
                        r.get(5)?,
                        r.get(6)?,
                    ))
                })
                .and_then(|rows| rows.collect())
                .map_err(|e| self.error("listing the topics", e))?
        };
        let mut topics: BTreeMap<String, Topic> = BTreeMap::new();
        for (id, name, msg_type, format, count, first, last) in rows {
            let (first, last) = (self.time(first, &name)?, self.time(last, &name)?);
            self.topic_ids.entry(name.clone()).or_default().push(id);
            let topic = topics.entry(name.clone()).or_insert_with(|| {
                let (msg_type, encoding) = match format.as_str() {
                    "cdr" => (msg_type, Encoding::Cdr),
                    "ros1" => (msg_type, Encoding::Ros1),
                    // Listed, but typed so that no PointCloud2 / Imu check accepts it.
                    other => (format!("{msg_type} [{other} encoded]"), Encoding::Cdr),
                };
                Topic {
                    name,
                    msg_type,
                    encoding,
                    count: 0,
                    first_ns: None,
                    last_ns: None,
                }
            });
            topic.count += count.max(0) as u64;
            topic.first_ns = match (topic.first_ns, first) {
                (Some(a), Some(b)) => Some(a.min(b)),
                (a, b) => a.or(b),
            };
            topic.last_ns = match (topic.last_ns, last) {
                (Some(a), Some(b)) => Some(a.max(b)),
                (a, b) => a.or(b),
            };
        }
        self.topics = topics.into_values().collect();
        Ok(())
    }

    /// A timestamp column value as nanoseconds; negative ones are refused.
    fn time(&self, value: Option<i64>, topic: &str) -> Result<Option<u64>, BagError> {
        value
            .map(|v| {
                u64::try_from(v).map_err(|_| {
                    BagError::malformed(
                        &self.path,
                        0,
                        format!("a message of {topic} with a negative timestamp ({v})"),
                    )
                })
            })
            .transpose()
    }

    fn error(&self, doing: &str, e: rusqlite::Error) -> BagError {
        sql_error(&self.path, doing, e)
    }
}

/// A SQLite error as a [`BagError::Malformed`] (SQLite does not say where).
fn sql_error(path: &Path, doing: &str, e: rusqlite::Error) -> BagError {
    BagError::malformed(
        path,
        0,
        format!("{doing}: {e} (not a rosbag2 database, or a corrupt one)"),
    )
}

/// Refuses a file shorter than its header says (a truncated copy): SQLite would read
/// the missing pages as zeros and may not notice.
fn check_not_truncated(path: &Path) -> Result<(), BagError> {
    use std::io::Read;
    let mut header = [0u8; 100];
    let mut file = std::fs::File::open(path).map_err(|e| BagError::os(path, e))?;
    let len = file.metadata().map_err(|e| BagError::os(path, e))?.len();
    if file.read_exact(&mut header).is_err() {
        return Err(BagError::malformed(
            path,
            len,
            "an SQLite file shorter than its 100-byte header: truncated",
        ));
    }
    let page_size = match u16::from_be_bytes([header[16], header[17]]) {
        1 => 65536,
        n => u64::from(n),
    };
    let pages = u64::from(u32::from_be_bytes([
        header[28], header[29], header[30], header[31],
    ]));
    // The page count is valid only when the two change counters agree.
    let counted = header[92..96] == header[24..28];
    let expected = page_size.saturating_mul(pages);
    if counted && pages > 0 && len < expected {
        return Err(BagError::malformed(
            path,
            len,
            format!("the SQLite header says {expected} bytes, the file has {len}: truncated"),
        ));
    }
    Ok(())
}

/// `file:<path>?immutable=1` when the path needs no escaping in a URI.
fn immutable_uri(path: &Path) -> Option<String> {
    let text = path.to_str()?;
    let plain = text
        .chars()
        .all(|c| c.is_ascii_alphanumeric() || "/._-+~".contains(c));
    plain.then(|| format!("file:{text}?immutable=1"))
}

impl Container for SqliteBag {
    fn topics(&self) -> &[Topic] {
        &self.topics
    }

    fn messages<'a>(
        &'a self,
        topic: &Topic,
    ) -> Result<Box<dyn Iterator<Item = Result<Message, BagError>> + Send + 'a>, BagError> {
        let refs = self.index(topic)?;
        let mut failed = false;
        Ok(Box::new(refs.into_iter().map_while(move |at| {
            if failed {
                return None;
            }
            let result = self.read(&at);
            failed = result.is_err();
            Some(result)
        })))
    }

    fn index(&self, topic: &Topic) -> Result<Vec<MessageRef>, BagError> {
        let Some(ids) = self.topic_ids.get(&topic.name) else {
            return Ok(Vec::new());
        };
        // The ids are integers read from the database: safe to spell into the query.
        let list = ids.iter().map(i64::to_string).collect::<Vec<_>>().join(",");
        let sql = format!(
            "SELECT id, timestamp FROM messages WHERE topic_id IN ({list}) ORDER BY timestamp, id"
        );
        let rows: Vec<(i64, i64)> = {
            let conn = self.conn();
            let mut statement = conn.prepare(&sql).map_err(|e| self.error("indexing", e))?;
            statement
                .query_map([], |r| Ok((r.get(0)?, r.get(1)?)))
                .and_then(|rows| rows.collect())
                .map_err(|e| self.error(&format!("indexing {}", topic.name), e))?
        };
        rows.into_iter()
            .map(|(id, timestamp)| {
                Ok(MessageRef {
                    log_time_ns: self.time(Some(timestamp), &topic.name)?.unwrap_or(0),
                    // Row ids of rosbag2 are positive (INTEGER PRIMARY KEY from 1).
                    locator: id as u64,
                    offset: 0,
                })
            })
            .collect()
    }

    fn read(&self, at: &MessageRef) -> Result<Message, BagError> {
        let row: Option<(i64, Vec<u8>)> = {
            let conn = self.conn();
            let mut statement = conn
                .prepare_cached("SELECT timestamp, data FROM messages WHERE id = ?1")
                .map_err(|e| self.error("reading a message", e))?;
            statement
                .query_row([at.locator as i64], |r| Ok((r.get(0)?, r.get(1)?)))
                .optional()
                .map_err(|e| self.error(&format!("reading message row {}", at.locator), e))?
        };
        let Some((timestamp, data)) = row else {
            return Err(BagError::malformed(
                &self.path,
                0,
                format!(
                    "no message of row id {} (the database changed?)",
                    at.locator
                ),
            ));
        };
        let log_time_ns = self
            .time(Some(timestamp), &format!("row {}", at.locator))?
            .unwrap_or(0);
        Ok(Message { log_time_ns, data })
    }
}
