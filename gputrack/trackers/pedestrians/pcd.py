"""Read a PCD file (Point Cloud Library's format) into NumPy, including ``binary_compressed`` (LZF).

Only what an organised depth-camera cloud needs: fields of 1-, 2-, 4- or 8-byte numbers with COUNT 1,
DATA ``ascii``, ``binary`` or ``binary_compressed``. :func:`read_pcd` returns a dict of field name ->
array, shaped (HEIGHT, WIDTH) for an organised cloud. :func:`lzf_decompress` is the LZF format
(liblzf) in pure Python: a control byte c < 32 starts a run of c + 1 literal bytes; otherwise the
back-reference of length (c >> 5) + 2 (c >> 5 == 7: plus the next byte) at distance
((c & 31) << 8) + next byte + 1.
"""

from __future__ import annotations

import numpy as np

__all__ = ["depth_from_cloud", "lzf_decompress", "read_pcd"]

_TYPES = {("F", 4): "<f4", ("F", 8): "<f8", ("U", 1): "u1", ("U", 2): "<u2", ("U", 4): "<u4", ("I", 1): "i1",
          ("I", 2): "<i2", ("I", 4): "<i4", ("U", 8): "<u8", ("I", 8): "<i8"}  # fmt: skip


def lzf_decompress(data: bytes, size: int) -> bytes:
    """LZF-decompress ``data`` to exactly ``size`` bytes (ValueError on a corrupt stream)."""
    out = bytearray(size)
    ip, op, n = 0, 0, len(data)
    while ip < n:
        c = data[ip]
        ip += 1
        if c < 32:  # literal run
            k = c + 1
            if ip + k > n or op + k > size:
                raise ValueError("LZF: expected a literal run inside the buffers, got a corrupt stream")
            out[op:op + k] = data[ip:ip + k]
            ip += k
            op += k
            continue
        k = c >> 5
        if k == 7:
            k += data[ip]
            ip += 1
        ref = op - ((c & 31) << 8) - data[ip] - 1
        ip += 1
        k += 2
        if ref < 0 or op + k > size:
            raise ValueError("LZF: expected a back-reference inside the output, got a corrupt stream")
        if ref + k <= op:
            out[op:op + k] = out[ref:ref + k]
        else:  # overlapping: byte by byte (a repeated pattern)
            for t in range(k):
                out[op + t] = out[ref + t]
        op += k
    if op != size:
        raise ValueError(f"LZF: expected {size} bytes, got {op}")
    return bytes(out)


def read_pcd(path: str) -> dict:
    """The fields of a PCD file: {name: array}, (HEIGHT, WIDTH) for an organised cloud."""
    with open(path, "rb") as fh:
        raw = fh.read()
    head, pos = {}, 0
    while True:
        end = raw.index(b"\n", pos)
        line = raw[pos:end].decode("ascii").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        head[key.upper()] = vals
        if key.upper() == "DATA":
            break
    names, sizes, types = head["FIELDS"], [int(s) for s in head["SIZE"]], head["TYPE"]
    counts = [int(c) for c in head.get("COUNT", ["1"] * len(names))]
    if any(c != 1 for c in counts):
        raise ValueError(f"{path}: expected COUNT 1 for every field, got {counts}")
    W, H = int(head["WIDTH"][0]), int(head["HEIGHT"][0])
    n = int(head["POINTS"][0])
    dts = [np.dtype(_TYPES[(t, s)]) for t, s in zip(types, sizes)]
    kind = head["DATA"][0].lower()
    if kind == "ascii":
        table = np.loadtxt(raw[pos:].decode("ascii").splitlines(), ndmin=2)
        cols = {k: table[:, i].astype(dt) for i, (k, dt) in enumerate(zip(names, dts))}
    elif kind == "binary":
        rec = np.frombuffer(raw, dtype=np.dtype(list(zip(names, dts))), count=n, offset=pos)
        cols = {k: rec[k].copy() for k in names}
    elif kind == "binary_compressed":
        csize, usize = np.frombuffer(raw, "<u4", 2, pos)
        buf = lzf_decompress(raw[pos + 8:pos + 8 + int(csize)], int(usize))
        cols, off = {}, 0
        for k, dt in zip(names, dts):  # field by field (structure of arrays)
            cols[k] = np.frombuffer(buf, dt, n, off).copy()
            off += dt.itemsize * n
    else:
        raise ValueError(f"{path}: expected DATA ascii, binary or binary_compressed, got {kind}")
    if H > 1 and H * W == n:
        cols = {k: v.reshape(H, W) for k, v in cols.items()}
    return cols


def depth_from_cloud(cloud: dict, scale: float = 1000.0) -> np.ndarray:
    """An organised cloud's z as a float32 depth image (in mm for a cloud in metres), 0 = no point."""
    z = np.asarray(cloud["z"], np.float64) * scale
    return np.where(np.isfinite(z) & (z > 0), z, 0.0).astype(np.float32)
