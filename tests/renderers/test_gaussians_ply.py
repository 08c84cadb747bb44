"""GaussianModel and the 3DGS PLY reader/writer.

Reference files are built by hand with numpy here, independent of `write_ply`, so the
channel-major f_rest layout, name-based lookup and record skipping are checked against
the format itself rather than against our own writer.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from phd_core.errors import InputError
from phd_core.io import files
from phd_core.renderers import splats
from phd_core.renderers.gs3d import GaussianModel, is_ply, parse_ply, read_ply, write_ply

NUMPY_TYPES = {"float": "f4", "double": "f8", "uchar": "u1", "short": "i2", "int": "i4"}


def random_model(num: int, k: int, seed: int = 0) -> GaussianModel:
    gen = torch.Generator().manual_seed(seed)
    return GaussianModel(
        means=torch.randn(num, 3, generator=gen),
        log_scales=torch.randn(num, 3, generator=gen) - 3,
        quats=torch.randn(num, 4, generator=gen),
        opacity_logits=torch.randn(num, generator=gen),
        sh=torch.randn(num, k, 3, generator=gen),
    )


def standard_columns(num: int, k: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Random float32 values for every property a 3DGS PLY needs: name -> [G]."""
    rng = np.random.default_rng(seed)
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    names += [f"f_rest_{i}" for i in range(3 * (k - 1))]
    return {n: rng.standard_normal(num).astype(np.float32) for n in names}


def expected_model(cols: dict[str, np.ndarray], k: int) -> GaussianModel:
    """The model those columns describe, spelled out element by element."""
    num = len(cols["x"])
    sh = np.zeros((num, k, 3), dtype=np.float32)
    for c in range(3):
        sh[:, 0, c] = cols[f"f_dc_{c}"]
        for j in range(1, k):
            sh[:, j, c] = cols[f"f_rest_{c * (k - 1) + (j - 1)}"]  # channel-major

    def stack(names):
        return torch.from_numpy(np.stack([cols[n] for n in names], axis=1))

    return GaussianModel(
        means=stack(["x", "y", "z"]),
        log_scales=stack(["scale_0", "scale_1", "scale_2"]),
        quats=stack(["rot_0", "rot_1", "rot_2", "rot_3"]),
        opacity_logits=torch.from_numpy(cols["opacity"].copy()),
        sh=torch.from_numpy(sh),
    )


def ply_file(props: list[tuple[str, str, np.ndarray]], *, fmt: str = "binary_little_endian",
             header_before: str = "", body_before: bytes = b"",
             header_after: str = "", body_after: bytes = b"") -> bytes:
    """A PLY with one vertex element of (name, ply type, [G] values) properties, optionally
    with other elements (their header lines and body bytes) before and after it."""
    num = len(props[0][2]) if props else 0
    header = (f"ply\nformat {fmt} 1.0\ncomment made by hand\n{header_before}element vertex {num}\n"
              + "".join(f"property {t} {n}\n" for n, t, _ in props) + header_after + "end_header\n")
    if fmt == "ascii":
        rows = zip(*[[f"{v:.9g}" if t in ("float", "double") else str(int(v)) for v in vals]
                     for _, t, vals in props])
        body = "".join(" ".join(row) + "\n" for row in rows).encode()
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        records = np.zeros(num, dtype=[(n, order + NUMPY_TYPES[t]) for n, t, _ in props])
        for n, _, vals in props:
            records[n] = vals
        body = records.tobytes()
    return header.encode() + body_before + body + body_after


def standard_props(cols: dict[str, np.ndarray], k: int) -> list[tuple[str, str, np.ndarray]]:
    """The properties in the order the reference trainer writes them (normals zero)."""
    zeros = np.zeros(len(cols["x"]), dtype=np.float32)
    return [(n, "float", cols.get(n, zeros)) for n in splats.property_names(k)]


