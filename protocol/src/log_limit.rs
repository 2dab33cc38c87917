//! iceoryx2's own log lines, through a rate limit into `tracing`: a peer that keeps
//! losing requests or dying must not flood the log (iceoryx2 writes a line, with a
//! dump of the port's state, per event). One line per kind of event per interval,
//! with the count of those held back.

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use iceoryx2_log::{Log, LogLevel};

/// Longest stretch of an iceoryx2 message kept in a log line.
const MESSAGE_CHARS: usize = 200;

/// Lets through the first event of each kind, then one per `interval` with the count
/// held back since the last one let through.
#[derive(Debug)]
pub struct RateLimit {
    interval: Duration,
    kinds: HashMap<String, (Instant, u64)>,
}

impl RateLimit {
    /// At most one line per kind per `interval`.
    pub fn new(interval: Duration) -> Self {
        Self {
            interval,
            kinds: HashMap::new(),
        }
    }

    /// `Some(held back since the last line)` when an event of `kind` at `now` is to be
    /// logged; `None` when it is only counted.
    pub fn admit(&mut self, kind: &str, now: Instant) -> Option<u64> {
        match self.kinds.get_mut(kind) {
            Some((last, held)) if now.duration_since(*last) < self.interval => {
                *held += 1;
                None
            }
            Some((last, held)) => {
                let shown = *held;
                (*last, *held) = (now, 0);
                Some(shown)
            }
            None => {
                self.kinds.insert(kind.to_string(), (now, 0));
                Some(0)
            }
        }
    }
}

/// The kind of an iceoryx2 event: its level, the type that logged it (the origin up
/// to its state dump) and the message's words without numbers.
pub fn event_kind(level: LogLevel, origin: &str, message: &str) -> String {
    let source: String = origin
        .chars()
        .take_while(|c| c.is_alphanumeric() || "_:<>".contains(*c))
        .collect();
    let words: String = message
        .chars()
        .filter(|c| !c.is_ascii_digit())
        .take(80)
        .collect();
    format!("{level:?} {source} {words}")
}

/// Logs `line` at `level` unless an event of `kind` was logged within the last 10 s;
/// the next line let through says how many were held back. One limit for iceoryx2's
/// events and the server's own.
fn log_limited(level: LogLevel, kind: &str, line: &str) {
    static LIMIT: std::sync::OnceLock<Mutex<RateLimit>> = std::sync::OnceLock::new();
    let limit = LIMIT.get_or_init(|| Mutex::new(RateLimit::new(Duration::from_secs(10))));
    let held = limit
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .admit(kind, Instant::now());
    let line = match held {
        None => return,
        Some(0) => line.to_string(),
        Some(n) => format!("{line} ({n} more like it held back)"),
    };
    match level {
        LogLevel::Trace | LogLevel::Debug => tracing::debug!("{line}"),
        LogLevel::Info => tracing::info!("{line}"),
        LogLevel::Warn => tracing::warn!("{line}"),
        LogLevel::Error | LogLevel::Fatal => tracing::error!("{line}"),
    }
}

/// A warning for an event a client can repeat at will (answers it never reads,
/// requests /dev/shm cannot back), rate-limited per `kind` as [`log_limited`].
pub fn warn_limited(kind: &str, message: &str) {
    log_limited(LogLevel::Warn, kind, message);
}

/// iceoryx2's logger: its events, by [`event_kind`], through [`log_limited`].
struct Limited;

impl Log for Limited {
    fn log(&self, level: LogLevel, origin: std::fmt::Arguments, message: std::fmt::Arguments) {
        let message = message.to_string();
        let kind = event_kind(level, &origin.to_string(), &message);
        let source = kind.split(' ').nth(1).unwrap_or("");
        let text: String = message.chars().take(MESSAGE_CHARS).collect();
        log_limited(level, &kind, &format!("iceoryx2 {source}: {text}"));
    }
}

/// Routes iceoryx2's log through [`RateLimit`] (one line per kind per 10 s) into
/// `tracing`, at warnings and above unless `IOX2_LOG_LEVEL` says otherwise. Call once,
/// before any iceoryx2 use; false when iceoryx2 already had a logger.
pub fn install() -> bool {
    static LOG: Limited = Limited;
    let installed = iceoryx2_log::set_logger(&LOG);
    iceoryx2_log::set_log_level_from_env_or(LogLevel::Warn);
    installed
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_line_per_kind_per_interval_with_the_count_held_back() {
        let mut limit = RateLimit::new(Duration::from_secs(10));
        let t0 = Instant::now();
        let at = |s: f64| t0 + Duration::from_secs_f64(s);
        // 20 lost requests within 2 s: one line, the rest counted.
        let shown: Vec<_> = (0..20)
            .filter_map(|i| limit.admit("lost", at(i as f64 * 0.1)))
            .collect();
        assert_eq!(shown, vec![0]);
        // Another kind is not held back by the first.
        assert_eq!(limit.admit("dead node", at(1.0)), Some(0));
        // After the interval: one line, carrying the 19 held back.
        assert_eq!(limit.admit("lost", at(10.5)), Some(19));
        assert_eq!(limit.admit("lost", at(11.0)), None);
    }

    #[test]
    fn kinds_ignore_numbers_and_state_dumps() {
        let a = event_kind(
            LogLevel::Warn,
            "Server { port_id: 42, state: [huge] }",
            "lost request 17 of client 9",
        );
        let b = event_kind(
            LogLevel::Warn,
            "Server { port_id: 43, state: [other] }",
            "lost request 18 of client 12",
        );
        assert_eq!(a, b);
        assert!(a.starts_with("Warn Server"), "{a}");
        let c = event_kind(LogLevel::Warn, "Client { }", "lost request 1");
        assert_ne!(a, c);
    }
}
