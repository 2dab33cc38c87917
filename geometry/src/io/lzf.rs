//! LZF (Marc Lehmann's format), the compression of PCD `binary_compressed` data.
//!
//! A stream is a sequence of chunks. Control byte `c < 32`: a literal run of `c + 1`
//! bytes follows. Otherwise `len = c >> 5` (7 means one more length byte is added) and
//! a back-reference copies `len + 2` bytes from `((c & 31) << 8 | next byte) + 1` back.

/// Decompresses `input` into exactly `expected_len` bytes; the error says what is
/// wrong and at which input offset.
pub fn decompress(input: &[u8], expected_len: usize) -> Result<Vec<u8>, String> {
    // LZF expands at most ~90x: bound the allocation by the input, not the header.
    let mut out = Vec::with_capacity(expected_len.min(input.len().saturating_mul(90)));
    let mut i = 0usize;
    while i < input.len() {
        let ctrl = input[i] as usize;
        i += 1;
        if ctrl < 32 {
            let run = ctrl + 1;
            let end = i + run;
            if end > input.len() {
                return Err(format!(
                    "literal run of {run} bytes at offset {} passes the end of the data",
                    i - 1
                ));
            }
            out.extend_from_slice(&input[i..end]);
            i = end;
        } else {
            let mut len = ctrl >> 5;
            if len == 7 {
                let extra = *input
                    .get(i)
                    .ok_or_else(|| format!("missing length byte at offset {i}"))?;
                len += extra as usize;
                i += 1;
            }
            let low = *input
                .get(i)
                .ok_or_else(|| format!("missing offset byte at offset {i}"))?;
            i += 1;
            let back = (((ctrl & 31) << 8) | low as usize) + 1;
            if back > out.len() {
                return Err(format!(
                    "back-reference {back} bytes behind output position {} at offset {}",
                    out.len(),
                    i - 2
                ));
            }
            let start = out.len() - back;
            // Byte by byte: the source may overlap the bytes being written.
            for k in 0..len + 2 {
                out.push(out[start + k]);
            }
        }
        if out.len() > expected_len {
            return Err(format!(
                "data decompresses to more than the {expected_len} bytes announced"
            ));
        }
    }
    if out.len() != expected_len {
        return Err(format!(
            "data decompresses to {} bytes, {expected_len} announced",
            out.len()
        ));
    }
    Ok(out)
}

/// Compresses `input` with a greedy 3-byte hash match finder (what PCL's writer does,
/// in spirit); any conforming decoder reads the output.
pub fn compress(input: &[u8]) -> Vec<u8> {
    const MAX_BACK: usize = 8192;
    const MAX_MATCH: usize = 264; // 7 + 255 + 2
    const HASH_BITS: u32 = 14;
    let mut out = Vec::with_capacity(input.len() + input.len() / 32 + 2);
    let mut table = vec![usize::MAX; 1 << HASH_BITS];
    let mut literals: Vec<u8> = Vec::with_capacity(32);
    let flush = |out: &mut Vec<u8>, literals: &mut Vec<u8>| {
        for chunk in literals.chunks(32) {
            out.push((chunk.len() - 1) as u8);
            out.extend_from_slice(chunk);
        }
        literals.clear();
    };
    let mut i = 0;
    while i < input.len() {
        if i + 2 < input.len() {
            let h = (u32::from_le_bytes([input[i], input[i + 1], input[i + 2], 0])
                .wrapping_mul(2_654_435_761)
                >> (32 - HASH_BITS)) as usize;
            let candidate = table[h];
            table[h] = i;
            if candidate != usize::MAX
                && i - candidate <= MAX_BACK
                && input[candidate..candidate + 3] == input[i..i + 3]
            {
                let max_len = MAX_MATCH.min(input.len() - i);
                let mut len = 3;
                while len < max_len && input[candidate + len] == input[i + len] {
                    len += 1;
                }
                flush(&mut out, &mut literals);
                let back = i - candidate - 1;
                let code_len = len - 2;
                if code_len < 7 {
                    out.push(((code_len << 5) | (back >> 8)) as u8);
                } else {
                    out.push(((7 << 5) | (back >> 8)) as u8);
                    out.push((code_len - 7) as u8);
                }
                out.push((back & 0xff) as u8);
                i += len;
                continue;
            }
        }
        literals.push(input[i]);
        i += 1;
    }
    flush(&mut out, &mut literals);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decodes_a_hand_made_stream() {
        // "abc" as a literal run, then a 6-byte copy from 3 back (overlapping): "abcabcabc".
        let stream = [2, b'a', b'b', b'c', (4 << 5), 2];
        assert_eq!(decompress(&stream, 9).unwrap(), b"abcabcabc");
        // Long form: length 7 + 3 extra -> 12 bytes copied from 1 back.
        let stream = [0, b'z', (7 << 5), 3, 0];
        assert_eq!(decompress(&stream, 13).unwrap(), vec![b'z'; 13]);
    }

    #[test]
    fn rejects_corrupt_streams() {
        assert!(
            decompress(&[5, b'a'], 6)
                .unwrap_err()
                .contains("passes the end")
        );
        assert!(
            decompress(&[0, b'a', (1 << 5), 9], 4)
                .unwrap_err()
                .contains("back-reference")
        );
        assert!(
            decompress(&[1, b'a', b'b'], 5)
                .unwrap_err()
                .contains("announced")
        );
    }

    #[test]
    fn round_trips_repetitive_and_random_data() {
        let mut data: Vec<u8> = (0..50_000u32)
            .flat_map(|i| ((i / 7) as f32).to_le_bytes())
            .collect();
        let mut x = 12345u32;
        data.extend((0..5000).map(|_| {
            x = x.wrapping_mul(1_103_515_245).wrapping_add(12345);
            (x >> 16) as u8
        }));
        let packed = compress(&data);
        assert!(packed.len() < data.len());
        assert_eq!(decompress(&packed, data.len()).unwrap(), data);
        assert_eq!(decompress(&compress(&[]), 0).unwrap(), Vec::<u8>::new());
    }
}
