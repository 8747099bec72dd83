#!/usr/bin/env python3
"""Reads an Overtake weight blob using only its documentation (firmware-core/src/blob/mod.rs).

Prints the header and a summary of the weights as JSON. No dependencies beyond the Python
standard library: a check that the format doc is enough to write a reader in another language.

usage: python3 tools/read_blob.py FILE
"""
import json
import struct
import sys
import zlib


class Reader:
    def __init__(self, data):
        self.data, self.at = data, 0

    def byte(self):
        b = self.data[self.at]
        self.at += 1
        return b

    def varint(self):  # LEB128, unsigned
        shift, value = 0, 0
        while True:
            b = self.byte()
            value |= (b & 0x7F) << shift
            shift += 7
            if not b & 0x80:
                return value

    def f32(self):
        (v,) = struct.unpack_from("<f", self.data, self.at)
        self.at += 4
        return v

    def string(self):
        n = self.varint()
        s = self.data[self.at:self.at + n].decode("utf-8")
        self.at += n
        return s


def tensors(arch):
    """(rows, cols) of every tensor in payload order; cols 0 for a bias."""
    h, inp, out = arch["lstm_hidden"], arch["obs_dim"], []
    for _ in range(arch["lstm_layers"]):
        out += [(4 * h, inp), (4 * h, h), (4 * h, 0)]
        inp = h
    for w in arch["mlp_hidden"] + [arch["action_dim"]]:
        out += [(w, inp), (w, 0)]
        inp = w
    return out


def f32(x):
    """x rounded to the nearest f32 (a product of an f32 and an int8 is exact in a double)."""
    return struct.unpack("<f", struct.pack("<f", x))[0]


def dequantize(arch, payload):
    """The I8 payload's weights as scale * q, tensor by tensor (biases are f32)."""
    at, weights = 0, []
    for rows, cols in tensors(arch):
        if cols == 0:
            weights += struct.unpack_from(f"<{rows}f", payload, at)
            at += 4 * rows
            continue
        scales = struct.unpack_from(f"<{rows}f", payload, at)
        at += 4 * rows
        stride = (cols + 3) // 4 * 4
        for s in scales:
            q = struct.unpack_from(f"<{cols}b", payload, at)
            weights += [f32(v * s) for v in q]
            at += stride
    if at != len(payload):
        raise SystemExit("int8 payload size mismatch")
    return weights


def read(path):
    blob = open(path, "rb").read()
    if blob[:4] != b"OVTK":
        raise SystemExit("bad magic")
    version, header_len = struct.unpack_from("<HH", blob, 4)
    if version != 1:
        raise SystemExit(f"unsupported version {version}")
    r = Reader(blob[8:8 + header_len])
    arch = {
        "obs_dim": r.varint(),
        "lstm_layers": r.byte(),
        "lstm_hidden": r.varint(),
        "mlp_hidden": [r.varint() for _ in range(r.varint())],
        "action_dim": r.byte(),
        "activation": ["Tanh"][r.varint()],
    }
    obs = {
        "version": r.varint(),
        "layout": ["TimeTrial17", "OpponentPosition20", "FullOpponent30"][r.varint()],
        "scales": [r.f32() for _ in range(7)],
    }
    action_map = {"hover_rpm": r.f32(), "gain": r.f32()}
    control_period_ns = r.varint()
    dtype = ["F32", "I8"][r.varint()]
    provenance = {
        "name": r.string(),
        "seed": r.varint(),
        "iterations": r.varint(),
        "preset": r.string(),
        "config_hash": r.varint(),
    }
    payload_len = r.varint()
    if r.at != header_len:
        raise SystemExit("header length mismatch")
    offset = (8 + header_len + 3) // 4 * 4
    end = offset + payload_len
    (stored,) = struct.unpack_from("<I", blob, end)
    if zlib.crc32(blob[:end]) != stored:
        raise SystemExit("CRC mismatch")
    if dtype == "F32":
        weights = struct.unpack_from(f"<{payload_len // 4}f", blob, offset)
    else:
        weights = dequantize(arch, blob[offset:end])
    return {
        "architecture": arch,
        "observation": obs,
        "action_map": action_map,
        "control_period_ns": control_period_ns,
        "dtype": dtype,
        "provenance": provenance,
        "payload_len": payload_len,
        "weights": {"count": len(weights), "first": weights[:4], "last": weights[-4:], "sum": sum(weights)},
    }


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    print(json.dumps(read(sys.argv[1])))
