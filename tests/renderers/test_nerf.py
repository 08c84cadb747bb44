"""NeRF model, encodings, volume rendering, keep-masks and checkpoints (phd_core.renderers.nerf).

Reference values are computed independently: by hand (math in float64), in closed form,
or by an equivalent model edited by hand (a dropped unit = a zeroed row of the first layer).
"""

from __future__ import annotations

import io
import json
import math
import struct

import pytest
import torch
from safetensors.torch import save as st_save

from phd_core.errors import InputError
from phd_core.renderers import Renderer, nerf
from phd_core.renderers.nerf import (
    HASH_PRIMES,
    HashEncoding,
    NeRFConfig,
    NeRFRenderer,
    PositionalEncoding,
    RadianceField,
    band_weights,
    composite,
    is_nerf_checkpoint,
    load_nerf,
    load_nerf_bytes,
    nerf_bytes,
    save_nerf,
)
from phd_core.scene import look_at

BOX = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]


def small_config(**kw) -> NeRFConfig:
    values = dict(depth=3, width=16, color_width=8, pos_freqs=3, dir_freqs=2, samples=24, near=1.0, far=7.0,
                  bounds=BOX, grid_resolution=8, hash_levels=3, hash_log2_size=10, hash_base_resolution=2,
                  hash_max_resolution=16)
    values.update(kw)
    return NeRFConfig(**values)


def small_camera(width: int = 12, height: int = 10):
    return look_at((2.5, -3.0, 2.0), (0.0, 0.0, 0.0), width=width, height=height, fov_x=0.8)


