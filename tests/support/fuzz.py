"""Mutated requests for every route, for the fuzz property test and bench/bench_reliability.py.

`mutated_request(rng, ids)` takes a valid request of a random route and damages it the way
the issue-17 attack did: a value anywhere in the JSON tree replaced by NaN / +-Infinity /
1e309 (raw tokens, which JSON has not but Python's parser reads), huge or negative numbers,
subnormals, wrong types, server paths, a deleted or an unknown key. Uploads are also sent as
raw multipart bodies damaged at every level (`mutated_upload`): the boundary, the part
headers, the parts' contents (cameras nested 10^5 deep, bytes that are not UTF-8) and the
body's framing. Folder uploads (`mutated_folder`, issue 46) start from the folders the
trainers' builders write (`trainer_folders`), damage their files (config values, whole
files replaced by bombs, nesting or noise, odd paths) and then the zip itself (its bytes,
its headers' sizes, methods and counts). The server must answer every one with a status below
500, on a connection it keeps open.
"""

from __future__ import annotations

import json
import random
import re
import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import torch

from .archives import allocating_checkpoint, folder_files, listing_zip, view_checkpoint, zero_checkpoint, zip_of
from .captures import write_output_folder
from .fixtures import svc_cameras, svc_random_gaussians
from .trainers import gsplat_scene, splatfacto_scene

TOKENS = ["NaN", "Infinity", "-Infinity", "1e309", "-1e309", "5e-324", "1e-320", "1e308", "-0.0",
          "123456789012345678901234567890", "-1", "0", "1", "2.5", "true", "null", '""', '"/etc/passwd"',
          '"/dev/zero"', "[]", "{}", "[[1,2],[3,4]]", '"\\u0000"', '"' + "a" * 300 + '"', "[" * 5000 + "]" * 5000]
PLACEHOLDER = "@@fuzz@@"


@dataclass
class FuzzRequest:
    method: str
    path: str
    body: bytes | None = None            # JSON (may hold raw NaN tokens), or a raw multipart body
    files: dict | list | None = None     # multipart upload built by httpx
    content_type: bytes = b"application/json"


def _frames(count: int) -> list[dict]:
    return [c.to_frame() for c in svc_cameras(count, size=16)]


def valid_bodies(ids: dict[str, str]) -> list[tuple[str, str, dict]]:
    """(method, path, body) of one valid request per work route."""
    model = ids["model"]
    return [
        ("POST", f"/v1/models/{model}/rank", {"cameras": _frames(2), "samples": 2, "dropout_ratio": 0.1,
                                             "top_k": 1, "heatmaps": "base64", "downscale": 2}),
        ("POST", f"/v1/models/{model}/rank", {"cameras": {"camera_angle_x": 0.7, "w": 16, "h": 16,
                                                          "frames": [{"transform_matrix": _frames(1)[0]
                                                                      ["transform_matrix"]}]},
                                             "dropout_ratio": 0.2, "samples": 3, "captured": _frames(1)}),
        ("POST", "/v1/select", {"model_a": model, "model_b": ids["model_b"], "cameras": _frames(2), "samples": 2,
                                "ratio_a": 0.1, "ratio_b": 0.2, "rule": "sigma_mean", "images": "files"}),
        ("POST", f"/v1/models/{model}/calibrate", {"training_cameras": _frames(2), "epsilon": 0.5, "step": 0.5,
                                                  "samples": 2, "width": 12, "height": 12}),
    ]


def _paths(value: Any, prefix: tuple = ()) -> list[tuple]:
    """Every path into a JSON tree (keys and list indices), the root excluded."""
    found = []
    if isinstance(value, dict):
        for key, child in value.items():
            found.append(prefix + (key,))
            found += _paths(child, prefix + (key,))
    elif isinstance(value, list):
        for i, child in enumerate(value):
            found.append(prefix + (i,))
            found += _paths(child, prefix + (i,))
    return found


