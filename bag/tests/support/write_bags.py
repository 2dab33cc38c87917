#!/usr/bin/env python3
"""Writes small bags of known content in every container kfmap-bag reads, with an
independent writer (the `rosbags` package), and a JSON manifest of what they hold.

    write_bags.py OUT_DIR [--big-mcap MB]

OUT_DIR receives:

- mcap_none/, mcap_zstd/   rosbag2 folders, storage mcap (chunks uncompressed / zstd)
- mcap_lz4/                the same with lz4 chunks (rosbags' writer patched to lz4 frames)
- mcap_bz2/                chunks compressed with bz2, which MCAP readers need not read
- sqlite/                  a rosbag2 folder, storage sqlite3
- ros1_none.bag, ros1_bz2.bag, ros1_lz4.bag
- manifest.json            {"ros2": [...], "ros1": [...]}: per topic its name, type and
                           messages (log time in ns and the hex of the serialized bytes)

With --corpus it instead writes tiny bags (a few KB) as the fuzz seed corpora:
OUT_DIR/bag_mcap/seed_{none,zstd}.mcap, OUT_DIR/bag_ros1/seed_{none,bz2,lz4}.bag and
OUT_DIR/bag_sqlite/seed.db3 (vacuumed to 512-byte pages); OUT_DIR is fuzz/corpus.

With --big-mcap MB it instead writes only big.mcap (a rosbag2 mcap folder `big/`) of
about MB megabytes of 1 MB PointCloud2 messages, for throughput measurements.
"""

import argparse
import json
import lz4.frame
import bz2
from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.typesys import Stores, get_typestore

T0 = 1_700_000_000_000_000_000  # log times start here (ns)


