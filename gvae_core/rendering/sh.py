"""Real spherical harmonics up to degree 3 (the constants of the reference 3DGS code) and the
view-dependent colour rule of DESIGN.md: SH(direction) + 0.5, clamped at 0."""

from __future__ import annotations

import torch

from ..conventions import SH_C0, SH_C1, SH_C2, SH_C3


def sh_basis(dirs: torch.Tensor, degree: int) -> list[torch.Tensor]:
    """(N,3) unit directions to the (degree+1)^2 real SH basis functions, each (N,), band-major."""
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2.0 * zz - xx - yy), SH_C2[3] * xz,
                SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [SH_C3[0] * y * (3.0 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4.0 * zz - xx - yy),
                SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy), SH_C3[4] * x * (4.0 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3.0 * yy)]
    return out


def sh_to_rgb(sh_dc: torch.Tensor, sh_rest: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Colour (N,3) of SH coefficients seen along unit `dirs` (N,3): Σ basis·coeff + 0.5, >= 0.

    sh_dc (N,3); sh_rest (N,K,3) with at least (degree+1)^2 - 1 coefficients (extra ones ignored)."""
    k = (degree + 1) ** 2 - 1
    rgb = sh_dc * SH_C0 + 0.5
    if k:
        basis = torch.stack(sh_basis(dirs, degree)[1:], 1)  # (N,k)
        rgb = rgb + torch.bmm(basis[:, None, :], sh_rest[:, :k])[:, 0]
    return rgb.clamp(min=0.0)