def _mutate(rng: random.Random, body: Any) -> bytes:
    """One to three damaged places in `body`, serialised with raw tokens."""
    body = json.loads(json.dumps(body))
    tokens = []
    for _ in range(rng.randint(1, 3)):
        paths = _paths(body)
        if not paths:
            break
        path = rng.choice(paths)
        parent = body
        for step in path[:-1]:
            parent = parent[step]
        action = rng.random()
        if action < 0.1 and isinstance(parent, dict):
            del parent[path[-1]]
        elif action < 0.15 and isinstance(parent, dict):
            parent[rng.choice(["unknown", "file", "path", "__proto__"])] = 1
        else:
            tokens.append(rng.choice(TOKENS))
            parent[path[-1]] = PLACEHOLDER
    text = json.dumps(body)
    for token in tokens:
        text = text.replace(f'"{PLACEHOLDER}"', token, 1)
    return text.encode()


def _deep(rng: random.Random) -> bytes:
    """Arrays or objects nested 500 to 100,000 deep (Python's decoder recurses once a level)."""
    depth = rng.choice([500, 990, 1100, 5000, 100_000])
    return b"[" * depth + b"]" * depth if rng.random() < 0.5 else b'{"a":' * depth + b"1" + b"}" * depth


PART_DAMAGE = [                                            # (rng, a part's bytes) -> damaged bytes
    lambda rng, data: _deep(rng), lambda rng, data: b"\xff\xfe" + data,
    lambda rng, data: data.decode("latin-1").encode("utf-16"), lambda rng, data: b"",
    lambda rng, data: data[:rng.randint(0, len(data))], lambda rng, data: data * 2,
    lambda rng, data: bytes(rng.randrange(256) for _ in range(rng.randint(1, 300))),
]
HEADER_DAMAGE = [                                          # a part's name -> damaged part headers
    lambda name: b"", lambda name: b'Content-Disposition: form-data; name="' + name + b'"\r\nNo-Colon-Here',
    lambda name: b"Content-Disposition: form-data; name=" + name + b"; name*=utf-8''%ff%fe",
    lambda name: b'Content-Disposition: form-data; name="\xe9\xff"',
    lambda name: b'Content-Disposition: form-data; name="' + name + b'"\r\nX-Big: ' + b"h" * 20_000,
    lambda name: b'Content-Disposition: form-data; name="' + name + b'"' + b"\r\nX: y" * 200,
    lambda name: b'Content-Disposition: form-data; name="' + name + b'"\r\nContent-Transfer-Encoding: base64',
    lambda name: b"Content-Disposition: attachment",
]
BOUNDARY_CHARS = "abcXYZ0189'()+_,-./:=? \"\xe9"


