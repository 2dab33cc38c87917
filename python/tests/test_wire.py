"""The ctypes layouts against the Rust layout test, and the pose conversions."""

from __future__ import annotations

import ctypes
import keyword
import os
import re
from pathlib import Path

import numpy as np
import pytest

import kfmap
from kfmap import geometry, wire

RUST_SIDE = Path(__file__).resolve().parents[2] / "protocol" / "src"


def require_rust_side(name: str) -> Path:
    """``protocol/src/NAME`` of the repository these tests run from. Outside the
    repository the test is skipped; under ``CI=true`` (``.ci/run``) nothing may skip, so a
    missing or moved file fails it, as kfmap-testdata's policy does for the Rust tests."""
    path = RUST_SIDE / name
    if not path.exists():
        if os.environ.get("CI") == "true":
            pytest.fail(f"{path} not found; CI=true requires it")
        pytest.skip(f"not in the kfmap repository ({path} not found)")
    return path


def rust_layouts() -> dict[str, tuple[int, dict[str, int]]]:
    """``layout!(Type, size, field = offset, ...)`` of ``header_layouts_are_the_documented_ones``."""
    text = require_rust_side("tests.rs").read_text()
    found = {}
    for name, size, body in re.findall(r"layout!\(\s*(\w+),\s*(\d+),(.*?)\);", text, re.S):
        found[name] = (int(size), {f: int(o) for f, o in re.findall(r"(\w+)\s*=\s*(\d+)", body)})
    return found


def test_layouts_match_the_rust_layout_test() -> None:
    layouts = rust_layouts()
    types = {"RequestHeader": wire.RequestHeader, "ResponseHeader": wire.ResponseHeader,
             "WirePairing": wire.WirePairing, "WireSessionGravity": wire.WireSessionGravity,
             "WireCovOptions": wire.WireCovOptions, "WireRanking": wire.WireRanking,
             "WireTrack": wire.WireTrack}
    # A place travels in a pairing's slot: a numpy record, not a ctypes structure.
    place_size, place_offsets = layouts.pop("WirePlace")
    assert wire.PLACE_DTYPE.itemsize == place_size
    assert {f: wire.PLACE_DTYPE.fields[f][1] for f in wire.PLACE_DTYPE.names} == place_offsets
    assert set(layouts) == set(types)
    for name, (size, rust_offsets) in layouts.items():
        t = types[name]
        # A Rust field named as a Python keyword (``lambda``) is ``lambda_`` in ctypes.
        offsets = {f"{f}_" if keyword.iskeyword(f) else f: o for f, o in rust_offsets.items()}
        assert ctypes.sizeof(t) == size, name
        assert [f for f, _ in t._fields_] == list(offsets), f"{name}: fields or their order"
        for field, offset in offsets.items():
            assert getattr(t, field).offset == offset, f"{name}.{field}"
    for field in wire.PAIRING_DTYPE.names:
        assert wire.PAIRING_DTYPE.fields[field][1] == getattr(wire.WirePairing, field).offset


def test_type_names_and_protocol_match_the_rust_side() -> None:
    wire_rs = require_rust_side("wire.rs").read_text()
    names = re.findall(r'#\[type_name\("([^"]+)"\)\]\s*pub struct (\w+)', wire_rs)
    declared = {struct: name for name, struct in names}
    for t in (wire.RequestHeader, wire.ResponseHeader, wire.WirePairing, wire.WireCovOptions,
              wire.WireRanking):
        assert t.type_name() == declared[t.__name__]
    mod_rs = require_rust_side("lib.rs").read_text()
    assert f"PROTOCOL_VERSION: u32 = {wire.PROTOCOL_VERSION};" in mod_rs
    for status in wire.StatusCode:
        assert f"{status.wire_name} = {int(status)}," in mod_rs
    labels = {v.lower(): label for v, label in re.findall(r'RequestKind::(\w+) => "([\w-]+)"', mod_rs)}
    codes = {v.lower(): int(c) for v, c in re.findall(r"^\s*(\w+) = (\d+),", mod_rs, re.M)}
    for kind in wire.RequestKind:
        key = kind.name.replace("_", "").lower()
        assert (labels[key], codes[key]) == (kind.label, int(kind))


def test_pose_round_trip() -> None:
    rng = np.random.default_rng(7)
    for _ in range(200):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = -q if q[3] < 0 else q
        t = np.eye(4)
        t[:3, :3] = geometry.quat_to_matrix(q)
        t[:3, 3] = rng.normal(size=3)
        values = kfmap.pose_to_wire(t)
        np.testing.assert_allclose(values[3:], q, atol=1e-12)
        np.testing.assert_allclose(kfmap.pose_from_wire(values), t, atol=1e-12)
    assert kfmap.pose_to_wire(None) == [0, 0, 0, 0, 0, 0, 1]


def test_roll_pitch_quat_is_ry_times_rx() -> None:
    roll, pitch = 0.1, -0.2
    rx = np.array([[1, 0, 0], [0, np.cos(roll), -np.sin(roll)], [0, np.sin(roll), np.cos(roll)]])
    ry = np.array([[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0], [-np.sin(pitch), 0, np.cos(pitch)]])
    np.testing.assert_allclose(geometry.quat_to_matrix(geometry.roll_pitch_quat(roll, pitch)),
                               ry @ rx, atol=1e-12)
