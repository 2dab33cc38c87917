#!/usr/bin/env python3
"""Writes a kfmap dataset folder (binary PCD scans, a TUM pose file, an IMU log) as a
bag with the `rosbags` package: an independent writer for kfmap's bag tests.

    dataset_to_bag.py DATASET OUT --container mcap|sqlite3|ros1 [--scans A..B]
        [--points-topic /points] [--imu-topic /imu] [--imu FILE] [--poses FILE]
        [--ros1-compression none|bz2|lz4] [--layout plain|ouster|velodyne|hesai|
        livox|livox-offset|robosense] [--base-sec S] [--break-cloud N]

Each scan becomes a sensor_msgs/PointCloud2 with the PCD's fields (float32, in the
PCD's order) and its header stamp (and log time) from the pose file's stamp of that
scan; each IMU line (t ax ay az wx wy wz, commas or spaces) a sensor_msgs/Imu at t.
Stamps are split into whole seconds and nanoseconds from the text, never through a
float, so the bag carries exactly the pose file's times.

--layout writes each cloud as that driver lays its points out, with the PCD's `time`
field (seconds after the scan stamp) in the driver's time field and unit: ouster `t`
UINT32 ns, velodyne `time` FLOAT32 s, hesai `timestamp` FLOAT64 s since the epoch,
livox (driver 2) `timestamp` FLOAT64 ns since the epoch, livox-offset `offset_time`
UINT32 ns, robosense `timestamp` FLOAT64 s since the epoch. --base-sec adds whole
seconds to every stamp (absolute per-point times need an epoch-like clock).
--break-cloud N drops the z field of cloud N (a bad-input case).
"""
import argparse
import re
from pathlib import Path

import numpy as np
from rosbags.typesys import Stores, get_typestore


def read_pcd(path):
    """x y z (and any other float32 fields) of a binary or ascii PCD, as a dict."""
    data = path.read_bytes()
    header = {}
    offset = 0
    while True:
        end = data.index(b"\n", offset)
        line = data[offset:end].decode("ascii").strip()
        offset = end + 1
        if not line or line.startswith("#"):
            continue
        key, _, rest = line.partition(" ")
        header[key] = rest.split()
        if key == "DATA":
            break
    fields = header["FIELDS"]
    assert header["TYPE"] == ["F"] * len(fields), f"{path}: only float fields"
    assert header["SIZE"] == ["4"] * len(fields), f"{path}: only float32 fields"
    n = int(header["POINTS"][0])
    mode = header["DATA"][0]
    if mode == "binary":
        values = np.frombuffer(data, dtype="<f4", count=n * len(fields), offset=offset)
    elif mode == "ascii":
        values = np.array(data[offset:].split(), dtype=np.float32)[: n * len(fields)]
    else:
        raise SystemExit(f"{path}: DATA {mode} not handled by this test writer")
    return fields, values.reshape(n, len(fields))


def stamp_parts(text):
    """A decimal time string as (sec, nanosec), exactly."""
    whole, _, frac = text.partition(".")
    frac = (frac + "000000000")[:9]
    return int(whole), int(frac)


# Driver layouts: (name, numpy type, byte offset) per field, and the point step.
LAYOUTS = {
    "ouster": ([("x", "<f4", 0), ("y", "<f4", 4), ("z", "<f4", 8), ("intensity", "<f4", 16),
                ("t", "<u4", 20), ("reflectivity", "<u2", 24), ("ring", "<u2", 26),
                ("ambient", "<u2", 28), ("range", "<u4", 32)], 48),
    "velodyne": ([("x", "<f4", 0), ("y", "<f4", 4), ("z", "<f4", 8), ("intensity", "<f4", 12),
                  ("ring", "<u2", 16), ("time", "<f4", 18)], 22),
    "hesai": ([("x", "<f4", 0), ("y", "<f4", 4), ("z", "<f4", 8), ("intensity", "<f4", 12),
               ("ring", "<u2", 16), ("timestamp", "<f8", 18)], 26),
    "livox": ([("x", "<f4", 0), ("y", "<f4", 4), ("z", "<f4", 8), ("intensity", "<f4", 12),
               ("tag", "u1", 16), ("line", "u1", 17), ("timestamp", "<f8", 18)], 26),
    "livox-offset": ([("x", "<f4", 0), ("y", "<f4", 4), ("z", "<f4", 8),
                      ("intensity", "<f4", 12), ("tag", "u1", 16), ("line", "u1", 17),
                      ("offset_time", "<u4", 18)], 22),
    "robosense": ([("x", "<f4", 0), ("y", "<f4", 4), ("z", "<f4", 8), ("intensity", "<f4", 12),
                   ("ring", "<u2", 16), ("timestamp", "<f8", 24)], 32),
}
ROS_TYPES = {"<f4": 7, "<f8": 8, "<u4": 6, "<u2": 4, "u1": 2}


def driver_cloud(layout, fields, values, sec, nsec):
    """The point bytes and PointFields of a cloud in a driver's layout."""
    spec, step = LAYOUTS[layout]
    dtype = np.dtype({"names": [f[0] for f in spec], "formats": [f[1] for f in spec],
                      "offsets": [f[2] for f in spec], "itemsize": step})
    col = {f: values[:, k] for k, f in enumerate(fields)}
    rel = col["time"].astype(np.float64)  # seconds after the stamp
    stamp = sec + nsec * 1e-9
    points = np.zeros(len(values), dtype=dtype)
    for axis in "xyz":
        points[axis] = col[axis]
    if "intensity" in col:
        points["intensity"] = col["intensity"]
    time_values = {
        "ouster": ("t", np.round(rel * 1e9)),
        "velodyne": ("time", rel),
        "hesai": ("timestamp", stamp + rel),
        "livox": ("timestamp", (sec * 10**9 + nsec) + np.round(rel * 1e9)),
        "livox-offset": ("offset_time", np.round(rel * 1e9)),
        "robosense": ("timestamp", stamp + rel),
    }
    name, value = time_values[layout]
    points[name] = value
    return spec, step, points.tobytes()


