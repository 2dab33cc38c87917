#!/usr/bin/env python3
"""Writes serialized sensor_msgs/PointCloud2 and sensor_msgs/Imu messages for
bag/tests/messages.rs, with the values a correct decoder must find.

Usage: messages.py OUT_DIR

The messages are serialized by `rosbags` (an independent implementation of ROS 2 CDR
and ROS 1 serialization); the expected values are computed here, in exact arithmetic
for times. OUT_DIR receives one `.cdr` / `.ros1` file per message and `manifest.json`:
a list of entries `{"file", "type": "PointCloud2" | "Imu", "encoding": "cdr" | "ros1"}`
plus either `"expect": {...}` or `"error": "<text the error must contain>"`.

Float values that must match exactly are given as their bits (NaN-safe, and immune to
decimal rounding in JSON readers): x y z and intensity as the bits of the expected f32,
Imu values as the bits of the f64; times as float seconds after the header stamp (the
comparison allows f32 rounding).
"""

import json
import sys
from fractions import Fraction
from pathlib import Path

import numpy as np
from rosbags.typesys import Stores, get_typestore

ROS2 = get_typestore(Stores.ROS2_HUMBLE)
ROS1 = get_typestore(Stores.ROS1_NOETIC)
PC2 = "sensor_msgs/msg/PointCloud2"
IMU = "sensor_msgs/msg/Imu"

# PointField datatype codes, and the numpy type of each (byte order added later).
CODES = {"INT8": 1, "UINT8": 2, "INT16": 3, "UINT16": 4, "INT32": 5, "UINT32": 6,
         "FLOAT32": 7, "FLOAT64": 8}
NUMPY = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}

RNG = np.random.default_rng(20240611)


def f64_bits(values):
    """The bits of each f64, as Python ints (JSON readers may round decimal floats)."""
    return [int(b) for b in np.asarray(values, dtype=np.float64).view(np.uint64)]


def f32_bits(values):
    """The bits of each value rounded to f32, as Python ints."""
    return [int(b) for b in np.asarray(values, dtype=np.float64).astype(np.float32).view(np.uint32)]


class Layout:
    """A driver's point layout: (name, offset, type name) fields and the point size."""

    def __init__(self, name, fields, point_step, time=None, intensity="intensity", ring=None):
        self.name = name
        self.fields = fields
        self.point_step = point_step
        self.time = time  # (field, unit) expected from the decoder, or None
        self.intensity = intensity
        self.ring = ring

    def dtype(self, big_endian):
        order = ">" if big_endian else "<"
        return np.dtype({
            "names": [f[0] for f in self.fields],
            "formats": [order + NUMPY[CODES[f[2]]] for f in self.fields],
            "offsets": [f[1] for f in self.fields],
            "itemsize": self.point_step,
        })


# The layouts drivers publish (offsets as the drivers' point structs put them).
OUSTER = Layout(
    "ouster",
    [("x", 0, "FLOAT32"), ("y", 4, "FLOAT32"), ("z", 8, "FLOAT32"),
     ("intensity", 16, "FLOAT32"), ("t", 20, "UINT32"), ("reflectivity", 24, "UINT16"),
     ("ring", 26, "UINT16"), ("ambient", 28, "UINT16"), ("range", 32, "UINT32")],
    48, time=("t", "RelativeNanos"), ring="ring")
VELODYNE = Layout(
    "velodyne",
    [("x", 0, "FLOAT32"), ("y", 4, "FLOAT32"), ("z", 8, "FLOAT32"),
     ("intensity", 12, "FLOAT32"), ("ring", 16, "UINT16"), ("time", 18, "FLOAT32")],
    22, time=("time", "RelativeSeconds"), ring="ring")
VELODYNE_24 = Layout("velodyne24", VELODYNE.fields, 24, VELODYNE.time, ring="ring")
HESAI = Layout(
    "hesai",
    [("x", 0, "FLOAT32"), ("y", 4, "FLOAT32"), ("z", 8, "FLOAT32"),
     ("intensity", 16, "FLOAT32"), ("timestamp", 24, "FLOAT64"), ("ring", 32, "UINT16")],
    48, time=("timestamp", "AbsoluteSeconds"), ring="ring")
LIVOX2 = Layout(
    "livox2",
    [("x", 0, "FLOAT32"), ("y", 4, "FLOAT32"), ("z", 8, "FLOAT32"),
     ("intensity", 12, "FLOAT32"), ("tag", 16, "UINT8"), ("line", 17, "UINT8"),
     ("timestamp", 18, "FLOAT64")],
    26, time=("timestamp", "AbsoluteNanos"), ring="line")
