"""Reads an MCAP file with PyPI's `mcap` and `mcap-ros2-support` (independent of irtrack's
writer), decodes every message with its ROS 2 schema and prints what it found as JSON.

usage: check_mcap.py FILE
"""
import json
import struct
import sys

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

out = {"counts": {}, "schemas": {}, "positions": [], "poses": [], "tf": [], "tf_children": [],
       "status": [], "clouds": [], "qos": {}, "monotonic": True, "profile": None, "summary": None,
       "metadata": []}
last = None
with open(sys.argv[1], "rb") as f:
    reader = make_reader(f, decoder_factories=[DecoderFactory()])
    out["profile"] = reader.get_header().profile
    # File order (the order the recorder wrote), not sorted by time: monotonic is checked.
    for schema, channel, message, msg in reader.iter_decoded_messages(log_time_order=False):
        t = channel.topic
        out["counts"][t] = out["counts"].get(t, 0) + 1
        out["schemas"][t] = [schema.name, schema.encoding, channel.message_encoding]
        out["qos"][t] = channel.metadata.get("offered_qos_profiles")
        if last is not None and message.log_time < last:
            out["monotonic"] = False
        last = message.log_time
        stamp = msg.header.stamp if hasattr(msg, "header") else None
        if schema.name == "geometry_msgs/msg/PointStamped":
            out["positions"].append([msg.header.frame_id, stamp.sec, stamp.nanosec,
                                     msg.point.x, msg.point.y, msg.point.z, message.log_time, t])
        elif schema.name == "geometry_msgs/msg/PoseStamped":
            p, q = msg.pose.position, msg.pose.orientation
            out["poses"].append([p.x, p.y, p.z, q.x, q.y, q.z, q.w, t, msg.header.frame_id,
                                 stamp.sec, stamp.nanosec])
        elif t == "/tf":
            tr = msg.transforms[0]
            out["tf"].append([tr.header.frame_id, tr.child_frame_id, tr.transform.translation.x])
            out["tf_children"].append([x.child_frame_id for x in msg.transforms])
        elif schema.name == "diagnostic_msgs/msg/DiagnosticStatus":
            out["status"].append([msg.level, msg.message, {kv.key: kv.value for kv in msg.values}])
        elif schema.name == "diagnostic_msgs/msg/DiagnosticArray":
            s = msg.status[0]
            out["status"].append([s.level, s.message, {kv.key: kv.value for kv in s.values},
                                  s.name, stamp.sec, stamp.nanosec])
        elif schema.name == "sensor_msgs/msg/PointCloud2":
            # Fields x y z float32 and loose_id uint32, as the writer declares them.
            offs = {fl.name: fl.offset for fl in msg.fields}
            pts = []
            for i in range(msg.width * msg.height):
                b = bytes(msg.data[i * msg.point_step:(i + 1) * msg.point_step])
                x, y, z = (struct.unpack_from("<f", b, offs[k])[0] for k in ("x", "y", "z"))
                pts.append([struct.unpack_from("<I", b, offs["loose_id"])[0], x, y, z])
            out["clouds"].append([stamp.sec, stamp.nanosec, pts])
    # The summary a finished recording has (None: a file ended after its last whole chunk,
    # read front to back above), and the metadata records.
    summary = reader.get_summary()
    if summary is not None:
        stats = summary.statistics
        out["summary"] = {"messages": stats.message_count if stats else None,
                          "chunks": len(summary.chunk_indexes)}
    out["metadata"] = [{"name": m.name, "metadata": dict(m.metadata)} for m in reader.iter_metadata()]
json.dump(out, sys.stdout)