def textured(model: RadianceField, seed: int = 1) -> RadianceField:
    """Random weights scaled up so that the field has visible structure (not a flat fog)."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * (1.0 if p.dim() == 1 else 1.5 / math.sqrt(p.shape[-1])))
    return model


# ----------------------------------------------------------------------------- encodings

def test_positional_encoding_matches_hand_computed_values():
    x = torch.tensor([[0.25, -0.5, 1.0], [0.1, 0.0, -0.3]])
    enc = PositionalEncoding(2)(x)
    assert enc.shape == (2, 3 + 6 * 2)
    for p in range(2):
        expected = list(map(float, x[p]))
        for k in range(2):
            f = math.pi * 2 ** k
            expected += [math.sin(f * float(v)) for v in x[p]] + [math.cos(f * float(v)) for v in x[p]]
        assert torch.allclose(enc[p].double(), torch.tensor(expected, dtype=torch.float64), atol=1e-6)


def test_band_weights_reveal_frequencies_linearly_and_mask_the_encoding():
    assert band_weights(4, 2.5).tolist() == [1.0, 1.0, 0.5, 0.0]
    assert band_weights(4, 9.0).tolist() == [1.0] * 4
    assert band_weights(4, None) is None
    x = torch.tensor([[0.3, -0.2, 0.7]])
    full = PositionalEncoding(3)(x)
    masked = PositionalEncoding(3)(x, band_weights(3, 1.5))
    assert torch.equal(masked[:, :3], x)                        # raw coordinates never masked
    assert torch.equal(masked[:, 3:9], full[:, 3:9])            # band 0 fully on
    assert torch.allclose(masked[:, 9:15], 0.5 * full[:, 9:15])  # band 1 half on
    assert torch.equal(masked[:, 15:], torch.zeros(1, 6))        # band 2 off


def test_spe_differs_from_pe_only_in_the_first_activation():
    pe = RadianceField(small_config(encoding="pe"), seed=3)
    spe = RadianceField(small_config(encoding="spe"), seed=3)
    for (name, a), (_, b) in zip(pe.state_dict().items(), spe.state_dict().items()):
        assert torch.equal(a, b), name
    gen = torch.Generator().manual_seed(0)
    points = torch.rand(50, 3, generator=gen) * 2 - 1
    dirs = torch.nn.functional.normalize(torch.randn(50, 3, generator=gen), dim=-1)
    pre = pe.first(pe.encode(points))
    h1_pe, skip_pe, dir_pe = pe.stem(points, dirs)
    h1_spe, _, _ = spe.stem(points, dirs)
    assert torch.equal(h1_pe, torch.relu(pre))
    assert torch.equal(h1_spe, torch.sin(pre))
    # The PE network with sin swapped in after its first layer is exactly the SPE network.
    sigma_swap, rgb_swap = pe.heads((torch.sin(pre), skip_pe, dir_pe))
    sigma_spe, rgb_spe = spe(points, dirs)
    assert torch.equal(sigma_swap, sigma_spe) and torch.equal(rgb_swap, rgb_spe)
    assert not torch.allclose(pe(points, dirs)[1], rgb_spe)


def small_hash() -> HashEncoding:
    torch.manual_seed(0)
    enc = HashEncoding(levels=2, features=2, log2_size=8, base=2, finest=8)   # res 2 (dense), 8 (hashed)
    with torch.no_grad():
        enc.table.copy_(torch.randn(enc.table.shape))
    return enc


def test_hash_corner_rows_by_hand():
    enc = small_hash()
    assert enc.resolutions.tolist() == [2, 8] and enc.dense.tolist() == [True, False]
    rows = enc.corner_rows(torch.tensor([[[1, 0, 0], [1, 2, 3]]]))       # one cell per level
    # Level 0 is dense: vertex (x, y, z) is row x + 3 y + 9 z.
    assert rows[0, 0].tolist() == [x + 3 * y + 9 * z for x in (1, 2) for y in (0, 1) for z in (0, 1)]
    # Level 1 is hashed into T = 256 rows, after level 0's 256.
    expected = [256 + ((x * HASH_PRIMES[0]) ^ (y * HASH_PRIMES[1]) ^ (z * HASH_PRIMES[2])) % 256
                for x in (1, 2) for y in (2, 3) for z in (3, 4)]
    assert rows[0, 1].tolist() == expected


def test_hash_encoding_interpolates_its_vertices_continuously_and_deterministically():
    enc = small_hash()
    level = 1                                          # the hashed level, resolution 8
    def features(unit):                                # unit-cube point -> this level's features
        out = enc(torch.tensor(unit, dtype=torch.float32)[None] * 2 - 1)
        return out[0, 2 * level:2 * level + 2]
    def vertex(v):                                     # table entry of an integer vertex
        row = enc.corner_rows(torch.tensor([[[0, 0, 0], v]]))[0, level, 0]
        return enc.table.view(-1, 2)[row]
    # At a vertex the encoding is that vertex's entry; midway along an edge it is the mean.
    assert torch.allclose(features([3 / 8, 5 / 8, 1 / 8]), vertex([3, 5, 1]), atol=1e-6)
    assert torch.allclose(features([3.5 / 8, 5 / 8, 1 / 8]), (vertex([3, 5, 1]) + vertex([4, 5, 1])) / 2, atol=1e-6)
    # Continuous across a cell face, and the same answer every time.
    x = torch.tensor([[4 / 8 * 2 - 1 - 1e-5, 0.13, -0.41], [4 / 8 * 2 - 1 + 1e-5, 0.13, -0.41]])
    a, b = enc(x), enc(x)
    assert torch.equal(a, b)
    assert (a[0] - a[1]).abs().max() < 1e-3
    gen = torch.Generator().manual_seed(1)
    far = enc(torch.rand(200, 3, generator=gen) * 2 - 1)
    assert far.std() > 0.1                             # the encoding is not trivially flat


# ----------------------------------------------------------------------------- compositing

def test_composite_two_segments_by_hand():
    sigma = torch.tensor([1.0, 2.0], dtype=torch.float64)
    delta = torch.tensor([0.5, 0.25], dtype=torch.float64)
    t = torch.tensor([2.0, 3.0], dtype=torch.float64)
    rgb = torch.tensor([[1.0, 0, 0], [0, 1.0, 0]], dtype=torch.float64)
    bg = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    color, acc, depth = composite(sigma, rgb, delta, t, bg)
    w0 = 1 - math.exp(-0.5)
    w1 = math.exp(-0.5) * (1 - math.exp(-0.5))
    assert torch.allclose(color, torch.tensor([w0, w1, math.exp(-1.0)], dtype=torch.float64), atol=1e-15)
    assert math.isclose(acc.item(), w0 + w1, rel_tol=1e-14)
    assert math.isclose(depth.item(), 2.0 * w0 + 3.0 * w1, rel_tol=1e-14)


def constant_medium(sigma: float, color: tuple[float, float, float], **kw) -> RadianceField:
    """A field of density `sigma` and colour `color` everywhere in the box."""
    model = RadianceField(small_config(**kw))
    with torch.no_grad():
        for p in model.parameters():
            p.zero_()
        model.density_head.bias.fill_(math.log(math.expm1(sigma)) - nerf.DENSITY_SHIFT)
        c = torch.tensor(color)
        model.color_out.bias.copy_(torch.log(c / (1 - c)))
    return model


@pytest.mark.parametrize("background", ["white", "black"])
def test_constant_density_medium_matches_closed_form_transmittance(background):
    sigma, color = 0.7, (0.2, 0.5, 0.9)
    model = constant_medium(sigma, color, samples=256, background=background)
    # Looking straight down from z = 4 with a narrow view: every ray enters the top face
    # z = 1 and leaves through the bottom face z = -1, a path of length 2 / |d_z|.
    camera = look_at((0, 0, 4), (0, 0, 0), up=(0, 1, 0), width=9, height=7, fov_x=0.2)
    out = NeRFRenderer(model).render_full(camera)
    origins, dirs = nerf.camera_rays(camera)
    dz = dirs[:, 2].double().abs()
    t0, length = 3.0 / dz, 2.0 / dz
    trans = torch.exp(-sigma * length)
    bg = torch.tensor(model.config.background, dtype=torch.float64)
    expected_rgb = torch.tensor(color, dtype=torch.float64) * (1 - trans)[:, None] + bg * trans[:, None]
    assert torch.allclose(out.alpha.flatten().double(), 1 - trans, atol=2e-6)
    assert torch.allclose(out.rgb.reshape(-1, 3).double(), expected_rgb, atol=2e-6)
    # Alpha-weighted depth: integral of t sigma exp(-sigma (t - t0)) over [t0, t0 + L].
    depth = t0 * (1 - trans) + (1 - trans) / sigma - length * trans
    assert torch.allclose(out.depth.flatten().double(), depth, rtol=1e-3)


def test_empty_space_gives_the_background():
    model = textured(RadianceField(small_config(background="black")))
    camera = small_camera()
    model.grid.set_density(torch.zeros(model.config.grid_resolution ** 3))      # every cell empty
    out = NeRFRenderer(model).render_full(camera)
    assert torch.equal(out.rgb, torch.zeros_like(out.rgb)) and torch.equal(out.alpha, torch.zeros_like(out.alpha))
    # Rays that miss the box see the background even when the grid is full.
    model = textured(RadianceField(small_config(background=[0.1, 0.6, 0.3])))
    away = look_at((0, 0, 5), (0, 0, 10), width=6, height=5, fov_x=0.5)
    rgb = NeRFRenderer(model).render(away)
    assert torch.allclose(rgb, torch.tensor([0.1, 0.6, 0.3]).expand_as(rgb), atol=0)


# ----------------------------------------------------------------------------- keep-masks

@pytest.mark.parametrize("encoding", ["pe", "spe", "hash"])
def test_keep_masks_match_a_model_with_the_units_removed(encoding):
    model = textured(RadianceField(small_config(encoding=encoding)))
    renderer = NeRFRenderer(model)
    camera = small_camera()
    full = renderer.render(camera)
    units = renderer.num_units
    assert full.shape == (1, camera.height, camera.width, 3) and full.dtype == torch.float32
    gen = torch.Generator().manual_seed(5)
    keep = torch.rand(3, units, generator=gen) >= 0.4
    ones, zeros = torch.ones(1, units, dtype=torch.bool), torch.zeros(1, units, dtype=torch.bool)
    batch = renderer.render(camera, torch.cat([keep, ones, zeros]))
    assert batch.shape == (5, camera.height, camera.width, 3)
    assert torch.equal(batch[3], full[0])                                 # all-ones = unmasked
    assert torch.isfinite(batch[4]).all()                                 # all-zeros is finite
    assert not torch.allclose(batch[0], full[0], atol=1e-3)               # dropping units matters
    for i in range(3):
        # Independent model: the dropped units' rows of the first layer zeroed by hand.
        edited = RadianceField(model.config)
        edited.load_state_dict(model.state_dict())
        with torch.no_grad():
            edited.first.weight[~keep[i]] = 0
            edited.first.bias[~keep[i]] = 0
        assert torch.allclose(batch[i], NeRFRenderer(edited).render(camera)[0], atol=1e-5)


def test_rescale_divides_survivors_by_the_kept_share():
    model = textured(RadianceField(small_config(encoding="pe")))
    camera = small_camera()
    keep = torch.zeros(1, 16, dtype=torch.bool)
    keep[0, :12] = True                                                   # r = 0.25
    scaled = NeRFRenderer(model, rescale=True).render(camera, keep)
    edited = RadianceField(model.config)
    edited.load_state_dict(model.state_dict())
    with torch.no_grad():                                                 # relu(a x) = a relu(x) for a > 0
        edited.first.weight[:12] /= 0.75
        edited.first.bias[:12] /= 0.75
    assert torch.allclose(scaled, NeRFRenderer(edited).render(camera, keep), atol=1e-5)
    nothing = NeRFRenderer(model, rescale=True).render(camera, torch.zeros(1, 16, dtype=torch.bool))
    assert torch.isfinite(nothing).all()


def test_chunking_does_not_change_the_render(monkeypatch):
    model = textured(RadianceField(small_config(encoding="hash")))
    camera = small_camera()
    keep = torch.rand(7, 16, generator=torch.Generator().manual_seed(2)) >= 0.3
    reference = NeRFRenderer(model).render_full(camera, keep)
    monkeypatch.setattr(nerf.renderer, "CHUNK_SAMPLES", 50)   # 2 rays per chunk (read where rays are cut)
    monkeypatch.setattr(nerf.volume, "CHUNK_ELEMENTS", 300)   # one mask per group
    chunked = NeRFRenderer(model).render_full(camera, keep)
    for name in ("rgb", "alpha", "depth"):
        assert torch.allclose(getattr(chunked, name), getattr(reference, name), atol=1e-6), name


def test_renderer_protocol_determinism_and_description():
    model = textured(RadianceField(small_config(encoding="spe")))
    renderer = NeRFRenderer(model, [small_camera()])
    assert isinstance(renderer, Renderer) and renderer.kind == "nerf" and renderer.num_units == 16
    camera = small_camera()
    assert torch.equal(renderer.render(camera), renderer.render(camera))
    info = json.loads(json.dumps(renderer.describe()))
    assert info["kind"] == "nerf" and info["num_units"] == 16 and info["encoding"] == "spe"
    assert info["bounds"] == {"min": BOX[0], "max": BOX[1]} and info["near"] == 1.0 and info["far"] == 7.0
    assert info["occupancy_grid"]["occupied_fraction"] == 1.0
    assert info["freenerf"] == {"frequency_mask": False, "occlusion": False}
    with pytest.raises(ValueError):
        renderer.render(camera, torch.ones(2, 15, dtype=torch.bool))


def test_occupancy_grid_cells_and_threshold():
    grid = nerf.OccupancyGrid(4, BOX, threshold=0.01)
    points = torch.tensor([[-0.99, -0.99, -0.99], [0.99, 0.99, 0.99], [0.1, -0.6, 0.9], [5.0, 0.0, 0.0]])
    assert grid.cells(points).tolist() == [0, 63, (2 * 4 + 0) * 4 + 3, (3 * 4 + 2) * 4 + 2]
    density = torch.zeros(64)
    density[63] = 2 * grid.density_threshold
    density[0] = 0.5 * grid.density_threshold
    grid.set_density(density)
    assert grid.lookup(points).tolist() == [False, True, False, False]
    # Threshold: a ray crossing a cell's diagonal at that density loses exactly 1% of its light.
    assert math.isclose(1 - math.exp(-grid.density_threshold * math.sqrt(3) * 0.5), 0.01, rel_tol=1e-6)


# ----------------------------------------------------------------------------- configuration

@pytest.mark.parametrize("field, value", [("encoding", "fourier"), ("width", 0), ("depth", 2.5),
                                          ("samples", -3), ("bounds", [[0, 0, 0], [1, -1, 1]]),
                                          ("far", 0.5), ("background", "purple"), ("grid_threshold", 1.0)])
def test_bad_config_names_the_field(field, value):
    with pytest.raises(InputError) as err:
        RadianceField(small_config(**{field: value}))
    assert err.value.field == field


# ----------------------------------------------------------------------------- checkpoints

def test_checkpoint_round_trip(tmp_path):
    model = textured(RadianceField(small_config(encoding="hash", freenerf_frequency=True)))
    model.grid.set_density(torch.linspace(0, 1, 8 ** 3))
    cameras = [small_camera(), small_camera(8, 8)]
    renderer = NeRFRenderer(model, cameras)
    path = tmp_path / "scene.nerf"
    save_nerf(renderer, path)
    assert [p.name for p in tmp_path.iterdir()] == ["scene.nerf"]      # no temp file left behind
    data = path.read_bytes()
    assert is_nerf_checkpoint(data[:4096])
    loaded = load_nerf(path)
    camera = small_camera()
    keep = torch.rand(2, 16, generator=torch.Generator().manual_seed(0)) > 0.5
    assert torch.equal(loaded.render(camera, keep), renderer.render(camera, keep))
    assert loaded.describe() == renderer.describe()
    assert [c.to_frame() for c in loaded.training_cameras] == [c.to_frame() for c in cameras]
    assert load_nerf_bytes(data, rescale=True).rescale is True


def bad_load(data: bytes) -> str:
    with pytest.raises(InputError) as err:
        load_nerf_bytes(data, "upload")
    assert err.value.field == "model"
    return err.value.reason


def rewrite(data: bytes, edit) -> bytes:
    """Re-serialise a checkpoint after `edit(tensors, metadata)`."""
    from safetensors.torch import load
    size = struct.unpack("<Q", data[:8])[0]
    metadata = json.loads(data[8:8 + size])["__metadata__"]
    tensors = load(data)
    edit(tensors, metadata)
    return st_save(tensors, metadata=metadata)


def test_foreign_truncated_and_tampered_files_are_rejected_clearly():
    model = textured(RadianceField(small_config()))
    data = nerf_bytes(NeRFRenderer(model, [small_camera()]))
    # Not ours at all.
    buffer = io.BytesIO()
    torch.save(model.state_dict(), buffer)
    for foreign in (buffer.getvalue(), bytes(range(256)) * 8, b"", b"ply\nformat ascii 1.0\n"):
        assert not is_nerf_checkpoint(foreign[:4096])
        assert "not a phd-nerf checkpoint" in bad_load(foreign)
    plain = st_save({"w": torch.zeros(3)}, metadata={"format": "pt"})
    assert not is_nerf_checkpoint(plain) and "not a phd-nerf" in bad_load(plain)
    # Truncated: inside the tensor data, and inside the header.
    assert "truncated" in bad_load(data[:len(data) - 100])
    header_end = 8 + struct.unpack("<Q", data[:8])[0]
    assert "truncated" in bad_load(data[:header_end - 10])
    # Tampered: values, shapes, config, version, cameras.
    def nan_weight(t, m):
        t["first.weight"][0, 0] = float("nan")
    assert "NaN" in bad_load(rewrite(data, nan_weight))
    def drop_tensor(t, m):
        del t["density_head.bias"]
    assert "missing" in bad_load(rewrite(data, drop_tensor))
    def wider(t, m):
        m["config"] = m["config"].replace('"width": 16', '"width": 32')
    assert "shape" in bad_load(rewrite(data, wider))
    def deep(t, m):
        m["config"] = m["config"].replace('"depth": 3', '"depth": 99')
    assert "depth" in bad_load(rewrite(data, deep))
    def garbage_config(t, m):
        m["config"] = "{not json"
    assert "JSON" in bad_load(rewrite(data, garbage_config))
    def future(t, m):
        m["version"] = "7"
    assert "version" in bad_load(rewrite(data, future))
    def bad_cameras(t, m):
        t[nerf.CAMERAS_TENSOR] = torch.frombuffer(bytearray(b'[{"fl_x": 1}]'), dtype=torch.uint8)
    assert "training cameras" in bad_load(rewrite(data, bad_cameras))
    def extra(t, m):
        t["payload"] = torch.zeros(4)
    assert "unexpected" in bad_load(rewrite(data, extra))