def assert_models_equal(got: GaussianModel, want: GaussianModel) -> None:
    """Bit-exact equality of every field (as int32 views, so -0.0 != 0.0 and NaN == NaN)."""
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == torch.float32 and a.shape == b.shape, name
        assert torch.equal(a.contiguous().view(torch.int32), b.contiguous().view(torch.int32)), name


# ----------------------------------------------------------------------------- round trip

@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("num", [0, 57])
def test_write_read_round_trip_is_bit_exact(tmp_path, degree, num):
    model = random_model(num, (degree + 1) ** 2, seed=degree)
    write_ply(model, tmp_path / "m.ply")
    back = read_ply(tmp_path / "m.ply")
    assert back.num_splats == num and back.sh_degree == degree
    assert_models_equal(back, model)


def test_writer_matches_hand_built_reference_and_f_rest_is_channel_major(tmp_path):
    k = 4
    cols = standard_columns(2, k)
    # Identifiable values: f_rest_i of splat g is 100 g + i.
    for i in range(9):
        cols[f"f_rest_{i}"] = np.array([i, 100 + i], dtype=np.float32)
    data = ply_file(standard_props(cols, k))
    model = parse_ply(data)
    # Channel-major: coefficient 2 (k-1 = 1) of channel 1 (green) is f_rest_{1*3 + 1} = f_rest_4.
    assert model.sh[1, 2, 1].item() == 104.0
    assert model.sh[0, 3, 2].item() == 8.0
    assert model.sh[0, 1, 0].item() == 0.0
    assert_models_equal(model, expected_model(cols, k))
    write_ply(model, tmp_path / "m.ply")
    assert (tmp_path / "m.ply").read_bytes() == data.replace(b"comment made by hand\n", b"")


# ----------------------------------------------------------------------------- robust reading

@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian"])
def test_shuffled_properties_extras_and_other_elements(fmt):
    k = 9
    cols = standard_columns(5, k, seed=3)
    rng = np.random.default_rng(7)
    props = [(n, "float", v) for n, v in cols.items()]
    props += [("filter_3D", "float", rng.random(5)), ("red", "uchar", rng.integers(0, 255, 5)),
              ("confidence", "double", rng.random(5)), ("label", "short", rng.integers(-9, 9, 5))]
    props = [props[i] for i in rng.permutation(len(props))]
    order = "<" if fmt == "binary_little_endian" else ">"
    # A fixed-size element before vertex, a list element after it.
    camera = np.array([(1.5, 7)], dtype=[("fx", order + "f8"), ("id", order + "i4")]).tobytes()
    faces = np.array([3], dtype="u1").tobytes() + np.array([0, 1, 2], dtype=order + "i4").tobytes()
    data = ply_file(props, fmt=fmt,
                    header_before="element camera 1\nproperty double fx\nproperty int id\n",
                    body_before=camera,
                    header_after="element face 1\nproperty list uchar int vertex_indices\n",
                    body_after=faces)
    assert_models_equal(parse_ply(data), expected_model(cols, k))


def test_ascii_file_with_crlf_and_preceding_element():
    k = 4
    cols = standard_columns(3, k, seed=5)
    props = standard_props(cols, k) + [("red", "uchar", np.array([1, 2, 3]))]
    data = ply_file(props, fmt="ascii",
                    header_before="element camera 2\nproperty list uchar float fov\n",
                    body_before=b"1 0.5\n2 0.5 0.7\n")
    data = data.replace(b"\n", b"\r\n")
    assert is_ply(data)
    # %.9g decimal round-trips float32 exactly.
    assert_models_equal(parse_ply(data), expected_model(cols, k))


@pytest.mark.parametrize("block", [1, 97, 1 << 22])
def test_ascii_body_parsed_in_blocks_gives_the_same_model(monkeypatch, block):
    """Blocks that end mid-file, after one line or past the end all give the exact model."""
    k = 4
    cols = standard_columns(40, k, seed=6)
    data = ply_file(standard_props(cols, k), fmt="ascii",
                    header_before="element camera 3\nproperty float fov\n", body_before=b"1\n2\n3\n")
    monkeypatch.setattr(splats.ply, "ASCII_BLOCK_BYTES", block)
    assert_models_equal(parse_ply(data), expected_model(cols, k))
    assert_models_equal(parse_ply(data.rstrip(b"\n")), expected_model(cols, k))   # no final newline


