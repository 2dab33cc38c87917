#!/usr/bin/env python3
"""Writes the compressed test vectors of kfmap-bag's chunk decoders (bag/src/raw.rs):
frames made by the reference C libraries, so the pure-Rust decoders are checked against
what other writers produce without building the C encoders into every test build.

    python3 -m venv /tmp/codec-venv && /tmp/codec-venv/bin/pip install zstandard lz4
    /tmp/codec-venv/bin/python tools/bag_codec_vectors.py

writes bag/tests/data/codec/two_frames.zst (two zstd frames, levels 3 and 19, of the
two parts below, one after the other, as a multi-frame MCAP chunk holds them: the first
with its content size and a checksum, the second with neither) and
whole.lz4 (one lz4 frame of both parts). The committed files came from zstandard 0.25.0
(libzstd 1.5.7) and lz4 4.4.5 (liblz4 1.9.4).
"""
from pathlib import Path

import lz4.frame
import zstandard

# The same bytes the Rust test builds: 70 000 of (i * 7 mod 251), then 5 000 of (i mod 13).
FIRST = bytes((i * 7 % 251) for i in range(70_000))
SECOND = bytes((i % 13) for i in range(5_000))

out = Path(__file__).resolve().parent.parent / "bag" / "tests" / "data" / "codec"
out.mkdir(parents=True, exist_ok=True)
# The first frame states its size and carries a checksum; the second, like a streaming
# encoder's, does neither: the decoder must take both headers.
frames = (zstandard.ZstdCompressor(level=3, write_checksum=True).compress(FIRST)
          + zstandard.ZstdCompressor(level=19, write_content_size=False).compress(SECOND))
(out / "two_frames.zst").write_bytes(frames)
(out / "whole.lz4").write_bytes(lz4.frame.compress(FIRST + SECOND))
print(f"{out}: two_frames.zst {len(frames)} bytes, whole.lz4 {(out / 'whole.lz4').stat().st_size} bytes")
