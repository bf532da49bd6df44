"""Golden NatNet 3.1 packets for firmware/src/outputs/natnet/wire.rs, written field by field
from docs/outputs.md with Python's struct module (independent of the Rust encoder).
Run: python3 firmware/tests/data/natnet_golden.py"""
import struct


def packet(msg_id, payload):
    return struct.pack("<HH", msg_id, len(payload)) + payload


def cstr(s):
    return s.encode() + b"\0"


def f3(v):
    return struct.pack("<3f", *v)


# NAT_SERVERINFO: irtrackd 0.1.0.0, unicast, data port 1510 (the command socket's).
server_info = packet(
    1,
    b"irtrackd".ljust(256, b"\0")
    + bytes([0, 1, 0, 0])
    + bytes([3, 1, 0, 0])
    + struct.pack("<QHB", 1_000_000_000, 1510, 0)
    + bytes([0, 0, 0, 0]),
)

# NAT_MODELDEF: tool "probe" (rigid body 1) with two LEDs.
leds = [(0.0, 0.0, 0.02), (0.1, 0.0, 0.02)]
model_def = packet(
    5,
    struct.pack("<i", 2)
    + struct.pack("<I", 0) + cstr("probe") + struct.pack("<i", 2) + cstr("probe_1") + cstr("probe_2")
    + struct.pack("<I", 1) + cstr("probe") + struct.pack("<Ii", 1, -1) + f3((0, 0, 0))
    + struct.pack("<i", 2) + f3(leds[0]) + f3(leds[1]) + struct.pack("<ii", 0, 0),
)

# NAT_FRAMEOFDATA: frame 42, the tool tracked at (0.1, 0.2, 1.0) m without rotation.
p = (0.1, 0.2, 1.0)
m = [(p[0] + l[0], p[1] + l[1], p[2] + l[2]) for l in leds]
capture = 1_000_000_000
frame = packet(
    7,
    struct.pack("<I", 42)
    + struct.pack("<i", 1) + cstr("probe") + struct.pack("<i", 2) + f3(m[0]) + f3(m[1])
    + struct.pack("<i", 0)  # unlabelled
    + struct.pack("<i", 1) + struct.pack("<I", 1) + f3(p) + struct.pack("<4f", 0, 0, 0, 1)
    + struct.pack("<fh", 0.0005, 1)
    + struct.pack("<i", 0)  # skeletons
    + struct.pack("<i", 2)
    + struct.pack("<I", (1 << 16) | 1) + f3(m[0]) + struct.pack("<fHf", 0.005, 0x0C, 0.0)
    + struct.pack("<I", (1 << 16) | 2) + f3(m[1]) + struct.pack("<fHf", 0.005, 0x0C, 0.0)
    + struct.pack("<ii", 0, 0)  # force plates, devices
    + struct.pack("<II", 0, 0)  # timecode
    + struct.pack("<d", capture / 1e9)
    + struct.pack("<QQQ", capture, capture + 2_000_000, capture + 2_500_000)
    + struct.pack("<h", 0)
    + struct.pack("<i", 0),
)

# The same frame with a loose LED (loose_id 4, ray gap 0.25 mm) at (0.3, -0.1, 0.9) m: in the
# legacy unlabelled list (NatNet 2 clients) and as labelled marker 5 of model 0 with the
# unlabelled and point-cloud-solved flags (NatNet 3+ clients skip the legacy list).
u = (0.3, -0.1, 0.9)
frame_loose = packet(
    7,
    struct.pack("<I", 42)
    + struct.pack("<i", 1) + cstr("probe") + struct.pack("<i", 2) + f3(m[0]) + f3(m[1])
    + struct.pack("<i", 1) + f3(u)  # unlabelled (legacy list)
    + struct.pack("<i", 1) + struct.pack("<I", 1) + f3(p) + struct.pack("<4f", 0, 0, 0, 1)
    + struct.pack("<fh", 0.0005, 1)
    + struct.pack("<i", 0)  # skeletons
    + struct.pack("<i", 3)
    + struct.pack("<I", (1 << 16) | 1) + f3(m[0]) + struct.pack("<fHf", 0.005, 0x0C, 0.0)
    + struct.pack("<I", (1 << 16) | 2) + f3(m[1]) + struct.pack("<fHf", 0.005, 0x0C, 0.0)
    + struct.pack("<I", (0 << 16) | 5) + f3(u) + struct.pack("<fHf", 0.005, 0x12, 0.00025)
    + struct.pack("<ii", 0, 0)  # force plates, devices
    + struct.pack("<II", 0, 0)  # timecode
    + struct.pack("<d", capture / 1e9)
    + struct.pack("<QQQ", capture, capture + 2_000_000, capture + 2_500_000)
    + struct.pack("<h", 0)
    + struct.pack("<i", 0),
)

for name, b in [("SERVER_INFO", server_info), ("MODEL_DEF", model_def), ("FRAME", frame),
                ("FRAME_LOOSE", frame_loose)]:
    print(f'const {name}: &str = "{b.hex()}";')
