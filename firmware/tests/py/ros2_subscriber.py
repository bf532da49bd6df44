"""An independent ROS 2 subscriber without ROS: Cyclone DDS (PyPI `cyclonedds`, the DDS of
ROS 2's rmw_cyclonedds) reads the DDS topics `rt/<name>` with ROS 2's type names, and PyPI
`rosbags` decodes each sample's CDR bytes with its ROS 2 message definition. Cyclone's own
decoding is bypassed on purpose: the bytes are exactly what went over the wire.

usage: ros2_subscriber.py --domain N [--reliable] [--count N] [--seconds S]
                          [--stall-after K --stall-s S] TOPIC=TYPE ...
  TOPIC  a ROS 2 topic, e.g. /irtrack/probe4/pose (read as DDS topic rt/irtrack/probe4/pose)
  TYPE   a ROS 2 type, e.g. geometry_msgs/msg/PoseStamped

Prints one JSON line per sample: {"topic", "type", "msg"}; then {"done": counts}. With
--stall-after it stops taking samples after K of them (the reader stays matched, its queue
fills) for --stall-s seconds, then exits: a stalled consumer.
"""
import argparse
import json
import sys
import time
from dataclasses import dataclass

from cyclonedds.core import Qos, Policy, WaitSet, ReadCondition, SampleState, ViewState, InstanceState
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import float64, int32, uint8, uint32, sequence
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration
from rosbags.typesys import Stores, get_typestore


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32
    nanosec: uint32


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time
    frame_id: str


@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: float64
    y: float64
    z: float64


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
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
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point
    orientation: Quaternion


@dataclass
class PoseStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PoseStamped_"):
    header: Header
    pose: Pose


@dataclass
class PointStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PointStamped_"):
    header: Header
    point: Point


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


TYPES = {
    "geometry_msgs/msg/PoseStamped": PoseStamped,
    "geometry_msgs/msg/PointStamped": PointStamped,
    "tf2_msgs/msg/TFMessage": TFMessage,
    "sensor_msgs/msg/PointCloud2": PointCloud2,
}


class Raw:
    """The sample's serialized bytes (encapsulation header included), undecoded."""

    def __init__(self, data):
        self.data = bytes(data)


class RawDecoder:
    """Stands in for a topic's data type when its reader hands over samples: keeps the CDR
    bytes (matching, type name and key still come from the real IDL type)."""

    @staticmethod
    def deserialize(data, has_header=True, use_version_2=None):
        return Raw(data)

    @staticmethod
    def deserialize_key(data, has_header=True, use_version_2=None):
        return Raw(data)


def plain(v):
    """A rosbags message as JSON-friendly dicts and lists."""
    if hasattr(v, "__dataclass_fields__"):
        return {k: plain(getattr(v, k)) for k in v.__dataclass_fields__ if k != "__msgtype__"}
    if isinstance(v, (list, tuple)):
        return [plain(x) for x in v]
    if hasattr(v, "tolist"):
        return v.tolist()
    return v


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--domain", type=int, default=0)
    ap.add_argument("--reliable", action="store_true")
    ap.add_argument("--count", type=int, default=100, help="stop after this many samples in all")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--stall-after", type=int, default=None)
    ap.add_argument("--stall-s", type=float, default=3.0)
    ap.add_argument("--static", action="append", default=[],
                    help="TOPIC=TYPE read reliable + transient local (e.g. /tf_static)")
    ap.add_argument("topics", nargs="+")
    a = ap.parse_args()
    store = get_typestore(Stores.ROS2_HUMBLE)
    dp = DomainParticipant(a.domain)
    if a.reliable:
        qos = Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.History.KeepLast(5))
    else:
        qos = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(5))
    static_qos = Qos(Policy.Reliability.Reliable(duration(seconds=1)),
                     Policy.Durability.TransientLocal, Policy.History.KeepLast(1))
    readers = []
    for spec, q in [(s, qos) for s in a.topics] + [(s, static_qos) for s in a.static]:
        name, ty = spec.split("=", 1)
        topic = Topic(dp, "rt" + name, TYPES[ty])
        reader = DataReader(dp, topic, qos=q)
        topic.data_type = RawDecoder
        readers.append((name, ty, reader))
    ws = WaitSet(dp)
    for _, _, r in readers:
        ws.attach(ReadCondition(r, SampleState.Any | ViewState.Any | InstanceState.Any))
    print(json.dumps({"ready": [n for n, _, _ in readers]}), flush=True)
    counts = {n: 0 for n, _, _ in readers}
    total = 0
    end = time.monotonic() + a.seconds
    while time.monotonic() < end and total < a.count:
        if a.stall_after is not None and total >= a.stall_after:
            # Stalled: matched, never taking again.
            print(json.dumps({"stalled": total}), flush=True)
            time.sleep(a.stall_s)
            break
        ws.wait(duration(milliseconds=100))
        for name, ty, r in readers:
            for s in r.take(N=64):
                if not isinstance(s, Raw):
                    continue
                msg = store.deserialize_cdr(s.data, ty)
                counts[name] += 1
                total += 1
                print(json.dumps({"topic": name, "type": ty, "msg": plain(msg)}), flush=True)
    print(json.dumps({"done": counts}), flush=True)


if __name__ == "__main__":
    sys.exit(main())