LIVOX_OFFSET = Layout(
    "livox_offset",
    [("x", 0, "FLOAT32"), ("y", 4, "FLOAT32"), ("z", 8, "FLOAT32"),
     ("intensity", 12, "FLOAT32"), ("tag", 16, "UINT8"), ("line", 17, "UINT8"),
     ("offset_time", 18, "UINT32"), ("timestamp", 22, "FLOAT64")],
    30, time=("offset_time", "RelativeNanos"), ring="line")
ROBOSENSE = Layout(
    "robosense",
    [("x", 0, "FLOAT32"), ("y", 4, "FLOAT32"), ("z", 8, "FLOAT32"),
     ("intensity", 16, "FLOAT32"), ("ring", 20, "UINT16"), ("timestamp", 24, "FLOAT64")],
    32, time=("timestamp", "AbsoluteSeconds"), ring="ring")
# Coordinates in double precision, no time.
FLOAT64_XYZ = Layout(
    "float64_xyz",
    [("x", 0, "FLOAT64"), ("y", 8, "FLOAT64"), ("z", 16, "FLOAT64"),
     ("intensity", 24, "UINT8")],
    25)
# Fields listed out of offset order, and offsets not in x y z order either.
SHUFFLED = Layout(
    "shuffled",
    [("t", 8, "UINT32"), ("z", 4, "FLOAT32"), ("intensity", 0, "UINT16"),
     ("y", 16, "FLOAT32"), ("x", 12, "FLOAT32")],
    20, time=("t", "RelativeNanos"))


def fill(layout, n, stamp, invalid):
    """Random points of `layout`: a structured array (native order) plus the expected
    x y z, intensity and relative time. `invalid` marks some returns NaN or zero."""
    sec, nsec = stamp
    pts = np.zeros(n, dtype=layout.dtype(False))
    names = {f[0]: f for f in layout.fields}
    for axis in "xyz":
        pts[axis] = RNG.uniform(-80.0, 80.0, n)
    rel_ns = np.sort(RNG.integers(0, 100_000_000, n))  # a 0.1 s sweep
    nan = np.zeros(n, bool)
    zero = np.zeros(n, bool)
    if invalid:
        nan = RNG.random(n) < 0.15
        zero = (RNG.random(n) < 0.1) & ~nan
        zero[0] = True  # the first point says nothing about the time unit
    for axis in "xyz":
        pts[axis][nan] = np.nan
    for name, _, typ in layout.fields:
        if name in "xyz":
            continue
        code = CODES[typ]
        if name == layout.intensity:
            top = 255 if code == 2 else 1000
            pts[name] = RNG.integers(0, top, n) if code != 7 else RNG.uniform(0, 1000, n)
        elif name in ("ring", "line"):
            pts[name] = RNG.integers(0, 128, n)
        elif name in ("t", "offset_time"):
            pts[name] = rel_ns
        elif name == "time":
            pts[name] = (rel_ns * 1e-9).astype(np.float32)
        elif name == "timestamp" and layout.time[1] == "AbsoluteSeconds":
            pts[name] = [float(sec + Fraction(nsec + int(r), 10**9)) for r in rel_ns]
        elif name == "timestamp":
            # ns since the epoch as a double; for the offset_time layout, 1 s off, so a
            # decoder reading it instead of offset_time fails.
            extra = 10**9 if layout.time[0] == "offset_time" else 0
            pts[name] = [float(sec * 10**9 + nsec + int(r) + extra) for r in rel_ns]
        else:
            pts[name] = RNG.integers(0, 1000, n)
    # Drivers write zero returns as all-zero points, time included.
    for name, _, typ in layout.fields:
        if name in ("intensity", "timestamp", "x", "y", "z"):
            pts[name][zero] = 0

    expect = {axis: f32_bits(pts[axis]) for axis in "xyz"}
    expect["intensity"] = f32_bits(pts[layout.intensity]) if layout.intensity in names else None
    if layout.time is None:
        expect["time"] = None
    else:
        field, unit = layout.time
        values = pts[field]
        times = []
        for v in values.tolist():
            if unit == "RelativeNanos":
                t = Fraction(int(v), 10**9)
            elif unit == "RelativeSeconds":
                t = Fraction(v)
            elif unit == "AbsoluteSeconds":
                t = Fraction(v) - sec - Fraction(nsec, 10**9)
            else:
                t = (Fraction(v) - sec * 10**9 - nsec) / 10**9
            times.append(float(t))
        expect["time"] = times
    return pts, expect


