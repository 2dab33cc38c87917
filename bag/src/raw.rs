//! Bounds-checked reading of little-endian records, and bounded decompression, shared
//! by the MCAP and ROS 1 readers.
//!
//! Every read is checked against the bytes at hand, so a truncated or corrupt file gives
//! an error naming the byte offset instead of a panic; and nothing is allocated from a
//! length field before that length is known to fit in the file (or, for decompressed
//! data, before the bytes have actually been produced).

use std::io::Read;

/// What went wrong at which byte (file offset); the reader adds the path.
#[derive(Debug)]
pub(crate) struct RawError {
    /// Bytes from the start of the file.
    pub offset: u64,
    /// What is wrong.
    pub reason: String,
}

impl RawError {
    pub(crate) fn new(offset: u64, reason: impl Into<String>) -> Self {
        RawError {
            offset,
            reason: reason.into(),
        }
    }
}

/// A cursor over a byte slice that knows where the slice lies in the file, so each error
/// names a file offset.
#[derive(Debug, Clone)]
pub(crate) struct Cursor<'a> {
    buf: &'a [u8],
    pos: usize,
    /// File offset of `buf[0]` (or, for a decompressed chunk, of the chunk record).
    base: u64,
}

impl<'a> Cursor<'a> {
    /// A cursor at the start of `buf`, which lies at file offset `base`.
    pub(crate) fn new(buf: &'a [u8], base: u64) -> Self {
        Cursor { buf, pos: 0, base }
    }

    /// The file offset of the next byte.
    pub(crate) fn offset(&self) -> u64 {
        self.base.saturating_add(self.pos as u64)
    }

    /// The position inside the slice.
    pub(crate) fn pos(&self) -> usize {
        self.pos
    }

    /// Bytes left.
    pub(crate) fn remaining(&self) -> usize {
        self.buf.len() - self.pos
    }

    /// True when every byte has been read.
    pub(crate) fn is_empty(&self) -> bool {
        self.remaining() == 0
    }

    /// An error at the current position.
    pub(crate) fn error(&self, reason: impl Into<String>) -> RawError {
        RawError::new(self.offset(), reason)
    }

    /// The next `n` bytes; an error naming `what` if fewer remain.
    pub(crate) fn bytes(&mut self, n: u64, what: &str) -> Result<&'a [u8], RawError> {
        if n > self.remaining() as u64 {
            return Err(self.error(format!(
                "{what}: {n} bytes wanted, {} left (truncated or corrupt)",
                self.remaining()
            )));
        }
        let start = self.pos;
        // `n` fits in usize: it is at most `remaining()`.
        self.pos += n as usize;
        Ok(&self.buf[start..self.pos])
    }

    fn array<const N: usize>(&mut self, what: &str) -> Result<[u8; N], RawError> {
        let bytes = self.bytes(N as u64, what)?;
        let mut out = [0u8; N];
        out.copy_from_slice(bytes);
        Ok(out)
    }

    pub(crate) fn u8(&mut self, what: &str) -> Result<u8, RawError> {
        Ok(self.array::<1>(what)?[0])
    }

    pub(crate) fn u16(&mut self, what: &str) -> Result<u16, RawError> {
        Ok(u16::from_le_bytes(self.array(what)?))
    }

    pub(crate) fn u32(&mut self, what: &str) -> Result<u32, RawError> {
        Ok(u32::from_le_bytes(self.array(what)?))
    }

    pub(crate) fn u64(&mut self, what: &str) -> Result<u64, RawError> {
        Ok(u64::from_le_bytes(self.array(what)?))
    }

    /// A `u32`-length-prefixed UTF-8 string.
    pub(crate) fn string(&mut self, what: &str) -> Result<String, RawError> {
        let len = self.u32(what)?;
        let at = self.offset();
        let bytes = self.bytes(u64::from(len), what)?;
        String::from_utf8(bytes.to_vec())
            .map_err(|_| RawError::new(at, format!("{what}: not UTF-8")))
    }
}

/// Reads everything `decoder` produces, which must be exactly `expected` bytes. The
/// buffer grows with the bytes produced (never reserved from `expected` alone beyond
/// `reserve_cap`), so a corrupt size field cannot make it allocate more than the stream
/// really holds; a stream that produces more than `expected` is cut there and refused.
pub(crate) fn decompress_exact(
    decoder: impl Read,
    expected: u64,
    reserve_cap: u64,
) -> Result<Vec<u8>, String> {
    let mut out = Vec::with_capacity(expected.min(reserve_cap) as usize);
    // One byte past `expected` tells "too long" from "exactly right".
    let mut limited = decoder.take(expected.saturating_add(1));
    limited
        .read_to_end(&mut out)
        .map_err(|e| format!("decompression failed: {e}"))?;
    exactly(out, expected)
}