def mutated_upload(rng: random.Random, ply: bytes) -> FuzzRequest:
    """A raw multipart upload (file, cameras, name, background) damaged in one to three places."""
    parts = [[b"file", b'; filename="m.ply"', ply], [b"cameras", b"", json.dumps({"frames": _frames(2)}).encode()],
             [b"name", b"", b"fuzzed"], [b"background", b"", b"[1, 1, 1]"]]
    boundary, head, tail, crlf = b"fuzz-boundary-17", b"", b"", b"\r\n"
    headers = [b'Content-Disposition: form-data; name="%s"%s' % (name, extra) for name, extra, _ in parts]
    for _ in range(rng.randint(1, 3)):
        action, i = rng.randrange(9), rng.randrange(len(parts))
        if action == 0:                                    # a boundary of any length and character
            boundary = "".join(rng.choice(BOUNDARY_CHARS) for _ in range(rng.choice([1, 70, 256, 257, 300, 5000])))
            boundary = boundary.strip().encode("latin-1") or b"b"
        elif action in (1, 2):                             # a part's content
            parts[i][2] = rng.choice(PART_DAMAGE)(rng, parts[i][2])
        elif action == 3:                                  # a part's headers
            headers[i] = rng.choice(HEADER_DAMAGE)(parts[i][0])
        elif action == 4:                                  # a part dropped, repeated or unknown
            parts[i][0] = rng.choice([b"file", b"cameras", b"other", b""])
            headers[i] = b'Content-Disposition: form-data; name="%s"%s' % (parts[i][0], parts[i][1])
        elif action == 5:                                  # bytes before the first boundary
            head = rng.choice([b"preamble\r\n", b"--", b"\r\n" * 3, b"--" + boundary[:-1] + b"\r\n"])
        elif action == 6:                                  # bytes after the last one
            tail = rng.choice([b"epilogue", b"--" + boundary, b"\r\n--" * 100])
        elif action == 7:                                  # line ends other than CRLF
            crlf = rng.choice([b"\n", b"\r", b""])
        else:                                              # a part left out (all of them, at worst)
            headers.pop(i)
            parts.pop(i)
            if not parts:
                parts, headers = [[b"x", b"", b""]], [b""]
    body = head + b"".join(b"--" + boundary + crlf + h + crlf + crlf + data + crlf for h, (_, _, data) in
                           zip(headers, parts)) + b"--" + boundary + b"--" + crlf + tail
    if rng.random() < 0.1:                                 # cut anywhere
        body = body[:rng.randint(0, len(body))]
    quoted = rng.random() < 0.5
    content_type = b"multipart/form-data; boundary=" + (b'"%s"' % boundary if quoted else boundary)
    if rng.random() < 0.05:
        content_type = rng.choice([b"multipart/form-data", b"multipart/form-data; boundary=", b"multipart/mixed; "
                                   b"boundary=x", b"multipart/form-data; boundary=a; boundary=b", b"text/plain"])
    return FuzzRequest("POST", "/v1/models", body, content_type=content_type)


def mutated_request(rng: random.Random, ids: dict[str, str], ply: bytes) -> FuzzRequest:
    """A random route's valid request, damaged."""
    kind = rng.random()
    if kind < 0.1:                                         # an upload whose cameras part is damaged
        cameras = _mutate(rng, {"frames": _frames(2)})
        return FuzzRequest("POST", "/v1/models", files={"file": ("m.ply", ply), "cameras": (None, cameras)})
    if kind < 0.2:                                         # a raw multipart upload, damaged anywhere
        return mutated_upload(rng, ply)
    if kind < 0.3:                                         # ids and names from nowhere
        odd = rng.choice(["nope", "..%2F..%2Fetc%2Fpasswd", "%00", "a" * 300, ids["model"] + "x", "0" * 16])
        method, path = rng.choice([("GET", f"/v1/models/{odd}"), ("DELETE", f"/v1/models/{odd}"),
                                   ("GET", f"/v1/jobs/{odd}"), ("DELETE", f"/v1/jobs/{odd}"),
                                   ("GET", f"/v1/jobs/{odd}/artifacts/{odd}"),
                                   ("GET", f"/v1/jobs/{ids['job']}/artifacts/{odd}")])
        return FuzzRequest(method, path)
    method, path, body = rng.choice(valid_bodies(ids))
    if rng.random() < 0.05:
        return FuzzRequest(method, path, _mutate(rng, body)[:rng.randint(0, 200)])   # truncated JSON
    return FuzzRequest(method, path, _mutate(rng, body))


def send(client, request: FuzzRequest):
    """Send one fuzz request on an httpx.Client (its base_url the server)."""
    if request.files is not None:
        return client.request(request.method, request.path, files=request.files)
    headers = {"content-type": request.content_type} if request.body is not None else {}
    return client.request(request.method, request.path, content=request.body, headers=headers)


# ----------------------------------------------------------------------------- folder uploads (issue 46)

Files = dict[str, bytes]          # a folder: path inside the zip -> content


