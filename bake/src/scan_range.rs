//! `--scans A..B`: a half-open range of a dataset's scan indices, counted in the sorted
//! scan list [`crate::bake::find_scans`] gives. `kfmap bake` takes it; any subcommand
//! replaying a dataset can take it the same way (clap parses it through [`FromStr`]).
//!
//! ```
//! use kfmap_bake::scan_range::ScanRange;
//! let range: ScanRange = "100..200".parse().unwrap();
//! assert_eq!(range.within(177).unwrap_err().to_string(),
//!            "--scans 100..200: the dataset has 177 scans (indices 0..177)");
//! assert_eq!("100..".parse::<ScanRange>().unwrap().within(177).unwrap(), 100..177);
//! ```

use std::fmt;
use std::ops::Range;
use std::str::FromStr;

/// Scans `start..end` of a dataset, as typed: `A..B`, `A..` (to the last scan) or `..B`
/// (from the first). Parsing guarantees `start < end` when both are given;
/// [`ScanRange::within`] checks the range against a dataset's scan count.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ScanRange {
    /// First scan index taken.
    pub start: usize,
    /// First scan index not taken; `None`: up to the last scan.
    pub end: Option<usize>,
}

/// Why a scan range was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ScanRangeError {
    /// The text is not `A..B`.
    #[error(
        "'{text}' is not a scan range: {reason} (write A..B for scans A to B-1, e.g. 100..200; A.. or ..B leave one end open)"
    )]
    Parse {
        /// The text as given.
        text: String,
        /// What is wrong with it.
        reason: String,
    },
    /// The range reaches beyond the dataset or holds no scan.
    #[error("--scans {range}: the dataset has {count} scans (indices 0..{count})")]
    OutOfRange {
        /// The range asked for.
        range: ScanRange,
        /// Scans in the dataset.
        count: usize,
    },
}

impl ScanRange {
    /// Every scan.
    pub const ALL: ScanRange = ScanRange {
        start: 0,
        end: None,
    };

    /// The indices this range takes of a dataset of `count` scans: `A < B <= count`, or
    /// an error naming the range and the count.
    pub fn within(&self, count: usize) -> Result<Range<usize>, ScanRangeError> {
        let end = self.end.unwrap_or(count);
        if self.start < end && end <= count {
            Ok(self.start..end)
        } else {
            Err(ScanRangeError::OutOfRange {
                range: *self,
                count,
            })
        }
    }
}

impl fmt::Display for ScanRange {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.end {
            Some(end) => write!(f, "{}..{end}", self.start),
            None => write!(f, "{}..", self.start),
        }
    }
}

impl FromStr for ScanRange {
    type Err = ScanRangeError;

    fn from_str(text: &str) -> Result<Self, ScanRangeError> {
        let refuse = |reason: String| ScanRangeError::Parse {
            text: text.to_string(),
            reason,
        };
        let (a, b) = text
            .trim()
            .split_once("..")
            .ok_or_else(|| refuse("no '..' between the two indices".into()))?;
        let index = |word: &str| -> Result<Option<usize>, ScanRangeError> {
            let word = word.trim();
            if word.is_empty() {
                return Ok(None);
            }
            word.parse()
                .map(Some)
                .map_err(|_| refuse(format!("'{word}' is not a scan index (0, 1, 2, ...)")))
        };
        if b.starts_with('=') {
            return Err(refuse("A..=B is not supported; B is excluded".into()));
        }
        let (start, end) = (index(a)?, index(b)?);
        let start = start.unwrap_or(0);
        if let Some(end) = end.filter(|&end| end <= start) {
            return Err(refuse(format!(
                "{start}..{end} holds no scan; A must be below B"
            )));
        }
        Ok(ScanRange { start, end })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<ScanRange, ScanRangeError> {
        text.parse()
    }

    #[test]
    fn parses_closed_and_open_ranges() {
        assert_eq!(
            parse("5..12").unwrap(),
            ScanRange {
                start: 5,
                end: Some(12)
            }
        );
        assert_eq!(parse(" 5..").unwrap().within(30).unwrap(), 5..30);
        assert_eq!(parse("..7").unwrap().within(30).unwrap(), 0..7);
        assert_eq!(parse("..").unwrap(), ScanRange::ALL);
        assert_eq!(parse("0..30").unwrap().within(30).unwrap(), 0..30);
    }

    #[test]
    fn refuses_malformed_and_empty_ranges_by_name() {
        for (text, reason) in [
            ("5", "no '..'"),
            ("5-10", "no '..'"),
            ("a..10", "'a' is not a scan index"),
            ("-1..10", "'-1' is not a scan index"),
            ("5..x", "'x' is not a scan index"),
            ("5..=10", "A..=B is not supported"),
            ("10..10", "holds no scan"),
            ("12..3", "holds no scan"),
            ("1..2..3", "'2..3' is not a scan index"),
        ] {
            let message = parse(text).unwrap_err().to_string();
            assert!(
                message.contains(reason) && message.contains(text),
                "{text}: {message}"
            );
        }
    }

    #[test]
    fn ranges_beyond_the_dataset_name_the_count() {
        let error = parse("5..300").unwrap().within(177).unwrap_err();
        assert_eq!(
            error.to_string(),
            "--scans 5..300: the dataset has 177 scans (indices 0..177)"
        );
        assert!(parse("177..").unwrap().within(177).is_err());
        assert!(parse("176..").unwrap().within(177).is_ok());
        assert!(parse("..178").unwrap().within(177).is_err());
    }
}
