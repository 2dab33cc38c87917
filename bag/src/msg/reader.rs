//! The primitive readers under both message decoders: one cursor over a message's bytes
//! that knows the two serializations kfmap reads.
//!
//! - **ROS 2 (CDR)**: a 4-byte encapsulation header (`00 01` little-endian, `00 00`
//!   big-endian), then every value aligned to its own size, counted from the end of that
//!   header. Strings are a `u32` length that includes the trailing NUL, then the bytes;
//!   sequences are a `u32` count, then the elements.
//! - **ROS 1**: little-endian, no alignment, strings and variable arrays a `u32` length
//!   (no NUL), fixed arrays with no prefix.
//!
//! Every read checks the bytes left first, so a truncated or hostile message gives a
//! [`DecodeError`] naming the field, never a panic, and a length prefix is checked
//! against the bytes left before anything is allocated for it.

use super::{DecodeError, Stamp};
use crate::Encoding;

/// A cursor over one serialized message.
#[derive(Debug, Clone)]
pub(crate) struct Reader<'a> {
    /// The message body: for CDR, the bytes after the encapsulation header (alignment
    /// counts from here).
    body: &'a [u8],
    /// Next byte to read in `body`.
    pos: usize,
    /// CDR big-endian encapsulation.
    big_endian: bool,
    /// CDR aligns values to their size; ROS 1 packs them.
    aligned: bool,
}

impl<'a> Reader<'a> {
    /// A reader of `bytes` serialized as `encoding`; for CDR, checks the encapsulation
    /// header and refuses every representation but plain CDR.
    pub(crate) fn new(bytes: &'a [u8], encoding: Encoding) -> Result<Self, DecodeError> {
        match encoding {
            Encoding::Ros1 => Ok(Self {
                body: bytes,
                pos: 0,
                big_endian: false,
                aligned: false,
            }),
            Encoding::Cdr => {
                let Some((header, body)) = bytes.split_first_chunk::<4>() else {
                    return Err(DecodeError::NoEncapsulation(bytes.len()));
                };
                // The representation identifier is big-endian; the options bytes after it
                // only count padding at the end, which the decoders ignore.
                let big_endian = match u16::from_be_bytes([header[0], header[1]]) {
                    0x0000 => true,
                    0x0001 => false,
                    id => return Err(unsupported_representation(id)),
                };
                Ok(Self {
                    body,
                    pos: 0,
                    big_endian,
                    aligned: true,
                })
            }
        }
    }

    /// Bytes not read yet.
    pub(crate) fn remaining(&self) -> usize {
        self.body.len() - self.pos
    }

    /// Skips the padding before a value of `size` bytes (CDR only).
    fn align(&mut self, size: usize, what: &str) -> Result<(), DecodeError> {
        if self.aligned {
            let pad = (size - self.pos % size) % size;
            self.take(pad, what)?;
        }
        Ok(())
    }