def test_ascii_vertex_count_beyond_the_body_is_refused_before_allocating():
    data = b"ply\nformat ascii 1.0\nelement vertex 1000000000000\nproperty float x\nend_header\n1\n"
    with pytest.raises(InputError) as exc:
        parse_ply(data)
    assert exc.value.field == "ply.vertex" and "truncated" in exc.value.reason


def test_is_ply_sniffs_content():
    assert is_ply(b"ply\nformat ascii 1.0\n") and is_ply(b"ply\r\n")
    assert not is_ply(b"PK\x03\x04") and not is_ply(b"plyx\n") and not is_ply(b"")


# ----------------------------------------------------------------------------- bad files

def _valid_props(**overrides: np.ndarray) -> list[tuple[str, str, np.ndarray]]:
    cols = standard_columns(3, 4)
    cols.update(overrides)
    return standard_props(cols, 4)


def _without(name: str) -> bytes:
    return ply_file([p for p in _valid_props() if p[0] != name])


def _header_with(old: bytes, new: bytes) -> bytes:
    return ply_file(_valid_props()).replace(old, new, 1)


BAD_FILES = {
    "truncated": (lambda: ply_file(_valid_props())[:-4], "ply.vertex", "truncated"),
    "fewer ascii rows": (lambda: ply_file(_valid_props(), fmt="ascii").rsplit(b"\n", 2)[0],
                         "ply.vertex", "truncated"),
    "12 f_rest": (lambda: ply_file(_valid_props() + [(f"f_rest_{i}", "float", np.zeros(3)) for i in (9, 10, 11)]),
                  "ply.f_rest", "12"),
    "f_rest gap": (lambda: ply_file([(n.replace("f_rest_0", "f_rest_99"), t, v) for n, t, v in _valid_props()]),
                   "ply.f_rest", "f_rest_0"),
    "no opacity": (lambda: _without("opacity"), "ply.opacity", "missing"),
    "no rot_3": (lambda: _without("rot_3"), "ply.rot_3", "missing"),
    "NaN opacity": (lambda: ply_file(_valid_props(opacity=np.array([0, np.nan, 0], np.float32))),
                    "ply.opacity", "vertex 1"),
    "Inf scale": (lambda: ply_file(_valid_props(scale_1=np.array([0, 0, np.inf], np.float32))),
                  "ply.scale_1", "vertex 2"),
    "NaN in ascii": (lambda: ply_file(_valid_props(x=np.array([np.nan, 0, 0], np.float32)), fmt="ascii"),
                     "ply.x", "vertex 0"),
    "garbage": (lambda: b"hello world\n\x00\x01", "ply.header", "PLY"),
    "no end_header": (lambda: _header_with(b"end_header\n", b""), "ply.header", "end_header"),
    "binary in header": (lambda: _header_with(b"end_header\n", b"\xff\xfe\n"), "ply.header", "end_header"),
    "negative count": (lambda: _header_with(b"element vertex 3", b"element vertex -3"), "ply.vertex", "-3"),
    "fractional count": (lambda: _header_with(b"element vertex 3", b"element vertex 3.0"), "ply.vertex", "3.0"),
    "unknown type": (lambda: _header_with(b"property float opacity", b"property half opacity"),
                     "ply.header", "half"),
    "no format": (lambda: _header_with(b"format binary_little_endian 1.0\n", b""), "ply.header", "format"),
    "no vertex": (lambda: _header_with(b"element vertex", b"element point"), "ply.vertex", "no 'element vertex'"),
    "list before vertex": (lambda: ply_file(_valid_props(), header_before="element cam 1\nproperty list uchar int i\n",
                                            body_before=b"\x00"), "ply.header", "list"),
    "unknown keyword": (lambda: _header_with(b"comment made by hand", b"colour red"), "ply.header", "colour"),
    "ascii extra value": (lambda: ply_file(_valid_props(), fmt="ascii")[:-1] + b" 7\n", "ply.vertex", "2 has 27"),
    "ascii non-number": (lambda: ply_file(_valid_props(), fmt="ascii")[:-2] + b"z\n", "ply.vertex", "not a number"),
}


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_bad_files_raise_input_error_naming_the_field(case):
    make, field, words = BAD_FILES[case]
    with pytest.raises(InputError) as info:
        parse_ply(make(), name="upload.ply")
    assert info.value.field == field
    assert words in info.value.reason and "upload.ply" in info.value.reason