def cloud(ts, index, points, types):
    """A PointCloud2 of `points` xyz float32 points whose values depend on `index`."""
    t = types
    fields = [
        t['sensor_msgs/msg/PointField'](name=n, offset=4 * i, datatype=7, count=1)
        for i, n in enumerate('xyz')
    ]
    xyz = (np.arange(points * 3, dtype=np.float32) + index * 0.5).reshape(points, 3)
    stamp = t['builtin_interfaces/msg/Time'](sec=ts // 10**9, nanosec=ts % 10**9)
    return t['sensor_msgs/msg/PointCloud2'](
        header=t['std_msgs/msg/Header'](stamp=stamp, frame_id='lidar'),
        height=1,
        width=points,
        fields=fields,
        is_bigendian=False,
        point_step=12,
        row_step=12 * points,
        data=np.frombuffer(xyz.tobytes(), dtype=np.uint8),
        is_dense=True,
    )


def imu(ts, index, types):
    t = types
    stamp = t['builtin_interfaces/msg/Time'](sec=ts // 10**9, nanosec=ts % 10**9)
    v3 = t['geometry_msgs/msg/Vector3']
    return t['sensor_msgs/msg/Imu'](
        header=t['std_msgs/msg/Header'](stamp=stamp, frame_id='imu'),
        orientation=t['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.zeros(9),
        angular_velocity=v3(x=0.01 * index, y=0.0, z=-0.02),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=v3(x=0.0, y=0.1, z=9.81),
        linear_acceleration_covariance=np.zeros(9),
    )


def tiny_messages(types):
    """Two small clouds, three imus, one string: the fuzz seeds."""
    return [
        ('/lidar/points', 'sensor_msgs/msg/PointCloud2', [(T0 + i, cloud(T0 + i, i, 2, types)) for i in range(2)]),
        ('/imu/data', 'sensor_msgs/msg/Imu', [(T0 + 10 * i, imu(T0 + 10 * i, i, types)) for i in range(3)]),
        ('/notes', 'std_msgs/msg/String', [(T0 + 5, types['std_msgs/msg/String'](data='hi'))]),
    ]


def corpus(out):
    """Tiny bags of every container for the fuzz seed corpora."""
    import shutil
    import sqlite3
    import tempfile

    for sub in ('bag_mcap', 'bag_ros1', 'bag_sqlite'):
        (out / sub).mkdir(parents=True, exist_ok=True)
    ros2 = tiny_messages(TS2.types)
    ser2 = lambda m: bytes(TS2.serialize_cdr(m, m.__msgtype__))  # noqa: E731
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for name, patch in [('none', None), ('zstd', 'zstd')]:
            write_ros2(tmp / name, StoragePlugin.MCAP, ros2, ser2, patch)
            shutil.copy(tmp / name / f'{name}.mcap', out / 'bag_mcap' / f'seed_{name}.mcap')
        write_ros2(tmp / 'db', StoragePlugin.SQLITE3, ros2, ser2)
        db = sqlite3.connect(tmp / 'db' / 'db.db3')
        db.execute('PRAGMA journal_mode=DELETE')
        db.execute('PRAGMA page_size=512')
        db.execute('VACUUM')
        db.close()
        shutil.copy(tmp / 'db' / 'db.db3', out / 'bag_sqlite' / 'seed.db3')
    ros1 = [(name, msgtype, [(ts, to_ros1(m)) for ts, m in msgs]) for name, msgtype, msgs in ros2]
    ser1 = lambda m: bytes(TS1.serialize_ros1(m, m.__msgtype__))  # noqa: E731
    for name, fmt in [('none', None), ('bz2', Writer1.CompressionFormat.BZ2), ('lz4', Writer1.CompressionFormat.LZ4)]:
        write_ros1(out / 'bag_ros1' / f'seed_{name}.bag', fmt, ros1, ser1)


def messages(types):
    """(topic, type, [(log time, message)]) of the small bags: clouds at 10 Hz, imu at
    100 Hz interleaved, and a few strings, one of them at the same time as a cloud."""
    clouds = [(T0 + i * 100_000_000, cloud(T0 + i * 100_000_000, i, 40 + 7 * i, types)) for i in range(6)]
    imus = [(T0 + 5_000_000 + i * 10_000_000, imu(T0 + i * 10_000_000, i, types)) for i in range(50)]
    strings = [
        (T0 + i * 200_000_000, types['std_msgs/msg/String'](data=f'note {i}' + 'x' * i))
        for i in range(3)
    ]
    return [
        ('/lidar/points', 'sensor_msgs/msg/PointCloud2', clouds),
        ('/imu/data', 'sensor_msgs/msg/Imu', imus),
        ('/notes', 'std_msgs/msg/String', strings),
    ]


def interleaved(topics):
    """Every (log time, topic index, message) in log-time order, as a recorder writes."""
    out = [(ts, k, msg) for k, (_, _, msgs) in enumerate(topics) for ts, msg in msgs]
    out.sort(key=lambda x: (x[0], x[1]))
    return out


def write_ros2(path, storage, topics, serialize, patch=None):
    writer = Writer2(path, version=9, storage_plugin=storage)
    if patch == 'zstd':
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    writer.open()
    if patch in ('lz4', 'bz2'):
        # rosbags writes zstd or plain chunks; these codecs are set on its MCAP writer.
        writer.storage.compression = patch
        writer.storage.compressor = lz4.frame.compress if patch == 'lz4' else bz2.compress
    conns = [writer.add_connection(name, msgtype, typestore=TS2) for name, msgtype, _ in topics]
    for n, (ts, k, msg) in enumerate(interleaved(topics)):
        writer.write(conns[k], ts, serialize(msg))
        if storage == StoragePlugin.MCAP and n % 16 == 15:
            # rosbags closes a chunk at 1 MiB; several chunks even for a small bag.
            writer.storage.close_chunk()
    writer.close()


def write_ros1(path, compression, topics, serialize):
    writer = Writer1(path)
    if compression:
        writer.set_compression(compression)
    writer.chunk_threshold = 4096  # several chunks even for a small bag
    writer.open()
    conns = [
        writer.add_connection(name, msgtype, typestore=TS1)
        for name, msgtype, _ in topics
    ]
    for ts, k, msg in interleaved(topics):
        writer.write(conns[k], ts, serialize(msg))
    writer.close()


def manifest(topics, serialize, ros1):
    return [
        {
            'name': name,
            'type': msgtype.replace('/msg/', '/') if ros1 else msgtype,
            'messages': [{'log_time_ns': ts, 'hex': bytes(serialize(m)).hex()} for ts, m in msgs],
        }
        for name, msgtype, msgs in topics
    ]


def big_mcap(out, megabytes):
    """A rosbag2 mcap folder of `megabytes` 1 MB PointCloud2 messages (uncompressed)."""
    types = TS2.types
    writer = Writer2(out / 'big', version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    conn = writer.add_connection('/lidar/points', 'sensor_msgs/msg/PointCloud2', typestore=TS2)
    points = (1 << 20) // 12
    for i in range(megabytes):
        ts = T0 + i * 100_000_000
        writer.write(conn, ts, bytes(TS2.serialize_cdr(cloud(ts, i, points, types), 'sensor_msgs/msg/PointCloud2')))
    writer.close()


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument('out', type=Path)
    parser.add_argument('--big-mcap', type=int, default=0)
    parser.add_argument('--corpus', action='store_true')
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.corpus:
        corpus(args.out)
        return
    if args.big_mcap:
        big_mcap(args.out, args.big_mcap)
        return

    ros2 = messages(TS2.types)
    ser2 = lambda m: bytes(TS2.serialize_cdr(m, m.__msgtype__))  # noqa: E731
    for name, patch in [('mcap_none', None), ('mcap_zstd', 'zstd'), ('mcap_lz4', 'lz4'), ('mcap_bz2', 'bz2')]:
        write_ros2(args.out / name, StoragePlugin.MCAP, ros2, ser2, patch)
    write_ros2(args.out / 'sqlite', StoragePlugin.SQLITE3, ros2, ser2)

    # ROS 1 messages: the same content, typed and serialized by the ROS 1 typestore.
    ros1 = [
        (name, msgtype, [(ts, to_ros1(m)) for ts, m in msgs])
        for name, msgtype, msgs in ros2
    ]
    ser1 = lambda m: bytes(TS1.serialize_ros1(m, m.__msgtype__))  # noqa: E731
    write_ros1(args.out / 'ros1_none.bag', None, ros1, ser1)
    write_ros1(args.out / 'ros1_bz2.bag', Writer1.CompressionFormat.BZ2, ros1, ser1)
    write_ros1(args.out / 'ros1_lz4.bag', Writer1.CompressionFormat.LZ4, ros1, ser1)

    (args.out / 'manifest.json').write_text(
        json.dumps({'ros2': manifest(ros2, ser2, False), 'ros1': manifest(ros1, ser1, True)})
    )


def to_ros1(msg):
    """The ROS 2 message `msg` as the ROS 1 typestore's type of the same name (the ROS 1
    header has a `seq`; the rest of these types match field for field)."""
    name = msg.__msgtype__
    cls = TS1.types[name]
    values = {}
    for field in cls.__dataclass_fields__:
        if field == 'seq':
            values[field] = 0
        elif field == 'stamp' and name == 'std_msgs/msg/Header':
            values[field] = TS1.types['builtin_interfaces/msg/Time'](sec=msg.stamp.sec, nanosec=msg.stamp.nanosec)
        else:
            value = getattr(msg, field)
            values[field] = [to_ros1(v) for v in value] if isinstance(value, list) else (
                to_ros1(value) if hasattr(value, '__msgtype__') else value
            )
    return cls(**values)


TS2 = get_typestore(Stores.ROS2_HUMBLE)
TS1 = get_typestore(Stores.ROS1_NOETIC)

if __name__ == '__main__':
    main()