    /// The next `n` bytes, borrowed.
    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], DecodeError> {
        if n > self.remaining() {
            return Err(DecodeError::Truncated {
                what: what.to_string(),
                needed: n,
                at: self.pos,
                left: self.remaining(),
            });
        }
        let bytes = &self.body[self.pos..self.pos + n];
        self.pos += n;
        Ok(bytes)
    }

    /// The next `N` bytes of a value, aligned and in the message's byte order turned
    /// little-endian.
    fn value<const N: usize>(&mut self, what: &str) -> Result<[u8; N], DecodeError> {
        self.align(N, what)?;
        let mut raw = [0u8; N];
        raw.copy_from_slice(self.take(N, what)?);
        if self.big_endian {
            raw.reverse();
        }
        Ok(raw)
    }

    /// A `uint8`.
    pub(crate) fn u8(&mut self, what: &str) -> Result<u8, DecodeError> {
        Ok(self.take(1, what)?[0])
    }

    /// A `bool`: one byte, 0 or 1 (anything else means the layout is off).
    pub(crate) fn bool(&mut self, what: &str) -> Result<bool, DecodeError> {
        match self.u8(what)? {
            0 => Ok(false),
            1 => Ok(true),
            b => Err(DecodeError::BadValue {
                what: what.to_string(),
                value: b.to_string(),
                expected: "a bool (0 or 1)",
            }),
        }
    }

    /// A `uint32`.
    pub(crate) fn u32(&mut self, what: &str) -> Result<u32, DecodeError> {
        self.value(what).map(u32::from_le_bytes)
    }

    /// An `int32`.
    pub(crate) fn i32(&mut self, what: &str) -> Result<i32, DecodeError> {
        self.value(what).map(i32::from_le_bytes)
    }

    /// A `float64`.
    pub(crate) fn f64(&mut self, what: &str) -> Result<f64, DecodeError> {
        self.value(what).map(f64::from_le_bytes)
    }

    /// `N` consecutive `float64` (a fixed array, or a struct of doubles).
    pub(crate) fn f64s<const N: usize>(&mut self, what: &str) -> Result<[f64; N], DecodeError> {
        let mut out = [0.0; N];
        for v in &mut out {
            *v = self.f64(what)?;
        }
        Ok(out)
    }

    /// A `string`. Invalid UTF-8 is replaced rather than refused: names are only
    /// compared with ASCII field names and reported.
    pub(crate) fn string(&mut self, what: &str) -> Result<String, DecodeError> {
        let len = self.u32(what)? as usize;
        let mut bytes = self.take(len, what)?;
        if self.aligned {
            // CDR counts the terminating NUL (an empty string may still be written as 0).
            bytes = bytes.strip_suffix(&[0]).unwrap_or(bytes);
        }
        Ok(String::from_utf8_lossy(bytes).into_owned())
    }

    /// A `uint8[]`, borrowed from the message.
    pub(crate) fn byte_sequence(&mut self, what: &str) -> Result<&'a [u8], DecodeError> {
        let len = self.u32(what)? as usize;
        self.take(len, what)
    }

    /// The element count of a sequence whose elements take at least `min_element_bytes`
    /// each: checked against the bytes left, so a caller may allocate for it.
    pub(crate) fn sequence_len(
        &mut self,
        what: &str,
        min_element_bytes: usize,
    ) -> Result<usize, DecodeError> {
        let count = self.u32(what)? as usize;
        if count.saturating_mul(min_element_bytes) > self.remaining() {
            return Err(DecodeError::BadCount {
                what: what.to_string(),
                count,
                left: self.remaining(),
            });
        }
        Ok(count)
    }

    /// A `std_msgs/Header`: its stamp and frame (ROS 1 adds a `seq`, skipped).
    pub(crate) fn header(&mut self) -> Result<(Stamp, String), DecodeError> {
        let stamp = if self.aligned {
            let sec = self.i32("header.stamp.sec")?;
            let nanosec = self.u32("header.stamp.nanosec")?;
            Stamp {
                sec: sec.into(),
                nanosec,
            }
        } else {
            self.u32("header.seq")?;
            let sec = self.u32("header.stamp.secs")?;
            let nanosec = self.u32("header.stamp.nsecs")?;
            Stamp {
                sec: sec.into(),
                nanosec,
            }
        };
        let frame_id = self.string("header.frame_id")?;
        Ok((stamp, frame_id))
    }
}