def test_read_missing_file(tmp_path):
    with pytest.raises(InputError) as info:
        read_ply(tmp_path / "absent.ply")
    assert info.value.field == "ply.path"


# ----------------------------------------------------------------------------- atomic write

def test_refused_model_leaves_existing_file_untouched(tmp_path):
    target = tmp_path / "scene.ply"
    target.write_bytes(b"old contents")
    model = random_model(4, 1)
    model.means[2, 1] = float("nan")
    with pytest.raises(InputError) as info:
        write_ply(model, target)
    assert info.value.field == "means"
    assert target.read_bytes() == b"old contents" and os.listdir(tmp_path) == ["scene.ply"]


def test_failed_write_cleans_up_and_keeps_old_file(tmp_path, monkeypatch):
    target = tmp_path / "scene.ply"
    target.write_bytes(b"old contents")

    def failing_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(files.os, "replace", failing_replace)
    with pytest.raises(OSError, match="disk full"):
        write_ply(random_model(4, 4), target)
    assert target.read_bytes() == b"old contents" and os.listdir(tmp_path) == ["scene.ply"]
    monkeypatch.undo()
    write_ply(random_model(4, 4), target)
    assert os.listdir(tmp_path) == ["scene.ply"] and read_ply(target).num_splats == 4


# ----------------------------------------------------------------------------- the container

@pytest.mark.parametrize("field, change", [
    ("sh", lambda m: setattr(m, "sh", torch.zeros(4, 5, 3))),
    ("quats", lambda m: setattr(m, "quats", torch.zeros(4, 3))),
    ("opacity_logits", lambda m: setattr(m, "opacity_logits", torch.zeros(5))),
    ("log_scales", lambda m: setattr(m, "log_scales", m.log_scales.double())),
    ("sh", lambda m: m.sh.__setitem__((0, 0, 0), float("inf"))),
])
def test_validate_names_the_bad_field(field, change):
    model = random_model(4, 4)
    model.validate()
    change(model)
    with pytest.raises(InputError) as info:
        model.validate()
    assert info.value.field == field


def test_subset_by_mask_and_index():
    model = random_model(6, 9)
    mask = torch.tensor([True, False, True, True, False, False])
    by_mask, by_index = model.subset(mask), model.subset(torch.tensor([0, 2, 3]))
    assert_models_equal(by_mask, by_index)
    assert by_mask.num_splats == 3 and by_mask.sh_degree == 2
    assert torch.equal(by_mask.sh[1], model.sh[2])


def test_bounds_min_max_and_quantiles():
    steps = torch.arange(101, dtype=torch.float32)
    model = random_model(101, 1)
    model.means = torch.stack([steps, -2 * steps, torch.full_like(steps, 5.0)], dim=1)
    assert model.bounds() == ([0.0, -200.0, 5.0], [100.0, 0.0, 5.0])
    low, high = model.bounds(0.1)
    assert low == pytest.approx([10.0, -180.0, 5.0]) and high == pytest.approx([90.0, -20.0, 5.0])
    assert random_model(0, 1).bounds() == ([], [])
    with pytest.raises(InputError):
        model.bounds(0.5)