def header(store, stamp, frame):
    time = store.types["builtin_interfaces/msg/Time"](sec=stamp[0], nanosec=stamp[1])
    h = store.types["std_msgs/msg/Header"]
    if store is ROS1:
        return h(seq=42, stamp=time, frame_id=frame)
    return h(stamp=time, frame_id=frame)


def point_cloud(store, stamp, frame, height, width, fields, is_bigendian, point_step,
                row_step, data, is_dense=False):
    pf = store.types["sensor_msgs/msg/PointField"]
    return store.types[PC2](
        header=header(store, stamp, frame), height=height, width=width,
        fields=[pf(name=n, offset=o, datatype=CODES[t] if isinstance(t, str) else t, count=c)
                for (n, o, t, c) in fields],
        is_bigendian=is_bigendian, point_step=point_step, row_step=row_step,
        data=np.frombuffer(bytes(data), dtype=np.uint8), is_dense=is_dense)


def serialize(store, msg, typename, big_endian_cdr=False):
    if store is ROS1:
        return bytes(ROS1.serialize_ros1(msg, typename))
    return bytes(ROS2.serialize_cdr(msg, typename, little_endian=not big_endian_cdr))


class Out:
    def __init__(self, root):
        self.root = root
        self.manifest = []

    def write(self, name, store, typename, msg, big_endian_cdr=False, **entry):
        ext = "ros1" if store is ROS1 else "cdr"
        file = f"{name}.{ext}"
        (self.root / file).write_bytes(serialize(store, msg, typename, big_endian_cdr))
        self.manifest.append({"file": file, "type": typename.split("/")[-1],
                              "encoding": ext, **entry})


def random_stamp():
    return (int(RNG.integers(1_600_000_000, 1_800_000_000)), int(RNG.integers(0, 10**9)))


def write_cloud(out, name, store, layout, height, width, invalid=False, big_endian=False,
                row_padding=0, big_endian_cdr=False):
    stamp = random_stamp()
    frame = f"{layout.name}_frame"
    pts, expect = fill(layout, height * width, stamp, invalid)
    packed = pts.astype(layout.dtype(big_endian)).tobytes()
    row_bytes = width * layout.point_step
    row_step = row_bytes + row_padding
    data = b"".join(packed[r * row_bytes:(r + 1) * row_bytes] + b"\xee" * row_padding
                    for r in range(height))
    fields = [(n, o, t, 1) for (n, o, t) in layout.fields]
    msg = point_cloud(store, stamp, frame, height, width, fields, big_endian,
                      layout.point_step, row_step, data, is_dense=not invalid)
    expect.update({
        "stamp": list(stamp), "frame_id": frame, "height": height, "width": width,
        "point_step": layout.point_step, "row_step": row_step, "is_bigendian": big_endian,
        "is_dense": not invalid,
        "fields": [[n, o, CODES[t], 1] for (n, o, t) in layout.fields],
        "time_field": None if layout.time is None
        else {"name": layout.time[0], "unit": layout.time[1]},
        "ring_field": layout.ring,
    })
    out.write(name, store, PC2, msg, big_endian_cdr, expect=expect)


def write_clouds(out):
    for layout in (OUSTER, VELODYNE, VELODYNE_24, HESAI, LIVOX2, LIVOX_OFFSET, ROBOSENSE):
        write_cloud(out, layout.name, ROS2, layout, 1, 24)
        for store in (ROS2, ROS1):
            write_cloud(out, f"{layout.name}_organized", store, layout, 4, 16, invalid=True)
    write_cloud(out, "velodyne_bigendian", ROS2, VELODYNE, 2, 10, invalid=True,
                big_endian=True)
    write_cloud(out, "ouster_bigendian_cdr", ROS2, OUSTER, 2, 8, big_endian=True,
                big_endian_cdr=True)
    write_cloud(out, "livox2_bigendian_ros1", ROS1, LIVOX2, 1, 12, big_endian=True)
    for store in (ROS2, ROS1):
        write_cloud(out, "float64_xyz", store, FLOAT64_XYZ, 3, 7, invalid=True)
        write_cloud(out, "shuffled", store, SHUFFLED, 2, 9)
        write_cloud(out, "ouster_row_padding", store, OUSTER, 3, 5, row_padding=16)
    write_cloud(out, "empty", ROS2, OUSTER, 1, 0)
    write_cloud(out, "seed_small", ROS2, VELODYNE, 1, 4)
    write_cloud(out, "seed_small", ROS1, LIVOX2, 1, 4)


