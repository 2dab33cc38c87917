//! The fixed 4096-byte header of a `.kfmap` file. Its numeric fields are little-endian
//! at fixed offsets in every format version, so any reader can say what a file is.

use xxhash_rust::xxh3::xxh3_64;

use super::ArchiveError;

/// File magic: the `\r\n` catches files mangled by text-mode transfers.
pub const MAGIC: [u8; 8] = *b"KFMAP\x00\r\n";
/// Format version this build writes and reads (3: the index records `T_map_input`;
/// 4: keyframes may hold per-point weights; 5: the place grid of relocalization; 6:
/// KD-tree leaves in blocks of lanes; 7: the place grid sparse, blocks in a hash table).
pub const FORMAT_VERSION: u32 = 7;
/// Header size; the payload starts here (page aligned, so 128-byte aligned in a map).
pub const HEADER_LEN: usize = 4096;
/// Keyframe segments start at multiples of this from the payload start (cache-line
/// aligned; rkyv needs the archive's own alignment, at most 16 here).
pub const SEGMENT_ALIGN: u64 = 128;
/// Endianness code of little-endian archives (rkyv's `little_endian`).
pub const LITTLE_ENDIAN: u8 = 1;
/// Endianness code of big-endian archives.
pub const BIG_ENDIAN: u8 = 2;
/// Width in bytes of rkyv's relative pointers in this build's archives.
pub const POINTER_WIDTH: u8 = 4;

const FIXED_LEN: usize = 80;
const CHECKSUM_AT: usize = 72;

/// The decoded header.
#[derive(Debug, Clone, PartialEq)]
pub struct Header {
    /// Format version.
    pub format_version: u32,
    /// [`LITTLE_ENDIAN`] or [`BIG_ENDIAN`].
    pub endianness: u8,
    /// rkyv relative pointer width, bytes.
    pub pointer_width: u8,
    /// Bytes after the header.
    pub payload_len: u64,
    /// xxh3-64 of the payload.
    pub payload_checksum: u64,
    /// Offset of the index archive from the payload start.
    pub index_offset: u64,
    /// Length of the index archive.
    pub index_len: u64,
    /// xxh3-64 of the index archive.
    pub index_checksum: u64,
    /// The map's creation options, TOML.
    pub options_toml: String,
    /// The program that wrote the file.
    pub creator: String,
}

impl Header {
    /// A header for this build's archives.
    pub fn new(options_toml: String) -> Self {
        Self {
            format_version: FORMAT_VERSION,
            endianness: LITTLE_ENDIAN,
            pointer_width: POINTER_WIDTH,
            payload_len: 0,
            payload_checksum: 0,
            index_offset: 0,
            index_len: 0,
            index_checksum: 0,
            options_toml,
            creator: format!("kfmap {}", env!("CARGO_PKG_VERSION")),
        }
    }

    /// The 4096 header bytes, or an error when the options do not fit.
    pub fn encode(&self) -> Result<Vec<u8>, ArchiveError> {
        let text_len = self.options_toml.len() + self.creator.len();
        if FIXED_LEN + text_len > HEADER_LEN {
            return Err(ArchiveError::OptionsTooLarge(text_len));
        }
        let mut b = vec![0u8; HEADER_LEN];
        b[0..8].copy_from_slice(&MAGIC);
        b[8..12].copy_from_slice(&self.format_version.to_le_bytes());
        b[12] = self.endianness;
        b[13] = self.pointer_width;
        b[16..24].copy_from_slice(&(HEADER_LEN as u64).to_le_bytes());
        b[24..32].copy_from_slice(&self.payload_len.to_le_bytes());
        b[32..40].copy_from_slice(&self.payload_checksum.to_le_bytes());
        b[40..48].copy_from_slice(&self.index_offset.to_le_bytes());
        b[48..56].copy_from_slice(&self.index_len.to_le_bytes());
        b[56..64].copy_from_slice(&self.index_checksum.to_le_bytes());
        b[64..68].copy_from_slice(&(self.options_toml.len() as u32).to_le_bytes());
        b[68..72].copy_from_slice(&(self.creator.len() as u32).to_le_bytes());
        let creator_at = FIXED_LEN + self.options_toml.len();
        b[FIXED_LEN..creator_at].copy_from_slice(self.options_toml.as_bytes());
        b[creator_at..creator_at + self.creator.len()].copy_from_slice(self.creator.as_bytes());
        let checksum = xxh3_64(&b);
        b[CHECKSUM_AT..CHECKSUM_AT + 8].copy_from_slice(&checksum.to_le_bytes());
        Ok(b)
    }

