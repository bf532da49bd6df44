"""Reads an MCAP file with PyPI's `mcap` and `mcap-ros2-support` (independent of irtrack's
writer), decodes every message with its ROS 2 schema and prints what it found as JSON.

usage: check_mcap.py FILE
"""
import json
import sys

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

out = {"counts": {}, "schemas": {}, "positions": [], "poses": [], "tf": [], "status": [],
       "monotonic": True, "profile": None}
last = None
with open(sys.argv[1], "rb") as f:
    reader = make_reader(f, decoder_factories=[DecoderFactory()])
    out["profile"] = reader.get_header().profile
    # File order (the order the recorder wrote), not sorted by time: monotonic is checked.
    for schema, channel, message, msg in reader.iter_decoded_messages(log_time_order=False):
        t = channel.topic
        out["counts"][t] = out["counts"].get(t, 0) + 1
        out["schemas"][t] = [schema.name, schema.encoding, channel.message_encoding]
        if last is not None and message.log_time < last:
            out["monotonic"] = False
        last = message.log_time
        stamp = msg.header.stamp if hasattr(msg, "header") else None
        if t == "/irtrack/position":
            out["positions"].append([msg.header.frame_id, stamp.sec, stamp.nanosec,
                                     msg.point.x, msg.point.y, msg.point.z, message.log_time])
        elif t == "/irtrack/pose":
            p, q = msg.pose.position, msg.pose.orientation
            out["poses"].append([p.x, p.y, p.z, q.x, q.y, q.z, q.w])
        elif t == "/tf":
            tr = msg.transforms[0]
            out["tf"].append([tr.header.frame_id, tr.child_frame_id, tr.transform.translation.x])
        elif t == "/irtrack/status":
            out["status"].append([msg.level, msg.message, {kv.key: kv.value for kv in msg.values}])
json.dump(out, sys.stdout)