def write_bad_clouds(out):
    """Clouds whose layout the decoder must refuse, with the error text expected."""
    xyz = [("x", 0, "FLOAT32", 1), ("y", 4, "FLOAT32", 1), ("z", 8, "FLOAT32", 1)]
    cases = [
        ("bad_no_z", xyz[:2] + [("intensity", 8, "FLOAT32", 1)], 32, 64, 128,
         "cloud has no field 'z' (fields: x y intensity)"),
        ("bad_x_uint16", [("x", 0, "UINT16", 1)] + xyz[1:], 32, 64, 128,
         "field 'x' is UINT16; x, y and z must be FLOAT32 or FLOAT64"),
        ("bad_past_point_step", xyz + [("intensity", 30, "FLOAT32", 1)], 32, 64, 128,
         "field 'intensity' at offset 30 (4 bytes) runs past point_step 32"),
        ("bad_count_past_point_step", xyz + [("rgb", 16, "UINT16", 9)], 32, 64, 128,
         "field 'rgb' at offset 16 (18 bytes) runs past point_step 32"),
        ("bad_datatype", xyz + [("intensity", 12, 9, 1)], 32, 64, 128,
         "field 'intensity' has unknown datatype 9"),
        ("bad_row_step", xyz, 32, 63, 128,
         "row_step 63 is less than width 2 x point_step 32 = 64"),
        ("bad_short_data", xyz, 32, 64, 127,
         "data holds 127 bytes, fewer than height 2 x row_step 64 = 128"),
    ]
    for store in (ROS2, ROS1):
        for name, fields, point_step, row_step, size, error in cases:
            msg = point_cloud(store, (1, 2), "f", 2, 2, fields, False, point_step, row_step,
                              bytes(size))
            out.write(name, store, PC2, msg, error=error)
        # Sizes whose products overflow 32 bits: checked in 64.
        msg = point_cloud(store, (1, 2), "f", 0xFFFFFFFF, 1, xyz, False, 12,
                          0xFFFFFFFF, bytes(64))
        out.write("bad_huge_sizes", store, PC2, msg,
                  error="fewer than height 4294967295 x row_step 4294967295")
        msg = point_cloud(store, (1, 2), "f", 1, 0xFFFFFFFF, xyz, False, 0xFFFFFFFF,
                          0xFFFFFFFF, bytes(64))
        out.write("bad_huge_row", store, PC2, msg,
                  error="row_step 4294967295 is less than width 4294967295 x point_step")


def write_imus(out):
    for i, (store, big_endian_cdr, frame) in enumerate([
        (ROS2, False, "imu_link"), (ROS2, False, "imu"), (ROS2, True, "imu_frame"),
        (ROS1, False, "imu_link"), (ROS1, False, ""),
    ]):
        stamp = random_stamp()
        values = {
            "orientation": RNG.normal(size=4).tolist(),
            "orientation_covariance": RNG.normal(size=9).tolist(),
            "angular_velocity": RNG.normal(size=3).tolist(),
            "angular_velocity_covariance": RNG.normal(size=9).tolist(),
            "linear_acceleration": (RNG.normal(size=3) * 9.81).tolist(),
            "linear_acceleration_covariance": RNG.normal(size=9).tolist(),
        }
        types = store.types
        q = types["geometry_msgs/msg/Quaternion"](*values["orientation"])
        v3 = types["geometry_msgs/msg/Vector3"]
        msg = types[IMU](
            header=header(store, stamp, frame),
            orientation=q,
            orientation_covariance=np.array(values["orientation_covariance"]),
            angular_velocity=v3(*values["angular_velocity"]),
            angular_velocity_covariance=np.array(values["angular_velocity_covariance"]),
            linear_acceleration=v3(*values["linear_acceleration"]),
            linear_acceleration_covariance=np.array(values["linear_acceleration_covariance"]),
        )
        suffix = "_be" if big_endian_cdr else ""
        bits = {key: f64_bits(v) for key, v in values.items()}
        out.write(f"imu_{i}{suffix}", store, IMU, msg, big_endian_cdr,
                  expect={"stamp": list(stamp), "frame_id": frame, **bits})


def main():
    if len(sys.argv) != 2:
        sys.exit("usage: messages.py OUT_DIR")
    root = Path(sys.argv[1])
    root.mkdir(parents=True, exist_ok=True)
    out = Out(root)
    write_clouds(out)
    write_bad_clouds(out)
    write_imus(out)
    (root / "manifest.json").write_text(json.dumps(out.manifest, indent=1))
    print(f"{len(out.manifest)} messages in {root}")


if __name__ == "__main__":
    main()
