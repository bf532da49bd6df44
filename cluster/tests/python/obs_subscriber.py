#!/usr/bin/env python3
"""Independent subscriber for irtrack observations (docs/observation-protocol.md).

Uses PyPI's eclipse-zenoh client, decodes each payload with `struct` and `zlib.crc32` from
the spec (not from the Rust code) and prints one JSON object per observation on stdout.

usage: obs_subscriber.py CONNECT_ENDPOINT KEY_EXPR COUNT TIMEOUT_S
"""
import json
import struct
import sys
import threading
import zlib

import zenoh


def decode(b: bytes) -> dict:
    if len(b) < 36 or b[0:2] != b"IO":
        raise ValueError("not an observation")
    version, flags, clock, camera, rig_len, board_len = struct.unpack_from("<BBBBBB", b, 2)
    if version != 1:
        raise ValueError(f"version {version}")
    seq, ts, exposure, dropped, delay = struct.unpack_from("<QQIII", b, 8)
    at = 36
    trigger = None
    if flags & 1:
        (trigger,) = struct.unpack_from("<Q", b, at)
        at += 8
    rig = b[at:at + rig_len].decode()
    at += rig_len
    board = b[at:at + board_len].decode()
    at += board_len
    count = b[at]
    at += 1
    blobs = []
    for _ in range(count):
        x, y, area, peak, rq, bflags, reserved = struct.unpack_from("<ffHHHBB", b, at)
        blobs.append({"x_px": x, "y_px": y, "area_px": area, "peak_dn": peak,
                      "roundness": rq / 65535.0, "flags": bflags})
        at += 16
    (crc,) = struct.unpack_from("<I", b, at)
    if crc != zlib.crc32(b[:at]) or at + 4 != len(b):
        raise ValueError("bad crc or length")
    return {"rig": rig, "board": board, "camera": camera, "sequence": seq,
            "capture_ts_ns": ts, "clock": clock, "exposure_us": exposure,
            "dropped": dropped, "send_delay_us": delay, "trigger": trigger, "blobs": blobs}


def main() -> int:
    endpoint, key, count, timeout_s = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    done = threading.Event()
    seen = []

    def on_sample(sample):
        if done.is_set():
            return
        try:
            obs = decode(bytes(sample.payload.to_bytes()))
            obs["key"] = str(sample.key_expr)
        except Exception as e:  # a bad payload is reported, not fatal
            obs = {"error": str(e), "key": str(sample.key_expr)}
        print(json.dumps(obs), flush=True)
        seen.append(obs)
        if len(seen) >= count:
            done.set()

    with zenoh.open(conf) as session:
        sub = session.declare_subscriber(key, on_sample)
        print(json.dumps({"ready": True}), flush=True)
        done.wait(timeout_s)
        sub.undeclare()
    return 0 if len(seen) >= count else 1


if __name__ == "__main__":
    sys.exit(main())