/// A zstd chunk (MCAP) decoded to exactly `expected` bytes, as [`decompress_exact`]. The
/// format allows several frames back to back; each is decoded in turn (pure Rust
/// `ruzstd`: no C library to build, see docs/DESIGN.md#build-profiles).
pub(crate) fn zstd_exact(data: &[u8], expected: u64, reserve_cap: u64) -> Result<Vec<u8>, String> {
    let mut out = Vec::with_capacity(expected.min(reserve_cap) as usize);
    let mut rest = data;
    // `rest` advances past each frame as it is read; one byte past `expected` is enough
    // to tell "too long".
    while !rest.is_empty() && out.len() as u64 <= expected {
        let frame = ruzstd::decoding::StreamingDecoder::new(&mut rest)
            .map_err(|e| format!("not a zstd frame: {e}"))?;
        // A hostile size field may be u64::MAX: saturate, never overflow.
        let budget = expected.saturating_add(1) - out.len() as u64;
        frame
            .take(budget)
            .read_to_end(&mut out)
            .map_err(|e| format!("decompression failed: {e}"))?;
    }
    exactly(out, expected)
}

/// An lz4 frame stream (MCAP and ROS 1 chunks) decoded to exactly `expected` bytes, as
/// [`decompress_exact`] (pure Rust `lz4_flex`, its safe and checked decoder).
pub(crate) fn lz4_exact(data: &[u8], expected: u64, reserve_cap: u64) -> Result<Vec<u8>, String> {
    decompress_exact(
        lz4_flex::frame::FrameDecoder::new(data),
        expected,
        reserve_cap,
    )
}

/// `out` when it holds exactly `expected` bytes, else what is wrong.
fn exactly(out: Vec<u8>, expected: u64) -> Result<Vec<u8>, String> {
    if out.len() as u64 != expected {
        return Err(format!(
            "decompressed to {}{} bytes, the header says {expected}",
            out.len(),
            if out.len() as u64 > expected { "+" } else { "" }
        ));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_past_the_end_are_errors_naming_the_offset() {
        let mut c = Cursor::new(&[1, 0, 2, 0, 0, 0], 100);
        assert_eq!(c.u16("a").unwrap(), 1);
        assert_eq!(c.u32("b").unwrap(), 2);
        let err = c.u8("c").unwrap_err();
        assert_eq!(err.offset, 106);
        let mut c = Cursor::new(&[255, 255, 255, 255, b'x'], 0);
        assert!(c.string("s").is_err());
    }

    #[test]
    fn decompression_must_match_the_declared_size() {
        let data = vec![7u8; 100];
        assert_eq!(decompress_exact(&data[..], 100, 10).unwrap(), data);
        assert!(decompress_exact(&data[..], 99, 10).is_err());
        assert!(decompress_exact(&data[..], 101, 10).is_err());
        // A size field of 2^60 allocates nothing up front beyond the cap.
        assert!(decompress_exact(&data[..], 1 << 60, 10).is_err());
    }

    /// The pure-Rust decoders against frames the reference C libraries wrote (libzstd
    /// and liblz4 through their Python bindings, `tools/bag_codec_vectors.py`): every
    /// frame of a multi-frame zstd chunk (one stating its size with a checksum, one
    /// stating neither, as streaming encoders write), an lz4 frame, and truncated or
    /// mis-sized input refused.
    #[test]
    fn zstd_and_lz4_chunks_decode_as_the_c_libraries_wrote_them() {
        let first: Vec<u8> = (0..70_000u32).map(|i| (i * 7 % 251) as u8).collect();
        let second: Vec<u8> = (0..5_000u32).map(|i| (i % 13) as u8).collect();
        let whole = [first, second].concat();
        let n = whole.len() as u64;

        let frames = include_bytes!("../tests/data/codec/two_frames.zst");
        assert_eq!(zstd_exact(frames, n, 1 << 20).unwrap(), whole);
        assert!(zstd_exact(frames, n - 1, 1 << 20).is_err());
        assert!(zstd_exact(frames, n + 1, 1 << 20).is_err());
        assert!(zstd_exact(&frames[..frames.len() - 3], n, 1 << 20).is_err());
        assert!(zstd_exact(&whole[..100], 100, 1 << 20).is_err());
        assert!(zstd_exact(frames, u64::MAX, 1 << 20).is_err());

        let lz4_frame = include_bytes!("../tests/data/codec/whole.lz4");
        assert_eq!(lz4_exact(lz4_frame, n, 1 << 20).unwrap(), whole);
        assert!(lz4_exact(lz4_frame, n - 1, 1 << 20).is_err());
        assert!(lz4_exact(&lz4_frame[..lz4_frame.len() / 2], n, 1 << 20).is_err());
        assert!(lz4_exact(&whole[..100], 100, 1 << 20).is_err());
        assert!(lz4_exact(lz4_frame, u64::MAX, 1 << 20).is_err());
    }
}
