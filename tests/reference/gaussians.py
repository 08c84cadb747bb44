"""An independent, slow, float64 per-pixel 3DGS renderer used only to check the fast one.

It shares no code with `phd_core.renderers.gs3d`: NumPy, explicit loops over pixels and
over splats in depth order, the model definition written out from the reference
rasteriser's equations.
"""

from __future__ import annotations

import math

import numpy as np

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396]
C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435]


def _rotation(q: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(q)
    if n == 0:
        return np.eye(3)
    w, x, y, z = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _sh_colour(sh: np.ndarray, d: np.ndarray) -> np.ndarray:
    x, y, z = d
    terms = [C0]
    if len(sh) > 1:
        terms += [-C1 * y, C1 * z, -C1 * x]
    if len(sh) > 4:
        terms += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * z * z - x * x - y * y), C2[3] * x * z,
                  C2[4] * (x * x - y * y)]
    if len(sh) > 9:
        terms += [C3[0] * y * (3 * x * x - y * y), C3[1] * x * y * z, C3[2] * y * (4 * z * z - x * x - y * y),
                  C3[3] * z * (2 * z * z - 3 * x * x - 3 * y * y), C3[4] * x * (4 * z * z - x * x - y * y),
                  C3[5] * z * (x * x - y * y), C3[6] * x * (x * x - 3 * y * y)]
    colour = sum(t * sh[k] for k, t in enumerate(terms)) + 0.5
    return np.maximum(colour, 0.0)


def render_reference(means, log_scales, quats, opacity_logits, sh, c2w_gl, fx, fy, cx, cy, width, height,
                     background, keep=None, near=0.2, per_splat=None, pixel_values=None):
    """Returns (rgb [H, W, 3], alpha [H, W], depth [H, W]) in float64.

    per_splat: a dict to fill with each splat's "weight" [G] (alpha * transmittance summed over
    the pixels) and "footprint" [G] (alpha >= 1/255 summed over the pixels, occlusion ignored);
    with pixel_values [H, W], also "valued" [G] (alpha * transmittance * the pixel's value summed)."""
    means = np.asarray(means, np.float64)
    g = len(means)
    keep = np.ones(g, bool) if keep is None else np.asarray(keep, bool)
    c2w = np.asarray(c2w_gl, np.float64) @ np.diag([1.0, -1.0, -1.0, 1.0])   # OpenGL -> OpenCV axes
    r_wc = c2w[:3, :3].T
    t_wc = -r_wc @ c2w[:3, 3]
    campos = c2w[:3, 3]
    splats = []
    for i in range(g):
        if not keep[i]:
            continue
        p = r_wc @ means[i] + t_wc
        if p[2] <= near:
            continue
        opacity = 1.0 / (1.0 + math.exp(-float(opacity_logits[i])))
        # EWA with the reference's clamp of the Jacobian's evaluation point.
        limx_p = (width - cx) / fx + 0.15 * width / fx
        limx_n = cx / fx + 0.15 * width / fx
        limy_p = (height - cy) / fy + 0.15 * height / fy
        limy_n = cy / fy + 0.15 * height / fy
        tx = min(max(p[0] / p[2], -limx_n), limx_p) * p[2]
        ty = min(max(p[1] / p[2], -limy_n), limy_p) * p[2]
        jac = np.array([[fx / p[2], 0, -fx * tx / p[2] ** 2], [0, fy / p[2], -fy * ty / p[2] ** 2]])
        rs = _rotation(np.asarray(quats[i], np.float64)) @ np.diag(np.exp(np.asarray(log_scales[i], np.float64)))
        cov = jac @ r_wc @ (rs @ rs.T) @ r_wc.T @ jac.T + 0.3 * np.eye(2)
        d = means[i] - campos
        colour = _sh_colour(np.asarray(sh[i], np.float64), d / np.linalg.norm(d))
        centre = np.array([fx * p[0] / p[2] + cx, fy * p[1] / p[2] + cy])
        splats.append((p[2], i, centre, np.linalg.inv(cov), opacity, colour))
    splats.sort(key=lambda s: (s[0], s[1]))
    weight, footprint, valued = np.zeros(g), np.zeros(g), np.zeros(g)
    rgb = np.zeros((height, width, 3))
    alpha_out = np.zeros((height, width))
    depth_out = np.zeros((height, width))
    for yy in range(height):
        for xx in range(width):
            pix = np.array([xx + 0.5, yy + 0.5])
            t = 1.0
            colour = np.zeros(3)
            depth = 0.0
            stopped = False
            for z, i, centre, conic, opacity, c in splats:
                dlt = pix - centre
                power = -0.5 * dlt @ conic @ dlt
                a = min(0.99, opacity * math.exp(min(power, 0.0)))
                if a < 1.0 / 255.0:
                    continue
                footprint[i] += a
                if stopped or t * (1 - a) < 1e-4:
                    stopped = True
                    continue
                weight[i] += a * t
                if pixel_values is not None:
                    valued[i] += a * t * float(pixel_values[yy][xx])
                colour += a * t * c
                depth += a * t * z
                t *= 1 - a
            rgb[yy, xx] = colour + t * np.asarray(background, np.float64)
            alpha_out[yy, xx] = 1 - t
            depth_out[yy, xx] = depth
    if per_splat is not None:
        per_splat.update(weight=weight, footprint=footprint, valued=valued)
    return rgb, alpha_out, depth_out
