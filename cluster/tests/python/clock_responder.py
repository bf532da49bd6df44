#!/usr/bin/env python3
"""A camera board's clock probe answer, written from the message's spec alone
(irtrack_cluster::clock, docs/cluster.md "Clock probe") on PyPI's eclipse-zenoh: an
independent Zenoh stack and an independent reading of the 40-byte message.

Connects to the solver as BOARD (with credentials when given), declares the queryable
`irtrack/<RIG>/<BOARD>/clock` and answers every probe request for SECONDS seconds, stamping
arrival and departure on CLOCK_REALTIME shifted by OFFSET_MS (a board whose clock is off).
Prints one JSON line: requests answered and malformed requests seen.

usage: clock_responder.py CONNECT_ENDPOINT RIG BOARD OFFSET_MS SECONDS [USER PASSWORD]
"""
import json
import struct
import sys
import time

import zenoh

# magic, version, kind, reserved, id, t1, t2, t3 — little-endian, 40 bytes.
LAYOUT = struct.Struct("<4sBBHQQQQ")


def main() -> int:
    endpoint, rig, board = sys.argv[1], sys.argv[2], sys.argv[3]
    offset_ns = int(float(sys.argv[4]) * 1e6)
    seconds = float(sys.argv[5])
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if len(sys.argv) >= 8:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(sys.argv[6]))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(sys.argv[7]))
    key = f"irtrack/{rig}/{board}/clock"
    counts = {"answered": 0, "malformed": 0}

    def answer(query):
        t2 = time.time_ns() + offset_ns
        payload = query.payload
        raw = payload.to_bytes() if payload is not None else b""
        if len(raw) != LAYOUT.size:
            counts["malformed"] += 1
            return
        magic, version, kind, reserved, probe_id, t1, _, _ = LAYOUT.unpack(raw)
        if magic != b"IRCK" or version != 1 or kind != 1 or reserved != 0:
            counts["malformed"] += 1
            return
        t3 = time.time_ns() + offset_ns
        query.reply(key, LAYOUT.pack(b"IRCK", 1, 2, 0, probe_id, t1, t2, t3))
        counts["answered"] += 1

    with zenoh.open(conf) as session:
        queryable = session.declare_queryable(key, answer)
        time.sleep(seconds)
        queryable.undeclare()
    print(json.dumps(counts), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
