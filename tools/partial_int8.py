#!/usr/bin/env python3
"""Rounds some of an f32 blob's weight matrices to their int8 values, keeping it f32.

usage: python3 tools/partial_int8.py IN.blob OUT.blob KINDS

KINDS is a comma-separated list of `wih` (the LSTM input matrices), `whh` (the recurrent
matrices), `mlp` (the MLP head's matrices) or `all`. Every row of a chosen matrix becomes
q * scale with scale = max|w| / 127 and q = round(w / scale), as `tools convert --dtype i8`
stores it (firmware_core::blob, "Payload (dtype I8)"); biases and the other matrices stay
exact, and OUT is an f32 blob with a fresh CRC. Racing OUT with `sitl eval` shows which
weights an int8 policy's losses come from (docs/RESULTS.md, the int8 section). Standard
library only; the layout is read with tools/read_blob.py.
"""
import array
import os
import struct
import sys
import zlib

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import read_blob  # noqa: E402


def f32(x):
    return struct.unpack("<f", struct.pack("<f", x))[0]


def main():
    if len(sys.argv) != 4:
        raise SystemExit(__doc__)
    src, dst, kinds = sys.argv[1], sys.argv[2], set(sys.argv[3].split(","))
    unknown = kinds - {"wih", "whh", "mlp", "all"}
    if unknown:
        raise SystemExit(f"unknown kinds {sorted(unknown)}; use wih, whh, mlp or all")
    header = read_blob.read(src)
    if header["dtype"] != "F32":
        raise SystemExit(f"{src}: an f32 blob is needed, this one is {header['dtype']}")
    blob = bytearray(open(src, "rb").read())
    _, header_len = struct.unpack_from("<HH", blob, 4)
    offset = (8 + header_len + 3) // 4 * 4
    end = offset + header["payload_len"]
    weights = array.array("f", bytes(blob[offset:end]))
    if sys.byteorder != "little":
        weights.byteswap()
    arch = header["architecture"]
    lstm_tensors = 3 * arch["lstm_layers"]
    at = 0
    for i, (rows, cols) in enumerate(read_blob.tensors(arch)):
        size = rows * max(cols, 1)
        kind = ["wih", "whh", "bias"][i % 3] if i < lstm_tensors else ("mlp" if cols else "bias")
        if cols and (kind in kinds or "all" in kinds):
            for r in range(rows):
                row = range(at + r * cols, at + (r + 1) * cols)
                scale = f32(max(abs(weights[j]) for j in row) / 127.0)
                if scale > 0.0:
                    for j in row:
                        weights[j] = f32(round(weights[j] / scale) * scale)
        at += size
    if sys.byteorder != "little":
        weights.byteswap()
    blob[offset:end] = weights.tobytes()
    struct.pack_into("<I", blob, end, zlib.crc32(bytes(blob[:end])))
    with open(dst, "wb") as f:
        f.write(blob)
    print(f"wrote {dst}: {sorted(kinds)} rounded to int8 values")


if __name__ == "__main__":
    main()
