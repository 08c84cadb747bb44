"""Mutated requests for every route, for the fuzz property test and bench/bench_reliability.py.

`mutated_request(rng, ids)` takes a valid request of a random route and damages it the way
the issue-17 attack did: a value anywhere in the JSON tree replaced by NaN / +-Infinity /
1e309 (raw tokens, which JSON has not but Python's parser reads), huge or negative numbers,
subnormals, wrong types, server paths, a deleted or an unknown key. Uploads are also sent as
raw multipart bodies damaged at every level (`mutated_upload`): the boundary, the part
headers, the parts' contents (cameras nested 10^5 deep, bytes that are not UTF-8) and the
body's framing. The server must answer every one with a status below 500, on a connection it
keeps open.
"""

from __future__ import annotations

import json
import random
from dataclasses import dataclass
from typing import Any

from .fixtures import svc_cameras

TOKENS = ["NaN", "Infinity", "-Infinity", "1e309", "-1e309", "5e-324", "1e-320", "1e308", "-0.0",
          "123456789012345678901234567890", "-1", "0", "1", "2.5", "true", "null", '""', '"/etc/passwd"',
          '"/dev/zero"', "[]", "{}", "[[1,2],[3,4]]", '"\\u0000"', '"' + "a" * 300 + '"', "[" * 5000 + "]" * 5000]
PLACEHOLDER = "@@fuzz@@"


@dataclass
class FuzzRequest:
    method: str
    path: str
    body: bytes | None = None            # JSON (may hold raw NaN tokens), or a raw multipart body
    files: dict | None = None            # multipart upload built by httpx
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
