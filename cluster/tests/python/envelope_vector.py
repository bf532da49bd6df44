#!/usr/bin/env python3
"""The golden credential envelope of cluster/tests/envelope.rs, built independently of the
Rust code with the Python `cryptography` package (X25519, HKDF-SHA256, ChaCha20-Poly1305,
Ed25519) from the layout in docs/cluster-envelope.md. Prints the envelope as hex.

    python3 cluster/tests/python/envelope_vector.py
"""
import hashlib
import struct

from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey
from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

RAW = serialization.Encoding.Raw, serialization.PublicFormat.Raw

signer = Ed25519PrivateKey.from_private_bytes(bytes([0x11]) * 32)
board = X25519PrivateKey.from_private_bytes(bytes([0x22]) * 32)
eph = X25519PrivateKey.from_private_bytes(bytes([0x33]) * 32)
nonce = bytes([0x44]) * 12
plaintext = b"b0-pw-7Tq2Lm9Xz4Kc8Vn1Rb5W\n"

recipient = board.public_key().public_bytes(*RAW)
eph_pub = eph.public_key().public_bytes(*RAW)
shared = eph.exchange(board.public_key())
key = HKDF(
    algorithm=hashes.SHA256(),
    length=32,
    salt=b"irtrack-cluster-credentials-v1",
    info=eph_pub + recipient,
).derive(shared)

name = b"b0"
header = (
    b"IRCK"
    + bytes([1, 1, len(name)])
    + name
    + struct.pack("<QQ", 7, 1795000000)
    + recipient
    + eph_pub
    + nonce
    + struct.pack("<I", len(plaintext) + 16)
)
ct = ChaCha20Poly1305(key).encrypt(nonce, plaintext, header)
signer_pub = signer.public_key().public_bytes(*RAW)
key_id = hashlib.sha512(signer_pub).digest()[:8]
signed = header + ct + key_id
envelope = signed + signer.sign(signed)
print(envelope.hex())
