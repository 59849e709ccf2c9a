"""Evaluation (DESIGN.md step 6): Chamfer distance of Gaussian centres to a ground-truth mesh,
PSNR/SSIM against ground-truth views, and the NIQE no-reference score."""

from .geometry import ChamferResult, MeshDistance, chamfer, point_mesh_distance_reference, read_mesh_ply

__all__ = ["ChamferResult", "MeshDistance", "chamfer", "point_mesh_distance_reference", "read_mesh_ply"]
