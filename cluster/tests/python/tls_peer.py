#!/usr/bin/env python3
"""An independent TLS stack (Python's ssl module, i.e. OpenSSL) on either side of irtrackd's
TLS tunnels (irtrack_cluster::tls, docs/cluster.md "TLS").

client PORT TRUSTED_CERT
    Connects to 127.0.0.1:PORT as a camera board would: TLS 1.3 only, trusting TRUSTED_CERT
    alone, checking the name irtrack-solver. Prints one JSON line: whether the handshake
    succeeded, the version and cipher, or the error.

server PORT CERT KEY SECONDS
    Listens on 127.0.0.1:PORT with CERT/KEY (TLS 1.3), as a solver (or an impostor) would,
    for SECONDS seconds. Prints "listening" once ready, then one JSON line: handshakes that
    succeeded, failed, and the decrypted bytes received.
"""
import json
import socket
import ssl
import sys
import time


def client(port: int, trusted: str) -> int:
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_3
    ctx.load_verify_locations(cafile=trusted)
    out = {"ok": False}
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=5) as raw:
            with ctx.wrap_socket(raw, server_hostname="irtrack-solver") as tls:
                out = {"ok": True, "version": tls.version(), "cipher": tls.cipher()[0]}
    except (ssl.SSLError, OSError) as e:
        out = {"ok": False, "error": f"{type(e).__name__}: {e}"}
    print(json.dumps(out), flush=True)
    return 0


def server(port: int, cert: str, key: str, seconds: float) -> int:
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_3
    ctx.load_cert_chain(cert, key)
    lsock = socket.create_server(("127.0.0.1", port))
    lsock.settimeout(0.2)
    print("listening", flush=True)
    done = {"handshakes": 0, "failed": 0, "bytes": 0, "errors": []}
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            raw, _ = lsock.accept()
        except socket.timeout:
            continue
        raw.settimeout(1.0)
        try:
            tls = ctx.wrap_socket(raw, server_side=True)
        except (ssl.SSLError, OSError) as e:
            done["failed"] += 1
            if len(done["errors"]) < 3:
                done["errors"].append(f"{type(e).__name__}: {e}")
            raw.close()
            continue
        done["handshakes"] += 1
        try:
            data = tls.recv(4096)
            done["bytes"] += len(data)
        except (ssl.SSLError, OSError):
            pass
        tls.close()
    print(json.dumps(done), flush=True)
    return 0


def main() -> int:
    if sys.argv[1] == "client":
        return client(int(sys.argv[2]), sys.argv[3])
    return server(int(sys.argv[2]), sys.argv[3], sys.argv[4], float(sys.argv[5]))


if __name__ == "__main__":
    sys.exit(main())