def trainer_folders(root: Path) -> dict[str, Files]:
    """A run of each trainer the service reads, with the capture its config names beside it, as
    a user zips it: splatfacto (its checkpoint, and its exported PLY), gsplat, the reference 3DGS."""
    splatfacto_scene(root / "splatfacto", export_ply=False)
    splatfacto_scene(root / "export", export_ply=True)
    gsplat_scene(root / "gsplat")
    write_output_folder(root / "3dgs" / "output" / "lego", svc_random_gaussians(200), svc_cameras(3))
    return {name: folder_files(root / name, root / name) for name in ("splatfacto", "export", "gsplat", "3dgs")}


YAML_TOKENS = ["abc", ".inf", "-.inf", ".nan", "-1", "0", "1e309", "[1, 2]", "[1, 2, 3]", "null", "{}", "true", "''",
               "'" + "x" * 5000 + "'", "[" * 300 + "]" * 300, "*nowhere", "&a [*a]", "!!python/name:os.system ''",
               "!!python/object/apply:os.system ['touch /tmp/phd-fuzz']", "- " + "/d" * 3000, "\"\\0\"", "0x7fffffff"]
CFG_TOKENS = ["True", "False", "1", "'" + "/x" * 3000 + "'", "'\\x00'", "None", "''", "abc"]
PATHS = ["../outside.ply", "/etc/outside.ply", "run/..\\..\\outside", "C:/x", "x" * 300, "d/" * 40 + "f",
         ("d" * 200 + "/") * 25 + "f", "nul\0byte", "__MACOSX/._cfg.yml", ".", "a//b/./c", "\u00fc/\u00df.json"]


def alias_bomb(levels: int = 7) -> bytes:
    """A YAML alias tree of 10^levels leaves in a few hundred bytes, as data_dir."""
    lines, previous = ['a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]'], "a"
    for k in range(levels - 1):
        lines.append(f"l{k}: &l{k} [" + ", ".join([f"*{previous}"] * 10) + "]")
        previous = f"l{k}"
    return ("\n".join(lines) + f"\ndata_dir: *{previous}\n").encode()


def _legacy_checkpoint() -> bytes:
    import io
    buffer = io.BytesIO()
    torch.save({"splats": {"means": torch.zeros(3, 3)}}, buffer, _use_new_zipfile_serialization=False)
    return buffer.getvalue()


CONTENTS: list[Callable[[random.Random, bytes], bytes]] = [   # a whole file replaced (rng, old content)
    lambda rng, data: b"", lambda rng, data: data[:rng.randint(0, len(data))], lambda rng, data: data * 2,
    lambda rng, data: bytes(rng.randrange(256) for _ in range(rng.randint(1, 3000))),
    lambda rng, data: _deep(rng), lambda rng, data: b"a: " + b"[" * 100_000 + b"]" * 100_000,
    lambda rng, data: alias_bomb(rng.choice([4, 7])), lambda rng, data: zero_checkpoint(rng.choice([1000, 2_000_000])),
    lambda rng, data: zero_checkpoint(400_000, chunk=8192), lambda rng, data: view_checkpoint(20_000_000),
    lambda rng, data: allocating_checkpoint(10**9), lambda rng, data: _legacy_checkpoint(),
    lambda rng, data: data.replace(b"element vertex ", b"element vertex 9" + b"9" * rng.randint(0, 30)),
    lambda rng, data: data.replace(b"format binary_little_endian", b"format ascii"),
]


def _config_value(rng: random.Random, files: Files) -> None:
    """One value of a config or camera file replaced: a JSON value by `_mutate`'s raw tokens, a
    YAML or cfg_args value by a wrong kind, a bomb, a long path or a Python tag."""
    names = [n for n in files if n.endswith((".json", ".yml", "cfg_args"))]
    if not names:
        return
    name = rng.choice(names)
    text = files[name].decode("utf-8", "replace")
    if name.endswith(".json"):
        try:
            files[name] = _mutate(rng, json.loads(text))
        except (ValueError, RecursionError):       # damaged already: not JSON, or nested past the decoder
            pass
        return
    if name.endswith("cfg_args"):
        values = list(re.finditer(r"=('[^']*'|[^,()]+)", text))
        token = rng.choice(CFG_TOKENS)
    else:
        values = list(re.finditer(r"(?m)^\s*[\w-]+: (.*)$", text))
        token = rng.choice(YAML_TOKENS)
    if values:
        value = rng.choice(values)
        files[name] = (text[:value.start(1)] + token + text[value.end(1):]).encode()


