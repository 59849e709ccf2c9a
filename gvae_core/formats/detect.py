"""Which splat format a file holds, by its content, and reading or writing any of them.

The first bytes decide: "ply" and a header with a `chunk` element and `packed_position` vertices is
SuperSplat's compressed PLY, any other PLY the reference layout (`read_ply`); gzip (`1f 8b`) or
"NGSP" is .spz; a file named .splat is a .splat; "glTF" is a .glb, and a JSON object naming glTF's
`asset` (or any JSON object named .gltf) a .gltf; a zip (`PK`), another JSON object or a folder holding
`meta.json` is a SOG scene; a file without a signature is a .splat when its size is a whole number
of 32-byte records whose first ones look like Gaussians; else a .ply goes to `read_ply` (which says
what is wrong with it), and anything else is refused. Writing goes by the file name
(`output_format`), which must be one of WRITE_NAMES.
"""

from __future__ import annotations

from pathlib import Path

from ..cloud import GaussianCloud
from ..ply import PlyError, read_header, read_ply, write_ply
from .compressed_ply import is_compressed_ply_header, read_compressed_ply, write_compressed_ply
from .gltf import is_gltf_name, looks_like_gltf, read_gltf, write_gltf
from .splat import looks_like_splat, read_splat, write_splat
from .sog import WebpCodec, is_sog_name, looks_like_sog, read_sog, write_sog
from .spz import GZIP_MAGIC, MAGIC, WRITE_VERSION, read_spz, write_spz

__all__ = ["FORMATS", "EXTENSIONS", "WRITE_NAMES", "detect_format", "output_format", "read_splat_file",
           "write_splat_file"]

#: What `detect_format` answers, with a description of each.
FORMATS = {
    "ply": "3DGS PLY (reference layout)",
    "compressed_ply": "compressed PLY (SuperSplat)",
    "spz": "Niantic .spz",
    "splat": ".splat (web viewers)",
    "sog": "SOG (PlayCanvas, SuperSplat)",
    "gltf": "glTF 2.0 (KHR_gaussian_splatting)",
}
#: File name extensions of the formats `read_splat_file` reads (a SOG scene also as its meta.json).
EXTENSIONS = (".ply", ".splat", ".spz", ".sog", ".glb", ".gltf")
#: The names `write_splat_file` writes, by how they end, and the format of each.
WRITE_NAMES = {".compressed.ply": "compressed_ply", ".ply": "ply", ".spz": "spz", ".splat": "splat",
               ".sog": "sog", "meta.json": "sog", ".glb": "gltf", ".gltf": "gltf"}

_READERS = {"ply": read_ply, "compressed_ply": read_compressed_ply, "spz": read_spz, "splat": read_splat,
            "gltf": read_gltf}


def detect_format(path) -> str:
    """One of FORMATS' keys for the file at `path`, from its content (PlyError when none fits)."""
    path = Path(path)
    where = str(path)
    if path.is_dir():
        if looks_like_sog(path, b""):
            return "sog"
        raise PlyError(f"{where}: a folder without a SOG scene's meta.json")
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(4096)
        if head.startswith((b"ply\n", b"ply\r\n")):
            f.seek(0)
            return "compressed_ply" if is_compressed_ply_header(read_header(f, where)) else "ply"
    if head.startswith(GZIP_MAGIC) or head.startswith(MAGIC):
        return "spz"
    if path.suffix.lower() == ".splat":
        return "splat"
    if looks_like_gltf(path, head):
        return "gltf"
    if looks_like_sog(path, head):
        return "sog"
    if looks_like_splat(head, size):
        return "splat"
    if path.suffix.lower() == ".ply":
        return "ply"  # read_ply says what is wrong with it
    raise PlyError(f"{where}: not a splat file this reader knows: no PLY header, no .spz signature (gzip or "
                   f"'NGSP'), not glTF, not a SOG scene (zip or meta.json), and not .splat records ({size} bytes"
                   + (")" if size % 32 else ", but the first records are not Gaussians)"))


def read_splat_file(path, *, sanitize: bool = False, webp: WebpCodec | None = None) -> GaussianCloud:
    """Read a 3DGS PLY, a compressed PLY, an .spz, a .splat, a SOG scene (.sog, meta.json or its
    folder) or the splats of a glTF file (.glb, .gltf) into a numpy GaussianCloud, the format found
    from the content (`detect_format`), with the SH degree the file has (0 for .splat). Bad or
    truncated files raise PlyError naming the file and the problem; infinite opacities and -inf
    log-scales are read as what they mean, other non-finite values raise PlyError too unless
    `sanitize` drops those rows (`ply.drop_nonfinite`). `webp` decodes a SOG scene's images
    (default: Pillow's)."""
    fmt = detect_format(path)
    if fmt == "sog":
        return read_sog(path, sanitize=sanitize, webp=webp)
    return _READERS[fmt](path, sanitize=sanitize)


def output_format(path) -> str:
    """The format (a FORMATS key) that `write_splat_file` writes for this file name; PlyError for a
    name it cannot write, listing the ones it can."""
    name = Path(path).name.lower()
    if is_sog_name(name):
        return "sog"
    if is_gltf_name(name):
        return "gltf"
    for ending, fmt in WRITE_NAMES.items():
        if name.endswith(ending) and fmt not in ("sog", "gltf"):
            return fmt
    raise PlyError(f"{path}: cannot tell which splat format to write from the name; use one ending in "
                   + ", ".join(WRITE_NAMES))


def write_splat_file(cloud: GaussianCloud, path, *, spz_version: int = WRITE_VERSION,
                     webp: WebpCodec | None = None) -> Path:
    """Write `cloud` in the format its file name asks for (`output_format`): .ply (`write_ply`), a
    name ending in .compressed.ply (`write_compressed_ply`), .spz (`write_spz`, `spz_version`),
    .splat (`write_splat`), .sog or meta.json (`write_sog`, images through `webp`), .glb or .gltf
    (`write_gltf`). A name it cannot
    write raises PlyError before any file is touched. Atomic, like each of them."""
    fmt = output_format(path)
    if fmt == "spz":
        return write_spz(cloud, path, version=spz_version)
    if fmt == "sog":
        return write_sog(cloud, path, webp=webp)
    return {"ply": write_ply, "compressed_ply": write_compressed_ply, "splat": write_splat,
            "gltf": write_gltf}[fmt](cloud, path)
