"""A benchmark scene's training images as a real capture could have them (the report's fault rows):
the cameras a little off (`pose_px`: every training camera turned by a random rotation that moves
its image by that many pixels at the training resolution), the exposure changing from image to
image (`exposure`: each image's colour times a factor drawn from 1 +- that share), or the images
made smaller with another filter than the area average (`filter`: bicubic or Lanczos).

`faulted_scene` writes a NeRF-Synthetic folder whose training split is the scene's training images
at the training height with the fault (8-bit PNGs, as a capture's are) and whose test split is the
scene's own (exact cameras, full-size images, the mesh beside them): train on it, refine from its
training images, score on its test views. The fault-free control ("none") goes through the same
8-bit images at the training height. Cached under `cache_dir()/faults`.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from ..camera import Camera
from ..capture import load_nerf_synthetic
from ..capture.transforms import read_transforms_file
from . import cache_dir

__all__ = ["Fault", "FAULTS", "faulted_scene"]

_FILTERS = {"area": None, "bicubic": Image.Resampling.BICUBIC, "lanczos": Image.Resampling.LANCZOS}


@dataclass(frozen=True)
class Fault:
    """What is wrong with a capture's training images (module docstring)."""

    name: str
    pose_px: float = 0.0
    exposure: float = 0.0
    filter: str = "area"


FAULTS: dict[str, Fault] = {f.name: f for f in [
    Fault("none"),
    Fault("pose 0.1 px", pose_px=0.1),
    Fault("pose 0.25 px", pose_px=0.25),
    Fault("pose 0.5 px", pose_px=0.5),
    Fault("exposure 10%", exposure=0.1),
    Fault("bicubic", filter="bicubic"),
    Fault("lanczos", filter="lanczos"),
]}


def _rotation(omega: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation by the vector `omega` (radians)."""
    angle = float(np.linalg.norm(omega))
    if angle < 1e-15:
        return np.eye(3)
    k = omega / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * kx @ kx


def _resize(rgba: np.ndarray, height: int, width: int, resample) -> np.ndarray:
    """Straight RGBA resized in premultiplied space with a PIL filter, channel by channel in float."""
    alpha = rgba[..., 3:4]
    premult = np.concatenate([rgba[..., :3] * alpha, alpha], -1).astype(np.float32)
    out = np.stack([np.asarray(Image.fromarray(premult[..., c], mode="F").resize((width, height), resample))
                    for c in range(4)], -1)
    a = np.clip(out[..., 3:4], 0.0, 1.0)
    rgb = np.where(a > 0, out[..., :3] / np.where(a > 0, a, 1.0), 0.0)
    return np.concatenate([np.clip(rgb, 0.0, 1.0), a], -1)


def faulted_scene(scene_dir, fault: Fault | str, height: int, *, seed: int = 0, cache=None) -> Path:
    """The scene at `scene_dir` with `fault` (a `Fault` or a name in FAULTS) in its training images
    at `height` px (module docstring); the random draws from `seed`. Returns the folder (cached)."""
    fault = FAULTS[fault] if isinstance(fault, str) else fault
    if fault.filter not in _FILTERS:
        raise ValueError(f"faults: filter must be one of {', '.join(_FILTERS)}, got {fault.filter!r}")
    scene_dir = Path(scene_dir)
    tag = "".join(ch if ch.isalnum() else "-" for ch in fault.name)
    final = cache_dir(cache) / "faults" / f"{scene_dir.name}-{tag}-h{int(height)}-s{int(seed)}"
    if (final / "fault.json").is_file():
        return final
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", dir=final.parent))
    try:
        _write(scene_dir, fault, int(height), int(seed), tmp)
        if not final.exists():
            os.replace(tmp, final)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return final


def _write(scene_dir: Path, fault: Fault, height: int, seed: int, out: Path) -> None:
    rng = np.random.default_rng([seed, 33])
    meta, frames = read_transforms_file(scene_dir / "transforms_train.json")
    full = load_nerf_synthetic(scene_dir, "train")  # the stored images, straight RGBA
    resample = _FILTERS[fault.filter]
    source = full if resample is not None else full.at_resolution(height)  # (area: the datasets' own resize)
    rgba_all = np.concatenate([source.images, source.alphas[..., None]], -1)
    (out / "train").mkdir()
    new_frames = []
    for i, (frame, cam) in enumerate(zip(frames, full.cameras)):
        small = cam.scaled(height)
        rgba = rgba_all[i] if resample is None else _resize(rgba_all[i], small.height, small.width, resample)
        if fault.exposure:
            rgba[..., :3] = np.clip(rgba[..., :3] * rng.uniform(1.0 - fault.exposure, 1.0 + fault.exposure), 0.0, 1.0)
        name = f"train/{i:03d}.png"
        Image.fromarray(np.round(rgba * 255.0).astype(np.uint8), "RGBA").save(out / name)
        c2w = np.asarray(frame["transform_matrix"], np.float64)
        if fault.pose_px:
            direction = rng.normal(size=2)
            direction /= np.linalg.norm(direction)
            omega = np.array([direction[0], direction[1], 0.0]) * fault.pose_px / max(small.fx, small.fy)
            w2c = cam.world_to_cam.copy()
            w2c[:3] = _rotation(omega) @ w2c[:3]  # turned about its own centre, in its own frame
            c2w = Camera(w2c, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height).to_blender_c2w()
        new_frames.append({**frame, "file_path": name, "transform_matrix": c2w.tolist()})
    (out / "transforms_train.json").write_text(json.dumps({**meta, "frames": new_frames}, indent=1))
    test_meta, test_frames = read_transforms_file(scene_dir / "transforms_test.json")
    test = [{**f, "file_path": str((scene_dir / f["file_path"]).resolve())} for f in test_frames]
    (out / "transforms_test.json").write_text(json.dumps({**test_meta, "frames": test}, indent=1))
    for extra in ("mesh.ply", "gt_points.npy"):
        if (scene_dir / extra).exists():
            os.symlink((scene_dir / extra).resolve(), out / extra)
    (out / "fault.json").write_text(json.dumps({"scene": str(scene_dir), "fault": asdict(fault), "height": height,
                                                "seed": seed}, indent=1))
