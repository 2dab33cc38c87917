#!/usr/bin/env python3
"""Anchor of `kfmap bench`'s bag rows: the pure-Python `rosbags` reader (0.11.9, PyPI)
against `kfmap bench bag-read` on the same MCAP file, one thread each, page cache warm.

    python tools/anchors/rosbags_read.py [--clouds 40] [--kfmap target/release/kfmap]

Writes an MCAP (rosbag2 folder, uncompressed chunks) of Ouster-layout PointCloud2
clouds (131 072 points x 48 bytes, as `kfmap bench` generates) with rosbags' own
writer, then reads it (best of three): rosbags streams the raw messages, then also
deserializes each one and views its x y z as a numpy (N, 3) float32 array; kfmap
streams, then decodes each into its point cloud. Prints GB/s of PointCloud2 payload.
Run in a venv with rosbags and numpy, outside the repository.
"""
import argparse
import json
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

POINTS, STEP = 131_072, 48


def write(path, clouds):
    ts = get_typestore(Stores.ROS2_HUMBLE)
    PointCloud2 = ts.types["sensor_msgs/msg/PointCloud2"]
    PointField = ts.types["sensor_msgs/msg/PointField"]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    spec = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7), ("t", 20, 6),
            ("reflectivity", 24, 4), ("ring", 26, 4), ("ambient", 28, 4), ("range", 32, 6)]
    rng = np.random.default_rng(1)
    data = rng.integers(0, 255, size=POINTS * STEP, dtype=np.uint8)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
        for k in range(clouds):
            stamp = 1_700_000_000 * 10**9 + k * 100_000_000
            msg = PointCloud2(
                header=Header(stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9),
                              frame_id="lidar"),
                height=128, width=1024,
                fields=[PointField(name=n, offset=o, datatype=d, count=1) for n, o, d in spec],
                is_bigendian=False, point_step=STEP, row_step=STEP * 1024, data=data,
                is_dense=True)
            writer.write(conn, stamp, ts.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
    return ts


def read(path, ts, decode):
    seen = 0
    with Reader(path) as reader:
        for conn, _, raw in reader.messages():
            if decode:
                msg = ts.deserialize_cdr(raw, conn.msgtype)
                points = np.frombuffer(msg.data, dtype=np.uint8).reshape(-1, msg.point_step)
                xyz = points[:, :12].copy().view("<f4").reshape(-1, 3)
                seen += len(xyz)
            else:
                seen += len(raw)
    return seen


def best(fn):
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--clouds", type=int, default=40)
    ap.add_argument("--kfmap", default="target/release/kfmap")
    args = ap.parse_args()
    payload = args.clouds * POINTS * STEP
    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / "ouster"
        ts = write(bag, args.clouds)
        stream_s = best(lambda: read(bag, ts, False))
        decode_s = best(lambda: read(bag, ts, True))
        kfmap = json.loads(subprocess.run([args.kfmap, "bench", "bag-read", str(bag)],
                                          check=True, capture_output=True, text=True).stdout)
    print(f"payload {payload / 1e6:.0f} MB in {args.clouds} clouds")
    print(f"rosbags: stream {payload / stream_s / 1e9:.2f} GB/s, "
          f"deserialize + xyz view {payload / decode_s / 1e9:.2f} GB/s")
    print(f"kfmap:   stream {kfmap['stream_gb_s']:.2f} GB/s, "
          f"decode to points {kfmap['decode_gb_s']:.2f} GB/s")


if __name__ == "__main__":
    main()
