"""Random byte edits of a file for the property tests of the readers (test_ply, test_formats)."""

import warnings

import numpy as np
from hypothesis import strategies as st

from gvae_core.ply import PlyError

#: Up to four edits: (kind, where in 0..1, a byte value that also picks sizes and the region).
EDITS = st.lists(st.tuples(st.sampled_from(["flip", "set", "cut", "insert", "delete"]),
                           st.floats(0, 1), st.integers(0, 255)), min_size=1, max_size=4)


def corrupt(data: bytes, ops, head_len: int) -> bytes:
    """`data` with `ops` (drawn from EDITS) applied; half of them land in the first `head_len`
    bytes (headers and signatures, where parsing is most delicate)."""
    data = bytearray(data)
    for op, where, value in ops:
        pos = int(where * (head_len if value % 2 else len(data))) % max(1, len(data))
        if not data and op in ("flip", "set"):
            continue
        if op == "flip":
            data[pos] ^= 1 << (value % 8)
        elif op == "set":
            data[pos] = value
        elif op == "cut":
            del data[pos:]
        elif op == "insert":
            data[pos:pos] = bytes([value]) * (1 + value % 3)
        else:
            del data[pos:pos + 1 + value % 5]
    return bytes(data)


def read_or_refuse(read, path) -> None:
    """`read(path)` of a corrupted file either raises PlyError naming the file or gives a cloud
    with only finite values (warnings about what it sanitised are expected)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            cloud = read(path)
        except PlyError as exc:
            assert str(path) in str(exc)
        else:
            assert all(np.isfinite(a).all() for a in cloud.arrays().values())
