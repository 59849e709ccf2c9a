"""Which splat format a file holds, by its content, and reading or writing any of them.

The first bytes decide: "ply" and a header with a `chunk` element and `packed_position` vertices is
SuperSplat's compressed PLY, any other PLY the reference layout (`read_ply`); gzip (`1f 8b`) or
"NGSP" is .spz. Without a signature a file is a .splat when its extension says so, or when its size
is a whole number of 32-byte records whose first ones look like Gaussians; else a .ply goes to
`read_ply` (which says what is wrong with it), and anything else is refused.
"""

from __future__ import annotations

from pathlib import Path

from ..cloud import GaussianCloud
from ..ply import PlyError, read_header, read_ply, write_ply
from .compressed_ply import is_compressed_ply_header, read_compressed_ply, write_compressed_ply
from .splat import looks_like_splat, read_splat, write_splat
from .spz import GZIP_MAGIC, MAGIC, read_spz, write_spz

__all__ = ["FORMATS", "EXTENSIONS", "detect_format", "read_splat_file", "write_splat_file"]

#: What `detect_format` answers, with a description of each.
FORMATS = {
    "ply": "3DGS PLY (reference layout)",
    "compressed_ply": "compressed PLY (SuperSplat)",
    "spz": "Niantic .spz",
    "splat": ".splat (web viewers)",
}
#: File name extensions of the formats `read_splat_file` reads.
EXTENSIONS = (".ply", ".splat", ".spz")

_READERS = {"ply": read_ply, "compressed_ply": read_compressed_ply, "spz": read_spz, "splat": read_splat}


def detect_format(path) -> str:
    """One of FORMATS' keys for the file at `path`, from its content (PlyError when none fits)."""
    path = Path(path)
    where = str(path)
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(4096)
        if head.startswith((b"ply\n", b"ply\r\n")):
            f.seek(0)
            return "compressed_ply" if is_compressed_ply_header(read_header(f, where)) else "ply"
    if head.startswith(GZIP_MAGIC) or head.startswith(MAGIC):
        return "spz"
    if path.suffix.lower() == ".splat" or looks_like_splat(head, size):
        return "splat"
    if path.suffix.lower() == ".ply":
        return "ply"  # read_ply says what is wrong with it
    raise PlyError(f"{where}: not a splat file this reader knows: no PLY header, no .spz signature (gzip or "
                   f"'NGSP'), and not .splat records ({size} bytes"
                   + (")" if size % 32 else ", but the first records are not Gaussians)"))


def read_splat_file(path, *, sanitize: bool = False) -> GaussianCloud:
    """Read a 3DGS PLY, a compressed PLY, an .spz or a .splat file into a numpy GaussianCloud, the
    format found from the content (`detect_format`), with the SH degree the file has (0 for
    .splat). Bad or truncated files raise PlyError naming the file and the problem; rows with
    non-finite values raise it too unless `sanitize` drops them (with a warning)."""
    return _READERS[detect_format(path)](path, sanitize=sanitize)


def write_splat_file(cloud: GaussianCloud, path) -> Path:
    """Write `cloud` in the format its file name asks for: .spz (`write_spz`, version 3), .splat
    (`write_splat`), a name ending in .compressed.ply (`write_compressed_ply`), else the 3DGS PLY
    (`write_ply`). Atomic, like each of them."""
    name = Path(path).name.lower()
    if name.endswith(".spz"):
        return write_spz(cloud, path)
    if name.endswith(".splat"):
        return write_splat(cloud, path)
    if name.endswith(".compressed.ply"):
        return write_compressed_ply(cloud, path)
    return write_ply(cloud, path)