    /// Decodes and checks a header: magic, version, endianness, pointer width, then
    /// its checksum, each with its own error.
    pub fn decode(bytes: &[u8]) -> Result<Self, ArchiveError> {
        if bytes.len() < MAGIC.len() || bytes[..MAGIC.len()] != MAGIC {
            return Err(ArchiveError::BadMagic);
        }
        if bytes.len() < HEADER_LEN {
            return Err(ArchiveError::Truncated {
                expected: HEADER_LEN as u64,
                actual: bytes.len() as u64,
            });
        }
        let b = &bytes[..HEADER_LEN];
        let u32_at = |at: usize| u32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes"));
        let u64_at = |at: usize| u64::from_le_bytes(b[at..at + 8].try_into().expect("8 bytes"));
        let format_version = u32_at(8);
        if format_version > FORMAT_VERSION {
            return Err(ArchiveError::NewerVersion {
                found: format_version,
                supported: FORMAT_VERSION,
            });
        }
        if format_version != FORMAT_VERSION {
            return Err(ArchiveError::OldVersion {
                found: format_version,
                supported: FORMAT_VERSION,
            });
        }
        let endianness = b[12];
        if endianness != LITTLE_ENDIAN {
            return Err(ArchiveError::WrongEndianness {
                found: endianness_name(endianness),
            });
        }
        let pointer_width = b[13];
        if pointer_width != POINTER_WIDTH {
            return Err(ArchiveError::PointerWidth {
                found: pointer_width,
                expected: POINTER_WIDTH,
            });
        }
        let mut zeroed = b.to_vec();
        zeroed[CHECKSUM_AT..CHECKSUM_AT + 8].fill(0);
        if xxh3_64(&zeroed) != u64_at(CHECKSUM_AT) || u64_at(16) != HEADER_LEN as u64 {
            return Err(ArchiveError::HeaderCorrupt);
        }
        let options_len = u32_at(64) as usize;
        let creator_len = u32_at(68) as usize;
        let creator_at = FIXED_LEN + options_len;
        let text = |range: std::ops::Range<usize>| {
            b.get(range)
                .and_then(|t| std::str::from_utf8(t).ok())
                .map(str::to_owned)
                .ok_or(ArchiveError::HeaderCorrupt)
        };
        Ok(Self {
            format_version,
            endianness,
            pointer_width,
            payload_len: u64_at(24),
            payload_checksum: u64_at(32),
            index_offset: u64_at(40),
            index_len: u64_at(48),
            index_checksum: u64_at(56),
            options_toml: text(FIXED_LEN..creator_at)?,
            creator: text(creator_at..creator_at.saturating_add(creator_len))?,
        })
    }
}

fn endianness_name(code: u8) -> &'static str {
    match code {
        LITTLE_ENDIAN => "little-endian",
        BIG_ENDIAN => "big-endian",
        _ => "unknown-endian",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_and_names_each_mismatch() {
        let mut h = Header::new("a = 1\n".into());
        h.payload_len = 12345;
        h.index_checksum = 7;
        let bytes = h.encode().unwrap();
        assert_eq!(bytes.len(), HEADER_LEN);
        assert_eq!(Header::decode(&bytes).unwrap(), h);

        let mut newer = bytes.clone();
        newer[8..12].copy_from_slice(&(FORMAT_VERSION + 1).to_le_bytes());
        assert!(matches!(
            Header::decode(&newer),
            Err(ArchiveError::NewerVersion { found, .. }) if found == FORMAT_VERSION + 1
        ));
        let mut big = bytes.clone();
        big[12] = BIG_ENDIAN;
        assert!(matches!(
            Header::decode(&big),
            Err(ArchiveError::WrongEndianness {
                found: "big-endian"
            })
        ));
        let mut wide = bytes.clone();
        wide[13] = 8;
        assert!(matches!(
            Header::decode(&wide),
            Err(ArchiveError::PointerWidth {
                found: 8,
                expected: 4
            })
        ));
        let mut flipped = bytes.clone();
        flipped[30] ^= 0x10; // payload length
        assert!(matches!(
            Header::decode(&flipped),
            Err(ArchiveError::HeaderCorrupt)
        ));
        assert!(matches!(
            Header::decode(b"PCD v0.7"),
            Err(ArchiveError::BadMagic)
        ));
        assert!(matches!(
            Header::decode(&bytes[..100]),
            Err(ArchiveError::Truncated { .. })
        ));
    }

    #[test]
    fn refuses_options_that_do_not_fit() {
        let h = Header::new("x".repeat(HEADER_LEN));
        assert!(matches!(h.encode(), Err(ArchiveError::OptionsTooLarge(_))));
    }
}
