"""An independent ROS 2 peer for kfmap-ros2's tests, on Eclipse Cyclone DDS (the DDS of
rmw_cyclonedds_cpp) through its PyPI binding: it publishes clouds (and an initial pose)
with the ROS 2 type and topic names and records what the node publishes.

    dds_peer.py MANIFEST OUT

MANIFEST (JSON): {"domain": 0, "wait_s": 30, "timeout_s": 20, "clouds": [{"stamp": s,
"frame_id": "lidar", "fields": [[name, offset, datatype, count], ...], "point_step": 16,
"width": n, "data": "path of the point bytes"}, ...], "initial_pose": {"before": k,
"pose": [x, y, z, qx, qy, qz, qw]} (optional)}; a cloud's "imu": [[t, ax, ay, az, gx, gy,
gz], ...] goes out on /imu (frame "imu_frame", default "imu") just before it, and its
"tf": [[parent, child, stamp, x, y, z, qx, qy, qz, qw], ...] on /tf; "tf_static": [[parent,
child, x, y, z, qx, qy, qz, qw], ...] goes out once, latched, before the first cloud. An entry {"pause": {"reached": path, "go":
path}} among the clouds creates `reached` and waits (at most wait_s) for `go` to exist
before the next cloud. Clouds are sent one at a time: the next
only after the node's diagnostics for this one's stamp arrived (at most timeout_s), so
every cloud is localized and none is dropped; with "period_s": p, cloud k also waits
until k periods after the first went out (a sensor's rate). With "lockstep": false the
clouds go out at the period whatever the node answers (a sensor that does not wait), and
the peer waits (at most timeout_s) for the diagnostics of the last cloud, then listens
"linger_s" (default 1) more: a fixed wait alone lost the last answer on a loaded CI host.

OUT: JSON lines, one per message received: {"topic": "pose", "stamp": s, "pose": [...],
"covariance": [...36]}, {"topic": "diagnostics", "stamp": s, "level": l, "message": m},
{"topic": "odometry", ...}, {"topic": "tf", "stamp": s, "parent": p, "child": c,
"transform": [...]}, {"topic": "gravity", "stamp": s, "frame": f, "vector": [x, y, z]}. Exits 1 when the node never matched or a cloud went unanswered.

With "record_bag": path in MANIFEST, the node's pose, diagnostics and map cloud are also
written to an MCAP bag as `ros2 bag record` writes them (the CDR bytes as received,
schemas in ros2msg), for `kfmap plot --bag`.
"""

import json
import os
import sys
import time
from dataclasses import dataclass

from cyclonedds.core import InstanceState, Policy, Qos, ReadCondition, SampleState, ViewState, WaitSet
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import array, float64, int32, sequence, uint8, uint32
from cyclonedds.util import duration
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32
    nanosec: uint32


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time
    frame_id: str


@dataclass
class PointField(IdlStruct, typename="sensor_msgs::msg::dds_::PointField_"):
    name: str
    offset: uint32
    datatype: uint8
    count: uint32


@dataclass
class PointCloud2(IdlStruct, typename="sensor_msgs::msg::dds_::PointCloud2_"):
    header: Header
    height: uint32
    width: uint32
    fields: sequence[PointField]
    is_bigendian: bool
    point_step: uint32
    row_step: uint32
    data: sequence[uint8]
    is_dense: bool


def byte_sequence_in_one_copy(cls, field):
    """Writes and reads `cls.field`, a sequence[uint8] in the type information, as one
    byte string: the same CDR (a length, then the bytes), one copy instead of one
    element at a time (50 ms for a 1.6 MB cloud, too slow for 10 Hz)."""
    from cyclonedds.idl._machinery import BytesMachine

    cls.__idl__.populate()
    for machine in (cls.__idl__.v1_machine, cls.__idl__.v2_machine):
        members = getattr(machine, "members_machines", None)
        if members is not None and field in members:
            members[field] = BytesMachine()


