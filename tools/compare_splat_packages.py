"""Measure the PyPI splat codecs against gvae_core.formats on the same files (BENCHMARKS.md, "Splat
formats: own codecs or a package"). Not part of the project: run it in a throwaway venv.

    python3 -m venv build/pkgvenv
    build/pkgvenv/bin/pip install "numpy>=2" gsply==0.4.6 gaussforge==0.6.0 ply2splat==0.6.0 zstandard==0.25.0
    # alspz 0.2.0 (Cython bindings of Niantic's own C++ spz library) is an sdist only: it builds with g++,
    # zlib and libzstd-dev (apt), scikit-build-core and Cython, after two CMake fixes (link the system
    # libzstd; -fPIC for its object library): pip install --no-build-isolation ./alspz-0.2.0
    PYTHONPATH=. build/pkgvenv/bin/python tools/compare_splat_packages.py --n 1000000

Every row: the median read time of the same file, and the largest difference between what the package
decoded and what gvae_core decoded from that file (quaternions normalised and sign-aligned, opacity
after the sigmoid); then each encoder's error against the cloud it was given, and whether our .spz
payload is byte for byte Niantic's.
"""

from __future__ import annotations

import argparse
import gzip
import os
import statistics
import tempfile
import time
import warnings
from pathlib import Path

import alspz
import gaussforge
import gsply
import numpy as np
import ply2splat

from gvae_core.conventions import sigmoid
from gvae_core.examples import random_cloud
from gvae_core.formats import read_splat_file, write_compressed_ply, write_splat, write_spz
from gvae_core.formats.splat import RECORD
from gvae_core.ply import read_ply, write_ply
from gvae_core.quaternions import normalize


def timed(fn, repeats):
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def arrays_of_cloud(c):
    return {"means": c.means, "scales": c.scales, "quats": c.quats, "opacities": c.opacities, "dc": c.sh_dc,
            "sh": c.sh_rest}


def from_gsply(g):
    return {"means": g.means, "scales": g.scales, "quats": g.quats, "opacities": g.opacities, "dc": g.sh0,
            "sh": g.shN}


def from_alspz(d):
    n = d["num_points"]
    sh = d["sh"] if d["sh"] is not None else np.zeros((n, 0))
    return {"means": d["positions"], "scales": d["scales"], "quats": d["rotations"][:, [3, 0, 1, 2]],
            "opacities": d["alphas"], "dc": d["colors"], "sh": sh.reshape(n, -1, 3)}


def from_gaussforge(result, quat_order):
    if "error" in result:
        raise RuntimeError(result["error"])
    ir = result["data"]
    n = ir["numPoints"]
    f = lambda k: np.frombuffer(ir[k], np.float32)  # noqa: E731
    q = f("rotations").reshape(n, 4)
    sh = f("sh").reshape(n, -1, 3) if len(ir["sh"]) else np.zeros((n, 0, 3), np.float32)
    return {"means": f("positions").reshape(n, 3), "scales": f("scales").reshape(n, 3),
            "quats": q if quat_order == "wxyz" else q[:, [3, 0, 1, 2]], "opacities": f("alphas"),
            "dc": f("colors").reshape(n, 3), "sh": sh}


def from_splat_bytes(raw):
    rec = np.frombuffer(raw, RECORD)
    with np.errstate(divide="ignore"):
        a = rec["rgba"][:, 3] / 255.0
        return {"means": rec["position"], "scales": np.log(rec["scale"]),
                "quats": (rec["rot"].astype(np.float32) - 128) / 128,
                "opacities": np.log(np.clip(a, 1e-6, 1 - 1e-6) / (1 - np.clip(a, 1e-6, 1 - 1e-6))),
                "dc": (rec["rgba"][:, :3] / 255.0 - 0.5) / 0.28209479177387814, "sh": np.zeros((len(rec), 0, 3))}


