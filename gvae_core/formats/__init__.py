"""The splat files people have, beside the reference 3DGS PLY (`gvae_core.ply`), with numpy alone.

One module per format, each reading into and writing from a `GaussianCloud` and documenting its
bytes and its quantisation: `splat` (the web viewers' .splat), `spz` (Niantic's .spz),
`compressed_ply` (SuperSplat's compressed PLY), `sog` (PlayCanvas's SOG: WebP images, with
`_quantize` for its codebooks and SH palette), `gltf` (Khronos's KHR_gaussian_splatting in .glb and
.gltf); `detect` finds a file's format from its content and reads or writes any of them. `_codec`
holds what they share. Errors are `PlyError`.
"""

from .compressed_ply import read_compressed_ply, write_compressed_ply
from .detect import EXTENSIONS, FORMATS, WRITE_NAMES, detect_format, output_format, read_splat_file, write_splat_file
from .gltf import read_gltf, write_gltf
from .sog import WebpCodec, read_sog, write_sog
from .splat import read_splat, write_splat
from .spz import read_spz, write_spz

__all__ = ["EXTENSIONS", "FORMATS", "WRITE_NAMES", "detect_format", "output_format", "read_splat_file",
           "write_splat_file", "read_splat", "write_splat", "read_spz", "write_spz", "read_compressed_ply",
           "write_compressed_ply", "read_sog", "write_sog", "WebpCodec", "read_gltf", "write_gltf"]
