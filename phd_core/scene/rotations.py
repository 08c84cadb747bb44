"""Rotations as unit quaternions (w, x, y, z): splat orientations, COLMAP poses and the
similarities between trainers' frames all convert through these."""

from __future__ import annotations

import torch


def quaternion_to_rotation(quats: torch.Tensor) -> torch.Tensor:
    """[G, 4] wxyz (any norm) -> [G, 3, 3]. A zero quaternion gives the identity."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


def rotation_to_quaternion(rotation: torch.Tensor) -> torch.Tensor:
    """[3, 3] rotation -> [4] float64 unit quaternion wxyz (Shepperd: from the largest of
    the trace and the diagonal, so no division by a small number)."""
    r = torch.as_tensor(rotation, dtype=torch.float64)
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    k = int(torch.argmax(torch.stack([trace, r[0, 0], r[1, 1], r[2, 2]])))
    if k == 0:
        s = 2 * (1 + trace).sqrt()
        q = [s / 4, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif k == 1:
        s = 2 * (1 + r[0, 0] - r[1, 1] - r[2, 2]).sqrt()
        q = [(r[2, 1] - r[1, 2]) / s, s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif k == 2:
        s = 2 * (1 + r[1, 1] - r[0, 0] - r[2, 2]).sqrt()
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s]
    else:
        s = 2 * (1 + r[2, 2] - r[0, 0] - r[1, 1]).sqrt()
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4]
    quaternion = torch.stack(q)
    return quaternion / quaternion.norm()


def quaternion_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b of wxyz quaternions [..., 4] (the rotation b, then a)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], dim=-1)