/// The error for a CDR representation other than plain CDR, naming it.
fn unsupported_representation(id: u16) -> DecodeError {
    let name = match id {
        0x0002 => "PL_CDR_BE (parameter list)",
        0x0003 => "PL_CDR_LE (parameter list)",
        0x0006 => "CDR2_BE (XCDR2)",
        0x0007 => "CDR2_LE (XCDR2)",
        0x0008 => "D_CDR2_BE (XCDR2 delimited)",
        0x0009 => "D_CDR2_LE (XCDR2 delimited)",
        0x000a => "PL_CDR2_BE (XCDR2 parameter list)",
        0x000b => "PL_CDR2_LE (XCDR2 parameter list)",
        _ => "unknown",
    };
    DecodeError::Representation { id, name }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cdr_aligns_from_the_end_of_the_encapsulation_header() {
        // u8 at 0, pad 1..4, u32 at 4, pad 8..8, f64 at 8 (body offsets).
        let mut bytes = vec![0x00, 0x01, 0x00, 0x00, 0xAB, 0xEE, 0xEE, 0xEE];
        bytes.extend(7u32.to_le_bytes());
        bytes.extend(2.5f64.to_le_bytes());
        let mut r = Reader::new(&bytes, Encoding::Cdr).unwrap();
        assert_eq!(r.u8("a").unwrap(), 0xAB);
        assert_eq!(r.u32("b").unwrap(), 7);
        assert_eq!(r.f64("c").unwrap(), 2.5);
        assert_eq!(r.remaining(), 0);
    }

    #[test]
    fn cdr_pads_a_double_after_an_odd_string_to_eight() {
        // "ab\0": u32 len at 0, bytes 4..7, pad to 8, f64 at 8.
        let mut bytes = vec![0x00, 0x01, 0, 0];
        bytes.extend(3u32.to_le_bytes());
        bytes.extend(b"ab\0");
        bytes.push(0xEE);
        bytes.extend((-1.0f64).to_le_bytes());
        let mut r = Reader::new(&bytes, Encoding::Cdr).unwrap();
        assert_eq!(r.string("s").unwrap(), "ab");
        assert_eq!(r.f64("d").unwrap(), -1.0);
    }

    #[test]
    fn cdr_big_endian_reverses_values() {
        let mut bytes = vec![0x00, 0x00, 0, 0];
        bytes.extend(0x0102_0304u32.to_be_bytes());
        bytes.extend((-5i32).to_be_bytes());
        bytes.extend(1.25f64.to_be_bytes());
        let mut r = Reader::new(&bytes, Encoding::Cdr).unwrap();
        assert_eq!(r.u32("a").unwrap(), 0x0102_0304);
        assert_eq!(r.i32("b").unwrap(), -5);
        assert_eq!(r.f64("c").unwrap(), 1.25);
    }

    #[test]
    fn ros1_packs_values_without_padding_or_nul() {
        let mut bytes = vec![0xAB];
        bytes.extend(2u32.to_le_bytes());
        bytes.extend(b"hi");
        bytes.extend(9.0f64.to_le_bytes());
        let mut r = Reader::new(&bytes, Encoding::Ros1).unwrap();
        assert_eq!(r.u8("a").unwrap(), 0xAB);
        assert_eq!(r.string("s").unwrap(), "hi");
        assert_eq!(r.f64("d").unwrap(), 9.0);
    }

    #[test]
    fn other_representations_are_refused_by_name() {
        for (id, name) in [(0x03u8, "PL_CDR_LE"), (0x07, "CDR2_LE"), (0x06, "CDR2_BE")] {
            let err = Reader::new(&[0, id, 0, 0], Encoding::Cdr).unwrap_err();
            assert!(
                matches!(err, DecodeError::Representation { id: got, .. } if got == u16::from(id)),
                "{err:?}"
            );
            assert!(err.to_string().contains(name), "{err}");
        }
        let err = Reader::new(&[0, 1], Encoding::Cdr).unwrap_err();
        assert_eq!(err, DecodeError::NoEncapsulation(2));
        assert!(err.to_string().contains("encapsulation header"), "{err}");
    }

    #[test]
    fn truncation_and_hostile_lengths_are_errors() {
        let mut r = Reader::new(&[0, 1, 0, 0, 1, 2], Encoding::Cdr).unwrap();
        let err = r.u32("height").unwrap_err();
        assert_eq!(
            err,
            DecodeError::Truncated {
                what: "height".into(),
                needed: 4,
                at: 0,
                left: 2
            }
        );
        assert!(err.to_string().contains("needs 4 bytes"), "{err}");

        let mut bytes = vec![0, 1, 0, 0];
        bytes.extend(u32::MAX.to_le_bytes());
        bytes.extend([0; 8]);
        let mut r = Reader::new(&bytes, Encoding::Cdr).unwrap();
        assert!(r.clone().byte_sequence("data").is_err());
        assert!(r.clone().string("frame").is_err());
        let err = r.sequence_len("fields", 13).unwrap_err();
        assert!(
            matches!(
                err,
                DecodeError::BadCount {
                    count: 4294967295,
                    left: 8,
                    ..
                }
            ),
            "{err:?}"
        );
    }

    #[test]
    fn a_bool_other_than_zero_or_one_is_an_error() {
        let mut r = Reader::new(&[2], Encoding::Ros1).unwrap();
        let err = r.bool("is_dense").unwrap_err();
        assert!(matches!(err, DecodeError::BadValue { .. }), "{err:?}");
        assert!(err.to_string().contains("not a bool"), "{err}");
    }
}
