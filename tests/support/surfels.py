"""Hand-made 2DGS models and PLY files in the 2DGS reference trainer's layout, written with
NumPy from the layout itself (not with `write_ply`), so the reader is checked against the
format, not against our own writer."""

from __future__ import annotations

import numpy as np
import torch

from phd_core.renderers.gs2d import SurfelModel


def random_surfels(count: int = 300, seed: int = 0, degree: int = 1, spread: float = 1.2) -> SurfelModel:
    """A random surfel cloud in [-spread/2, spread/2]^3, visible from the ring cameras of the tests."""
    g = torch.Generator().manual_seed(seed)
    return SurfelModel(
        means=(torch.rand(count, 3, generator=g) - 0.5) * spread,
        log_scales=torch.log(0.04 + 0.08 * torch.rand(count, 2, generator=g)),
        quats=torch.randn(count, 4, generator=g),
        opacity_logits=torch.rand(count, generator=g) * 4 - 1,
        sh=torch.randn(count, (degree + 1) ** 2, 3, generator=g) * 0.5,
    )


def reference_layout_ply(model: SurfelModel, *, fmt: str = "binary_little_endian", comments: int = 1) -> bytes:
    """`model` as the 2DGS reference trainer stores it: x y z nx ny nz f_dc_0..2 f_rest_*
    (channel-major) opacity scale_0 scale_1 rot_0..3, float32."""
    count, k = model.num_splats, model.sh.shape[1]
    sh = model.sh.detach().numpy()
    columns = {"x": model.means[:, 0], "y": model.means[:, 1], "z": model.means[:, 2]}
    columns |= {n: np.zeros(count) for n in ("nx", "ny", "nz")}
    columns |= {f"f_dc_{c}": sh[:, 0, c] for c in range(3)}
    columns |= {f"f_rest_{c * (k - 1) + j - 1}": sh[:, j, c] for c in range(3) for j in range(1, k)}
    columns["opacity"] = model.opacity_logits
    columns |= {f"scale_{i}": model.log_scales[:, i] for i in range(2)}
    columns |= {f"rot_{i}": model.quats[:, i] for i in range(4)}
    order = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
             *(f"f_rest_{i}" for i in range(3 * (k - 1))), "opacity", "scale_0", "scale_1",
             "rot_0", "rot_1", "rot_2", "rot_3"]
    header = ("ply\n" f"format {fmt} 1.0\n" + "comment 2DGS reference layout, made by hand\n" * comments
              + f"element vertex {count}\n" + "".join(f"property float {n}\n" for n in order) + "end_header\n")
    table = np.stack([np.asarray(columns[n], dtype=np.float32) for n in order], axis=1)   # [G, P]
    if fmt == "ascii":
        body = "".join(" ".join(f"{v:.9g}" for v in row) + "\n" for row in table).encode()
    else:
        body = table.astype(("<" if fmt == "binary_little_endian" else ">") + "f4").tobytes()
    return header.encode() + body
