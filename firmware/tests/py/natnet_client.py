"""Reads irtrackd's NatNet output with PyPI's `natnet` client (an independent implementation)
and prints what it decoded as one JSON document.

usage: natnet_client.py SERVER_IP COMMAND_PORT FRAMES TIMEOUT_S [multicast GROUP DATA_PORT]
"""
import json
import sys
import threading
import time

from natnet import NatNetClient

server, port, want, timeout = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
multicast = len(sys.argv) > 5 and sys.argv[5] == "multicast"
kwargs = dict(server_ip_address=server, local_ip_address="127.0.0.1", command_port=port,
              use_multicast=multicast)
if multicast:
    kwargs.update(multicast_address=sys.argv[6], data_port=int(sys.argv[7]))

frames, models = [], []
done = threading.Event()


def on_frame(f):
    if len(frames) < want:
        frames.append({
            "frame": f.prefix.frame_number,
            "timestamp": f.suffix.timestamp,
            "stamp_mid_exposure": f.suffix.stamp_camera_mid_exposure,
            "models_changed": f.suffix.tracked_models_changed,
            "marker_sets": [[m.model_name, [list(p) for p in m.marker_pos_list]] for m in f.marker_sets],
            "unlabeled": [list(p) for p in f.unlabeled_marker_pos],
            "rigid_bodies": [{"id": b.id_num, "pos": list(b.pos), "rot": list(b.rot),
                              "error": b.marker_error, "valid": b.tracking_valid}
                             for b in f.rigid_bodies],
            "labeled": [{"id": m.id_num, "pos": list(m.pos), "param": m.param,
                         "residual": m.residual} for m in f.labeled_markers],
        })
    if len(frames) >= want and models:
        done.set()


def on_models(d):
    models.append({
        "marker_sets": [[m.name, list(m.marker_names)] for m in d.marker_sets],
        "rigid_bodies": [{"name": b.name, "id": b.id_num, "parent": b.parent_id,
                          "markers": [list(m.pos) for m in b.markers]} for b in d.rigid_bodies],
    })
    if len(frames) >= want:
        done.set()


client = NatNetClient(**kwargs)
client.on_data_frame_received_event.handlers.append(on_frame)
client.on_data_description_received_event.handlers.append(on_models)
client.connect(timeout=timeout)
info = client.server_info
client.run_async()
client.request_modeldef()
ok = done.wait(timeout)
client.stop_async()
client.shutdown()
json.dump({
    "server": {"name": info.application_name, "version": str(info.server_version),
               "natnet": str(info.nat_net_protocol_version)},
    "models": models,
    "frames": frames,
    "complete": ok,
}, sys.stdout)