def diff(a, b) -> dict:
    out = {}
    for k in a:
        x, y = np.asarray(a[k], np.float64), np.asarray(b[k], np.float64)
        if k == "quats":
            x, y = normalize(x), normalize(y)
            d = np.minimum(np.abs(x - y).max(1), np.abs(x + y).max(1))
        elif k == "opacities":
            d = np.abs(sigmoid(x) - sigmoid(y))
        elif x.shape != y.shape:
            out[k] = "shape"
            continue
        else:
            d = np.abs(x - y)
        out[k] = float(d.max(initial=0.0))
    return out


def show(d: dict) -> str:
    return ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in d.items())


def _files(tmp: Path) -> dict[str, Path]:
    """The files each encoder writes, by key."""
    return {k: tmp / name for k, name in [("ply", "ref.ply"), ("spz3", "ours3.spz"), ("spz4", "ours4.spz"),
                                          ("spz3_niantic", "niantic3.spz"), ("spz4_niantic", "niantic4.spz"),
                                          ("splat", "ours.splat"), ("splat_ply2splat", "ply2splat.splat"),
                                          ("cply", "ours.compressed.ply"), ("cply_gaussforge", "gf.compressed.ply"),
                                          ("spz3_gsply", "gsply3.spz")]}


def _encode(cloud, f: dict[str, Path], gf, n: int) -> None:
    """Write every file; print each encoder's time and error against the source cloud."""
    source = arrays_of_cloud(cloud)
    print("\n| encoder | time (s) | max error against the source cloud |\n|---|---:|---|")
    write_ply(cloud, f["ply"])
    enc = [("gvae_core write_spz v3", lambda: write_spz(cloud, f["spz3"]), "spz3"),
           ("gvae_core write_spz v4", lambda: write_spz(cloud, f["spz4"], version=4), "spz4"),
           ("alspz (Niantic C++) v3", lambda: f["spz3_niantic"].write_bytes(alspz.save_spz(
               cloud.means, cloud.scales, cloud.quats[:, [1, 2, 3, 0]], cloud.opacities, cloud.sh_dc,
               cloud.sh_rest.reshape(n, -1), 3, version=3)), "spz3_niantic"),
           ("alspz (Niantic C++) v4", lambda: f["spz4_niantic"].write_bytes(alspz.save_spz(
               cloud.means, cloud.scales, cloud.quats[:, [1, 2, 3, 0]], cloud.opacities, cloud.sh_dc,
               cloud.sh_rest.reshape(n, -1), 3, version=4)), "spz4_niantic"),
           ("gsply write_spz v3", lambda: gsply.write_spz(f["spz3_gsply"], gsply.plyread(f["ply"]), version=3),
            "spz3_gsply"),
           ("gvae_core write_splat", lambda: write_splat(cloud, f["splat"]), "splat"),
           ("ply2splat convert (sort=False)", lambda: ply2splat.convert(str(f["ply"]), str(f["splat_ply2splat"]),
                                                                        sort=False), "splat_ply2splat"),
           ("gvae_core write_compressed_ply", lambda: write_compressed_ply(cloud, f["cply"]), "cply"),
           ("gaussforge ply -> compressed.ply", lambda: f["cply_gaussforge"].write_bytes(
               gf.convert(f["ply"].read_bytes(), "ply", "compressed.ply")["data"]), "cply_gaussforge")]
    for name, fn, key in enc:
        t, _ = timed(fn, 1)
        back = arrays_of_cloud(read_splat_file(f[key]))
        print(f"| {name} | {t:.2f} | {show(diff(source, back))} |")


