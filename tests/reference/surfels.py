"""An independent, slow, float64 per-pixel 2DGS renderer used only to check the fast one.

It shares no code with `phd_core.renderers.gs2d`: NumPy, explicit loops over pixels and over
surfels in depth order, and a different route to the same maths. Where the fast renderer
solves for (u, v) with homogeneous planes in screen space, this one casts the pixel's ray in
world space, intersects it with the surfel's plane (t = n.(p - o) / n.d) and reads (u, v)
off the tangent axes. The rest is written out from the 2DGS definition: Gaussian
exp(-(u^2 + v^2) / 2) on the surfel, screen-space low-pass exp(-|x - c|^2) (sigma =
sqrt(2)/2 px) where larger, the 3DGS compositing rules, and pairwise sums for the
depth distortion.
"""

from __future__ import annotations

import math

import numpy as np
from reference.gaussians import _rotation, _sh_colour


def render_surfels_reference(means, log_scales, quats, opacity_logits, sh, c2w_gl, fx, fy, cx, cy, width, height,
                             background, keep=None, near=0.2):
    """Returns (rgb [H, W, 3], alpha [H, W], depth [H, W], normal [H, W, 3], distortion [H, W])."""
    means = np.asarray(means, np.float64)
    g = len(means)
    keep = np.ones(g, bool) if keep is None else np.asarray(keep, bool)
    c2w = np.asarray(c2w_gl, np.float64) @ np.diag([1.0, -1.0, -1.0, 1.0])   # OpenGL -> OpenCV axes
    r_cw, origin = c2w[:3, :3], c2w[:3, 3]
    r_wc = r_cw.T
    surfels = []
    for i in range(g):
        if not keep[i]:
            continue
        p_cam = r_wc @ (means[i] - origin)
        if p_cam[2] <= near:
            continue
        rot = _rotation(np.asarray(quats[i], np.float64))
        scales = np.exp(np.clip(np.asarray(log_scales[i], np.float64), -30.0, 30.0))
        normal_cam = r_wc @ rot[:, 2]
        if normal_cam @ p_cam > 0:
            normal_cam = -normal_cam
        d = means[i] - origin
        surfels.append(dict(depth=p_cam[2], index=i, mean=means[i], t_u=rot[:, 0], t_v=rot[:, 1], n=rot[:, 2],
                            s=scales, centre=np.array([fx * p_cam[0] / p_cam[2] + cx, fy * p_cam[1] / p_cam[2] + cy]),
                            opacity=1.0 / (1.0 + math.exp(-float(opacity_logits[i]))), normal=normal_cam,
                            colour=_sh_colour(np.asarray(sh[i], np.float64), d / np.linalg.norm(d))))
    surfels.sort(key=lambda s: (s["depth"], s["index"]))

    rgb = np.zeros((height, width, 3))
    alpha_out = np.zeros((height, width))
    depth_out = np.zeros((height, width))
    normal_out = np.zeros((height, width, 3))
    distortion_out = np.zeros((height, width))
    for yy in range(height):
        for xx in range(width):
            pix = np.array([xx + 0.5, yy + 0.5])
            ray = r_cw @ np.array([(pix[0] - cx) / fx, (pix[1] - cy) / fy, 1.0])   # camera z of ray(t) is t
            t_left = 1.0
            weights, depths = [], []
            colour, normal = np.zeros(3), np.zeros(3)
            for s in surfels:
                rho_surfel, hit_depth = math.inf, None
                facing = s["n"] @ ray
                if facing != 0.0 and s["s"].min() > 0.0:
                    t_hit = s["n"] @ (s["mean"] - origin) / facing
                    if t_hit > near:
                        offset = origin + t_hit * ray - s["mean"]
                        u = offset @ s["t_u"] / s["s"][0]
                        v = offset @ s["t_v"] / s["s"][1]
                        rho_surfel, hit_depth = u * u + v * v, t_hit
                rho_lowpass = 2.0 * np.sum((pix - s["centre"]) ** 2)
                rho = min(rho_surfel, rho_lowpass)
                a = min(0.99, s["opacity"] * math.exp(-0.5 * rho))
                if a < 1.0 / 255.0:
                    continue
                if t_left * (1 - a) < 1e-4:
                    break
                w = a * t_left
                z = hit_depth if rho_surfel <= rho_lowpass else s["depth"]
                weights.append(w)
                depths.append(z)
                colour += w * s["colour"]
                normal += w * s["normal"]
                t_left *= 1 - a
            rgb[yy, xx] = colour + t_left * np.asarray(background, np.float64)
            alpha_out[yy, xx] = 1 - t_left
            depth_out[yy, xx] = sum(w * z for w, z in zip(weights, depths))
            normal_out[yy, xx] = normal
            distortion_out[yy, xx] = 0.5 * sum(wi * wj * (zi - zj) ** 2 for wi, zi in zip(weights, depths)
                                               for wj, zj in zip(weights, depths))
    return rgb, alpha_out, depth_out, normal_out, distortion_out