def _replace_file(rng: random.Random, files: Files) -> None:
    name = rng.choice(list(files))
    files[name] = rng.choice(CONTENTS)(rng, files[name])


def _flip_bytes(rng: random.Random, files: Files) -> None:
    name = rng.choice(list(files))
    data = bytearray(files[name])
    for _ in range(rng.randint(1, 20) if data else 0):
        data[rng.randrange(len(data))] = rng.randrange(256)
    files[name] = bytes(data)


def _odd_file(rng: random.Random, files: Files) -> None:
    """A file dropped, or one added under an odd path."""
    if rng.random() < 0.5 and len(files) > 1:
        del files[rng.choice(list(files))]
    else:
        files[rng.choice(PATHS)] = rng.choice([b"", b"ply\n", b"{}", json.dumps({"frames": []}).encode()])


FILE_DAMAGE = [_config_value, _config_value, _replace_file, _flip_bytes, _odd_file]


def _entries(data: bytes) -> list[int]:
    """Where the central directory entries of a zip start."""
    return [m.start() for m in re.finditer(re.escape(b"PK\x01\x02"), data)]


def _lie(rng: random.Random, data: bytes) -> bytes:
    """A central directory entry's declared field changed: method, flags, CRC, sizes, name length."""
    entries = _entries(data)
    if not entries:
        return data
    at = rng.choice(entries)
    field, size = rng.choice([(8, "H"), (10, "H"), (16, "L"), (20, "L"), (24, "L"), (28, "H"), (30, "H")])
    value = rng.choice([0, 1, 8, 12, 99, 0xFFFF, 0xFFFFFFFF, rng.randrange(1 << 16)])
    value &= 0xFFFF if size == "H" else 0xFFFFFFFF
    return data[:at + field] + struct.pack("<" + size, value) + data[at + field + struct.calcsize(size):]


ZIP_DAMAGE: list[Callable[[random.Random, bytes], bytes]] = [   # (rng, zip bytes) -> damaged zip bytes
    lambda rng, data: bytes(b ^ (rng.random() < 0.001) * rng.randrange(1, 256) for b in data),
    lambda rng, data: data[:rng.randint(0, len(data))], lambda rng, data: data + bytes(rng.randint(1, 100)),
    lambda rng, data: b"junk" * rng.randint(1, 100) + data, _lie, _lie,
    lambda rng, data: data[:-22] + struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, *[rng.randrange(1 << 16)] * 2,
                                               *struct.unpack("<2L", data[-10:-2]), 0) if len(data) > 22 else data,
    lambda rng, data: listing_zip(rng.choice([10_001, 200_000])), lambda rng, data: zip_of({}),
]


def mutated_folder(rng: random.Random, folders: dict[str, Files]) -> FuzzRequest:
    """A trainer's folder, its files damaged in one to three places, sent as a zip (itself damaged
    half of the time) or, as a browser's folder pick sends it, one `files` part per file."""
    files = dict(rng.choice(list(folders.values())))
    for _ in range(rng.randint(1, 3)):
        rng.choice(FILE_DAMAGE)(rng, files)
    if rng.random() < 0.15:
        return FuzzRequest("POST", "/v1/models", files=[("files", (name, data)) for name, data in files.items()])
    data = zip_of(files, rng.choice([zipfile.ZIP_DEFLATED, zipfile.ZIP_STORED]))
    if rng.random() < 0.5:
        data = rng.choice(ZIP_DAMAGE)(rng, data)
    return FuzzRequest("POST", "/v1/models", files={"archive": ("run.zip", data)})