def _readers(gf) -> dict[str, list]:
    """Per format, (name, read) of every reader; gvae_core's first."""
    return {
        "ply": [("gvae_core read_ply", lambda p: arrays_of_cloud(read_ply(p))),
                ("gsply plyread", lambda p: from_gsply(gsply.plyread(p))),
                ("gaussforge read", lambda p: from_gaussforge(gf.read(p.read_bytes(), "ply"), "wxyz"))],
        "spz3": [("gvae_core read_splat_file", lambda p: arrays_of_cloud(read_splat_file(p))),
                 ("gsply read_spz", lambda p: from_gsply(gsply.read_spz(p))),
                 ("alspz load_spz (Niantic C++)", lambda p: from_alspz(alspz.load_spz(p.read_bytes()))),
                 ("gaussforge read", lambda p: from_gaussforge(gf.read(p.read_bytes(), "spz"), "wxyz"))],
        "spz4": [("gvae_core read_splat_file", lambda p: arrays_of_cloud(read_splat_file(p))),
                 ("gsply read_spz", lambda p: from_gsply(gsply.read_spz(p))),
                 ("alspz load_spz (Niantic C++)", lambda p: from_alspz(alspz.load_spz(p.read_bytes())))],
        "splat": [("gvae_core read_splat_file", lambda p: arrays_of_cloud(read_splat_file(p))),
                  ("ply2splat load_splat_file",
                   lambda p: from_splat_bytes(ply2splat.load_splat_file(str(p)).to_bytes())),
                  ("gaussforge read", lambda p: from_gaussforge(gf.read(p.read_bytes(), "splat"), "wxyz"))],
        "cply": [("gvae_core read_splat_file", lambda p: arrays_of_cloud(read_splat_file(p))),
                 ("gsply plyread", lambda p: from_gsply(gsply.plyread(p))),
                 ("gaussforge read", lambda p: from_gaussforge(gf.read(p.read_bytes(), "compressed.ply"),
                                                               "wxyz"))],
    }


def _read(f: dict[str, Path], gf, repeats: int) -> None:
    """Print every reader on the same files, against gvae_core's decode of that file."""
    print("\n| file | reader | time (s) | x gvae_core | max difference from gvae_core's decode |")
    print("|---|---|---:|---:|---|")
    readers = _readers(gf)
    files = {"ply": ["ply"], "spz3": ["spz3", "spz3_niantic"], "spz4": ["spz4", "spz4_niantic"],
             "splat": ["splat", "splat_ply2splat"], "cply": ["cply", "cply_gaussforge"]}
    for fmt, keys in files.items():
        for key in keys:
            ours_t, ours = timed(lambda k=key, r=readers[fmt][0][1]: r(f[k]), repeats)
            for name, fn in readers[fmt]:
                try:
                    t, got = timed(lambda k=key, fn=fn: fn(f[k]), repeats)
                except Exception as exc:  # a package that cannot read the file: say so
                    print(f"| {key} | {name} | - | - | fails: {str(exc)[:80]} |")
                    continue
                print(f"| {key} | {name} | {t:.3f} | {t / ours_t:.2f} | {show(diff(ours, got))} |")


def _payloads(cloud, f: dict[str, Path], tmp: Path) -> None:
    """Print whether our .spz payload (and gzip file at level 6) is Niantic's, byte for byte."""
    ours = gzip.decompress(f["spz3"].read_bytes())
    theirs = gzip.decompress(f["spz3_niantic"].read_bytes())
    same = np.frombuffer(ours, np.uint8) == np.frombuffer(theirs, np.uint8) if len(ours) == len(theirs) else None
    print(f"\nspz v3 payload, ours vs Niantic's: {len(ours)} vs {len(theirs)} bytes, "
          + (f"{int((~same).sum())} differ" if same is not None else "lengths differ"))
    write_spz(cloud, tmp / "level6.spz", compresslevel=6)
    same_file = (tmp / "level6.spz").read_bytes() == f["spz3_niantic"].read_bytes()
    print("gzip file at level 6 identical to Niantic's:", same_file)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    cloud = random_cloud(args.n)
    cloud.sh_dc[:] = np.clip(cloud.sh_dc, -1.7, 1.7)  # inside every format's colour range
    tmp = Path(tempfile.mkdtemp())
    gf = gaussforge.GaussForge()
    print(f"{args.n} Gaussians, SH degree 3, median of {args.repeats}; load average {os.getloadavg()[0]:.2f}")
    f = _files(tmp)
    _encode(cloud, f, gf, args.n)
    _read(f, gf, args.repeats)
    _payloads(cloud, f, tmp)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
