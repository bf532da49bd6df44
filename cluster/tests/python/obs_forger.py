#!/usr/bin/env python3
"""A forged peer for the credentials tests (docs/cluster.md, "Credentials").

Uses PyPI's eclipse-zenoh (an independent Zenoh stack) to connect to the solver, with or
without user/password credentials, and puts COUNT payloads `forged-python-<tag>-<i>` on KEY,
one every 5 ms. Prints one JSON line: whether the session opened and how many puts Zenoh
accepted locally (a put to a peer that refused the link goes nowhere).

usage: obs_forger.py CONNECT_ENDPOINT KEY COUNT TAG [USER PASSWORD]
"""
import json
import sys
import time

import zenoh


def main() -> int:
    endpoint, key, count, tag = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if len(sys.argv) >= 7:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(sys.argv[5]))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(sys.argv[6]))
    try:
        session = zenoh.open(conf)
    except Exception as e:  # refused while opening: what the solver should do
        print(json.dumps({"opened": False, "error": str(e)}), flush=True)
        return 0
    put = 0
    with session:
        pub = session.declare_publisher(key)
        for i in range(count):
            try:
                pub.put(f"forged-python-{tag}-{i}".encode())
                put += 1
            except Exception:
                pass
            time.sleep(0.005)
        pub.undeclare()
    print(json.dumps({"opened": True, "put": put}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