def read_stamps(poses):
    return [stamp_parts(line.split()[0]) for line in poses.read_text().splitlines()
            if line.strip() and not line.startswith("#")]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--container", choices=["mcap", "sqlite3", "ros1"], required=True)
    ap.add_argument("--scans", default="..")
    ap.add_argument("--points-topic", default="/points")
    ap.add_argument("--imu-topic", default="/imu")
    ap.add_argument("--imu", type=Path)
    ap.add_argument("--poses", type=Path)
    ap.add_argument("--ros1-compression", choices=["none", "bz2", "lz4"], default="none")
    ap.add_argument("--layout", choices=["plain"] + sorted(LAYOUTS), default="plain")
    ap.add_argument("--base-sec", type=int, default=0)
    ap.add_argument("--break-cloud", type=int)
    args = ap.parse_args()

    scan_dir = args.dataset / "scans" if (args.dataset / "scans").is_dir() else args.dataset
    scans = sorted(p for p in scan_dir.iterdir() if p.suffix.lower() == ".pcd")
    poses = args.poses or next(args.dataset / n for n in
                               ["poses_gt.txt", "poses.txt", "traj.txt"]
                               if (args.dataset / n).is_file())
    stamps = [(s + args.base_sec, n) for s, n in read_stamps(poses)]
    a, _, b = args.scans.partition("..")
    picked = range(int(a or 0), int(b or len(scans)))
    ros1 = args.container == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    PointCloud2 = ts.types["sensor_msgs/msg/PointCloud2"]
    PointField = ts.types["sensor_msgs/msg/PointField"]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    Imu = ts.types["sensor_msgs/msg/Imu"]
    Quaternion = ts.types["geometry_msgs/msg/Quaternion"]
    Vector3 = ts.types["geometry_msgs/msg/Vector3"]

    def header(sec, nsec, frame, seq=0):
        if ros1:
            return Header(seq=seq, stamp=Time(sec=sec, nanosec=nsec), frame_id=frame)
        return Header(stamp=Time(sec=sec, nanosec=nsec), frame_id=frame)

    messages = []  # (log time ns, topic, message)
    for i in picked:
        fields, values = read_pcd(scans[i])
        sec, nsec = stamps[i]
        if args.layout == "plain":
            spec = [(f, "<f4", 4 * k) for k, f in enumerate(fields)]
            step = 4 * len(fields)
            data = np.ascontiguousarray(values, dtype="<f4").tobytes()
        else:
            spec, step, data = driver_cloud(args.layout, fields, values, sec, nsec)
        if i == args.break_cloud:
            spec = [f for f in spec if f[0] != "z"]
        cloud = PointCloud2(
            header=header(sec, nsec, "lidar", i),
            height=1, width=len(values),
            fields=[PointField(name=f, offset=o, datatype=ROS_TYPES[t], count=1)
                    for f, t, o in spec],
            is_bigendian=False, point_step=step, row_step=step * len(values),
            data=np.frombuffer(data, dtype=np.uint8),
            is_dense=True)
        messages.append((sec * 10**9 + nsec, args.points_topic, cloud))
    if args.imu:
        for k, line in enumerate(args.imu.read_text().splitlines()):
            cols = re.split(r"[,\s]+", line.strip())
            if len(cols) != 7 or not re.match(r"^-?[0-9]", cols[0]):
                continue  # the CSV header
            sec, nsec = stamp_parts(cols[0])
            sec += args.base_sec
            v = [float(c) for c in cols[1:]]
            zero9 = np.zeros(9)
            imu = Imu(header=header(sec, nsec, "imu", k),
                      orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
                      orientation_covariance=np.array([-1.0] + [0.0] * 8),
                      angular_velocity=Vector3(x=v[3], y=v[4], z=v[5]),
                      angular_velocity_covariance=zero9,
                      linear_acceleration=Vector3(x=v[0], y=v[1], z=v[2]),
                      linear_acceleration_covariance=zero9)
            messages.append((sec * 10**9 + nsec, args.imu_topic, imu))
    messages.sort(key=lambda m: m[0])
    types = {args.points_topic: "sensor_msgs/msg/PointCloud2",
             args.imu_topic: "sensor_msgs/msg/Imu"}

    if ros1:
        from rosbags.rosbag1 import Writer
        writer = Writer(args.out)
        if args.ros1_compression != "none":
            writer.set_compression(getattr(Writer.CompressionFormat,
                                           args.ros1_compression.upper()))
        with writer:
            conns = {}
            for t, topic, msg in messages:
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, types[topic], typestore=ts)
                writer.write(conns[topic], t, ts.serialize_ros1(msg, types[topic]))
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer
        plugin = StoragePlugin.MCAP if args.container == "mcap" else StoragePlugin.SQLITE3
        with Writer(args.out, version=9, storage_plugin=plugin) as writer:
            conns = {}
            for t, topic, msg in messages:
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, types[topic], typestore=ts)
                writer.write(conns[topic], t, ts.serialize_cdr(msg, types[topic]))


if __name__ == "__main__":
    main()