byte_sequence_in_one_copy(PointCloud2, "data")


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: float64
    y: float64
    z: float64


@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: float64
    y: float64
    z: float64


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: float64
    y: float64
    z: float64
    w: float64


@dataclass
class Vector3Stamped(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3Stamped_"):
    header: Header
    vector: Vector3


@dataclass
class Imu(IdlStruct, typename="sensor_msgs::msg::dds_::Imu_"):
    header: Header
    orientation: Quaternion
    orientation_covariance: array[float64, 9]
    angular_velocity: Vector3
    angular_velocity_covariance: array[float64, 9]
    linear_acceleration: Vector3
    linear_acceleration_covariance: array[float64, 9]


@dataclass
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point
    orientation: Quaternion


@dataclass
class PoseWithCovariance(IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovariance_"):
    pose: Pose
    covariance: array[float64, 36]


@dataclass
class PoseWithCovarianceStamped(
    IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"
):
    header: Header
    pose: PoseWithCovariance


@dataclass
class Twist(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
    linear: Vector3
    angular: Vector3


@dataclass
class TwistWithCovariance(IdlStruct, typename="geometry_msgs::msg::dds_::TwistWithCovariance_"):
    twist: Twist
    covariance: array[float64, 36]


@dataclass
class Odometry(IdlStruct, typename="nav_msgs::msg::dds_::Odometry_"):
    header: Header
    child_frame_id: str
    pose: PoseWithCovariance
    twist: TwistWithCovariance


@dataclass
class Transform(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation: Vector3
    rotation: Quaternion


@dataclass
class TransformStamped(IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):
    header: Header
    child_frame_id: str
    transform: Transform


@dataclass
class TFMessage(IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    transforms: sequence[TransformStamped]


@dataclass
class KeyValue(IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    key: str
    value: str


@dataclass
class DiagnosticStatus(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    level: uint8
    name: str
    message: str
    hardware_id: str
    values: sequence[KeyValue]


@dataclass
class DiagnosticArray(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    header: Header
    status: sequence[DiagnosticStatus]


def stamp_of(seconds):
    sec = int(seconds // 1)
    nanosec = int(round((seconds - sec) * 1e9))
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return Time(sec=sec, nanosec=nanosec)


def seconds_of(t):
    return t.sec + t.nanosec * 1e-9


# The recorded types' definitions (ros2msg, dependencies after a separator line), as
# rosbag2 stores them in an MCAP schema.
SEPARATOR = "=" * 80 + "\n"
HEADER = "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
TIME = "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
SCHEMAS = {
    "pose": ("geometry_msgs/msg/PoseWithCovarianceStamped", [
        "std_msgs/Header header\ngeometry_msgs/PoseWithCovariance pose\n", HEADER, TIME,
        "MSG: geometry_msgs/PoseWithCovariance\ngeometry_msgs/Pose pose\n"
        "float64[36] covariance\n",
        "MSG: geometry_msgs/Pose\ngeometry_msgs/Point position\n"
        "geometry_msgs/Quaternion orientation\n",
        "MSG: geometry_msgs/Point\nfloat64 x\nfloat64 y\nfloat64 z\n",
        "MSG: geometry_msgs/Quaternion\nfloat64 x 0\nfloat64 y 0\nfloat64 z 0\n"
        "float64 w 1\n",
    ]),
    "diagnostics": ("diagnostic_msgs/msg/DiagnosticArray", [
        "std_msgs/Header header\nDiagnosticStatus[] status\n", HEADER, TIME,
        "MSG: diagnostic_msgs/DiagnosticStatus\nbyte OK=0\nbyte WARN=1\nbyte ERROR=2\n"
        "byte STALE=3\nbyte level\nstring name\nstring message\nstring hardware_id\n"
        "KeyValue[] values\n",
        "MSG: diagnostic_msgs/KeyValue\nstring key\nstring value\n",
    ]),
    "map_cloud": ("sensor_msgs/msg/PointCloud2", [
        "std_msgs/Header header\nuint32 height\nuint32 width\nPointField[] fields\n"
        "bool is_bigendian\nuint32 point_step\nuint32 row_step\nuint8[] data\n"
        "bool is_dense\n", HEADER, TIME,
        "MSG: sensor_msgs/PointField\nuint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\n"
        "uint8 UINT16=4\nuint8 INT32=5\nuint8 UINT32=6\nuint8 FLOAT32=7\n"
        "uint8 FLOAT64=8\nstring name\nuint32 offset\nuint8 datatype\nuint32 count\n",
    ]),
}
TOPICS = {"pose": "/kfmap/pose", "diagnostics": "/diagnostics", "map_cloud": "/kfmap/map_cloud"}


class BagRecorder:
    """The node's outputs into an MCAP bag, as `ros2 bag record` stores them."""

    def __init__(self, path):
        from mcap.writer import Writer

        self.file = open(path, "wb")
        self.writer = Writer(self.file)
        self.writer.start(profile="ros2", library="kfmap dds_peer.py")
        self.channels = {}
        for topic, (name, parts) in SCHEMAS.items():
            schema = self.writer.register_schema(
                name=name, encoding="ros2msg", data=SEPARATOR.join(parts).encode())
            self.channels[topic] = self.writer.register_channel(
                topic=TOPICS[topic], message_encoding="cdr", schema_id=schema)

    def add(self, topic, sample):
        if topic in self.channels:
            now = time.time_ns()
            self.writer.add_message(self.channels[topic], log_time=now,
                                    data=sample.serialize(), publish_time=now)

    def close(self):
        self.writer.finish()
        self.file.close()


def main():
    manifest = json.load(open(sys.argv[1]))
    out = open(sys.argv[2], "w")
    participant = DomainParticipant(manifest.get("domain", 0))
    reliable = Qos(Policy.Reliability.Reliable(1_000_000_000), Policy.History.KeepLast(1000))
    latched = Qos(
        Policy.Reliability.Reliable(1_000_000_000),
        Policy.Durability.TransientLocal,
        Policy.History.KeepLast(1),
    )
    clouds_topic = Topic(participant, "rt/points", PointCloud2)
    cloud_writer = DataWriter(participant, clouds_topic, reliable)
    imu_writer = DataWriter(participant, Topic(participant, "rt/imu", Imu), reliable)
    tf_topic = Topic(participant, "rt/tf", TFMessage)
    tf_writer = DataWriter(participant, tf_topic, reliable)
    tf_static_writer = DataWriter(
        participant, Topic(participant, "rt/tf_static", TFMessage), latched)

    def transform(parent, child, stamp, x, y, z, qx, qy, qz, qw):
        return TransformStamped(
            header=Header(stamp=stamp_of(stamp), frame_id=parent),
            child_frame_id=child,
            transform=Transform(translation=Vector3(x=x, y=y, z=z),
                                rotation=Quaternion(x=qx, y=qy, z=qz, w=qw)),
        )
    initial_writer = DataWriter(
        participant, Topic(participant, "rt/initialpose", PoseWithCovarianceStamped), reliable
    )
    readers = {
        "pose": DataReader(
            participant, Topic(participant, "rt/kfmap/pose", PoseWithCovarianceStamped), reliable
        ),
        "odometry": DataReader(
            participant, Topic(participant, "rt/kfmap/odometry", Odometry), reliable
        ),
        "tf": DataReader(participant, tf_topic, reliable),
        "diagnostics": DataReader(
            participant, Topic(participant, "rt/diagnostics", DiagnosticArray), reliable
        ),
        "map_cloud": DataReader(
            participant, Topic(participant, "rt/kfmap/map_cloud", PointCloud2), latched
        ),
        "gravity": DataReader(
            participant, Topic(participant, "rt/kfmap/gravity", Vector3Stamped), latched
        ),
    }

    recorder = BagRecorder(manifest["record_bag"]) if "record_bag" in manifest else None

    def record(topic, sample):
        if recorder is not None:
            recorder.add(topic, sample)
        if topic == "pose":
            p = sample.pose.pose
            line = {
                "stamp": seconds_of(sample.header.stamp),
                "frame": sample.header.frame_id,
                "pose": [p.position.x, p.position.y, p.position.z, p.orientation.x,
                         p.orientation.y, p.orientation.z, p.orientation.w],
                "covariance": list(sample.pose.covariance),
            }
        elif topic == "odometry":
            p = sample.pose.pose
            line = {
                "stamp": seconds_of(sample.header.stamp),
                "child": sample.child_frame_id,
                "pose": [p.position.x, p.position.y, p.position.z, p.orientation.x,
                         p.orientation.y, p.orientation.z, p.orientation.w],
            }
        elif topic == "tf":
            for t in sample.transforms:
                r, q = t.transform.translation, t.transform.rotation
                out.write(json.dumps({
                    "topic": "tf", "stamp": seconds_of(t.header.stamp),
                    "parent": t.header.frame_id, "child": t.child_frame_id,
                    "transform": [r.x, r.y, r.z, q.x, q.y, q.z, q.w],
                }) + "\n")
            return []
        elif topic == "diagnostics":
            s = sample.status[0]
            line = {
                "stamp": seconds_of(sample.header.stamp),
                "level": int(s.level),
                "message": s.message,
                "values": {kv.key: kv.value for kv in s.values},
            }
        elif topic == "gravity":
            v = sample.vector
            line = {"stamp": seconds_of(sample.header.stamp), "frame": sample.header.frame_id,
                    "vector": [v.x, v.y, v.z]}
        else:
            line = {"stamp": seconds_of(sample.header.stamp), "frame": sample.header.frame_id,
                    "points": sample.width * sample.height}
        line["topic"] = topic
        out.write(json.dumps(line) + "\n")
        return [line]

    # Waiting for the node's outputs blocks on a wait set (no polling: the peer shares
    # the cores with the node and the server it measures).
    waitset = WaitSet(participant)
    for reader in readers.values():
        waitset.attach(ReadCondition(
            reader, SampleState.NotRead | ViewState.Any | InstanceState.Any))

    def wait_for_output(seconds):
        waitset.wait(duration(seconds=max(seconds, 0.0)))

    def drain():
        got = []
        for topic, reader in readers.items():
            for sample in reader.take(N=1000):
                got.extend(record(topic, sample))
        out.flush()
        return got

    def answered_within(stamp, seconds):
        """Records what arrives until the node's diagnostics for `stamp` did (True) or
        `seconds` passed (False)."""
        deadline = time.monotonic() + seconds
        while True:
            if any(line["topic"] == "diagnostics" and abs(line["stamp"] - stamp) < 1e-6
                   for line in drain()):
                return True
            if time.monotonic() > deadline:
                return False
            wait_for_output(min(0.05, deadline - time.monotonic()))

    # Bounded waits for the node's readers, under one deadline.
    deadline = time.monotonic() + manifest.get("wait_s", 30)

    def wait_matched(writer, topic):
        while writer.get_matched_subscriptions() == []:
            if time.monotonic() > deadline:
                print(f"dds_peer: the node's {topic} reader never matched", file=sys.stderr)
                sys.exit(1)
            time.sleep(0.05)

    wait_matched(cloud_writer, "/points")
    if manifest.get("tf_static"):
        # The mounting reaches the node before the first cloud: its reader matched, the
        # sample acknowledged (both bounded), never a fixed wait.
        wait_matched(tf_static_writer, "/tf_static")
        tf_static_writer.write(TFMessage(transforms=[
            transform(parent, child, 0.0, *values)
            for parent, child, *values in manifest["tf_static"]]))
        if not tf_static_writer.wait_for_acks(duration(seconds=manifest.get("wait_s", 30))):
            print("dds_peer: /tf_static was never acknowledged", file=sys.stderr)
            sys.exit(1)
    timeout = manifest.get("timeout_s", 20)
    initial = manifest.get("initial_pose")
    # Publishing rate: cloud k goes out at k periods after the first (a sensor's rate),
    # or, when the node is slower, once the previous one is answered.
    period = manifest.get("period_s", 0.0)
    lockstep = manifest.get("lockstep", True)
    first_sent = None
    for k, cloud in enumerate(manifest["clouds"]):
        if "pause" in cloud:
            open(cloud["pause"]["reached"], "w").close()
            deadline = time.monotonic() + manifest.get("wait_s", 30)
            while not os.path.exists(cloud["pause"]["go"]):
                if time.monotonic() > deadline:
                    print(f"dds_peer: no {cloud['pause']['go']} within wait_s", file=sys.stderr)
                    sys.exit(1)
                drain()
                wait_for_output(0.02)
            continue
        if initial is not None and initial["before"] == k:
            x, y, z, qx, qy, qz, qw = initial["pose"]
            initial_writer.write(PoseWithCovarianceStamped(
                header=Header(stamp=stamp_of(cloud["stamp"]), frame_id="map"),
                pose=PoseWithCovariance(
                    pose=Pose(position=Point(x=x, y=y, z=z),
                              orientation=Quaternion(x=qx, y=qy, z=qz, w=qw)),
                    covariance=[0.0] * 36,
                ),
            ))
            time.sleep(0.2)
        # The IMU samples up to this cloud first (a driver's IMU runs ahead of the
        # cloud, which goes out once the sweep is over), given a moment to arrive.
        for t, ax, ay, az, gx, gy, gz in cloud.get("imu", []):
            imu_writer.write(Imu(
                header=Header(stamp=stamp_of(t), frame_id=cloud.get("imu_frame", "imu")),
                orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=[-1.0] + [0.0] * 8,
                angular_velocity=Vector3(x=gx, y=gy, z=gz),
                angular_velocity_covariance=[0.0] * 9,
                linear_acceleration=Vector3(x=ax, y=ay, z=az),
                linear_acceleration_covariance=[0.0] * 9,
            ))
        if cloud.get("tf"):
            tf_writer.write(TFMessage(transforms=[
                transform(*t) for t in cloud["tf"]]))
        if cloud.get("imu") or cloud.get("tf"):
            time.sleep(0.02)
        data = open(cloud["data"], "rb").read()
        message = PointCloud2(
            header=Header(stamp=stamp_of(cloud["stamp"]), frame_id=cloud["frame_id"]),
            height=1,
            width=cloud["width"],
            fields=[PointField(name=n, offset=o, datatype=d, count=c)
                    for n, o, d, c in cloud["fields"]],
            is_bigendian=False,
            point_step=cloud["point_step"],
            row_step=cloud["point_step"] * cloud["width"],
            data=data,
            is_dense=False,
        )
        stamp = seconds_of(message.header.stamp)
        if first_sent is None:
            first_sent = time.monotonic()
        else:
            time.sleep(max(0.0, first_sent + k * period - time.monotonic()))
        cloud_writer.write(message)
        if not lockstep:
            drain()
            continue
        if not answered_within(stamp, timeout):
            print(f"dds_peer: no diagnostics for cloud {k} (stamp {stamp}) "
                  f"within {timeout} s", file=sys.stderr)
            sys.exit(1)
    if not lockstep and first_sent is not None:
        # The node keeps the newest cloud, so the last one sent is always answered (the
        # test asserts it from what is recorded).
        answered_within(stamp, timeout)
    # What else is in flight (the last transforms, the latched map cloud; without
    # lockstep, the answers to the last clouds).
    end = time.monotonic() + manifest.get("linger_s", 1.0)
    while time.monotonic() < end:
        drain()
        wait_for_output(min(0.05, end - time.monotonic()))
    out.close()
    if recorder is not None:
        recorder.close()


if __name__ == "__main__":
    main()
