"""What the web page needs from the service, through a real server and the real client: the
page's files served without the key (the API still needs it), the stored training cameras,
the model's render beside each heat map, and both models' renders in a selection."""

from __future__ import annotations

import base64
import json
from pathlib import Path

import httpx
import imageio.v3 as iio
import numpy as np
import pytest

from client import AuthenticationError, NotFoundError, PHDClient
from phd_core import uq
from phd_core.io import colorize, png_bytes
from phd_core.renderers import NO_CAMERAS_NOTE
from phd_core.renderers.gs3d import GaussianRenderer, read_ply
from support.fixtures import svc_cameras

PAGE_DIR = Path(__file__).resolve().parents[2] / "service" / "page"


def _png(data: str | bytes) -> np.ndarray:
    return iio.imread(base64.b64decode(data) if isinstance(data, str) else data)


def _pixels(image) -> np.ndarray:
    """An image as the service encodes it: float [0, 1] -> uint8 through the PNG writer."""
    return iio.imread(png_bytes(image))


def test_page_files_are_served_without_the_key_and_the_api_still_needs_it(svc_start):
    server = svc_start(api_key="k")
    with httpx.Client(base_url=server.url) as http:
        root = http.get("/")
        assert root.status_code == 307 and root.headers["location"] == "/ui/"
        assert http.get("/ui").headers["location"] == "/ui/"
        page = http.get("/ui/")
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        assert '<script src="app.js" defer></script>' in page.text
        for name, kind in (("app.js", "text/javascript"), ("captures.js", "text/javascript"), ("app.css", "text/css")):
            answer = http.get(f"/ui/{name}")
            assert answer.status_code == 200 and answer.headers["content-type"].startswith(kind)
        missing = http.get("/ui/settings.py")
        assert missing.status_code in (401, 404)          # never a file the route was not written for
        assert http.get("/v1/models").status_code == 401  # the page's API calls carry the key


def test_unknown_page_file_is_a_404_naming_it(svc_start):
    server = svc_start()
    answer = httpx.get(server.url + "/ui/secret.txt")
    assert answer.status_code == 404
    assert answer.json()["error"] == {"code": "not_found", "message": "the page has no file 'secret.txt'",
                                      "field": "name"}


def test_training_cameras_are_returned_as_stored(svc_start, svc_model_files):
    server = svc_start(api_key="k")
    train = svc_cameras(3)
    with PHDClient(server.url, api_key="k") as phd:
        info = phd.upload_model(svc_model_files["ply"], cameras=train)
        frames = phd.training_cameras(info.id)
        assert len(frames) == 3
        for frame, camera in zip(frames, train):
            assert np.allclose(frame["transform_matrix"], camera.c2w.numpy(), atol=1e-9)
            assert (frame["fl_x"], frame["w"], frame["h"]) == (pytest.approx(camera.fx), 24, 24)
        bare = phd.upload_model(svc_model_files["ply_b"])
        assert phd.training_cameras(bare.id) == []
        # A model stored without training cameras says so with the model; one with them does not.
        assert NO_CAMERAS_NOTE in bare.details["notes"] and NO_CAMERAS_NOTE not in info.details.get("notes", [])
        with pytest.raises(NotFoundError) as missing:
            phd.training_cameras("nope")
        assert missing.value.code == "model_not_found"
    with pytest.raises(AuthenticationError), PHDClient(server.url) as anonymous:
        anonymous.training_cameras(info.id)


def test_ranking_returns_the_render_beside_each_heat_map(svc_start, svc_model_files):
    server = svc_start()
    path = svc_model_files["ply"]
    candidates = svc_cameras(4, phase=0.2)
    renderer = GaussianRenderer(read_ply(path), training_cameras=svc_cameras(3))
    with PHDClient(server.url) as phd:
        info = phd.upload_model(path, cameras=svc_cameras(3))
        inline = phd.rank(info.id, candidates, samples=5, seed=4, dropout_ratio=0.3, top_k=2, heatmaps="base64")
        files = phd.rank(info.id, candidates, samples=5, seed=4, dropout_ratio=0.3, top_k=2, heatmaps="files")
        plain = phd.rank(info.id, candidates, samples=5, seed=4, dropout_ratio=0.3, top_k=2)
        assert all(v.render_png is None and v.render_url is None for v in plain.views)
        for a, b in zip(inline.views, files.views):
            assert a.index == b.index and b.render_png is None and a.render_url is None
            # The model's own render of the view, no dropout; the heat map is the ranked view's zeta.
            expected = renderer.render(candidates[a.index])[0]
            assert np.array_equal(_png(a.render_png), _pixels(expected))
            assert np.array_equal(_png(phd.download(b.render_url)), _pixels(expected))
            zeta = uq.view_uncertainty(renderer, candidates[a.index], ratio=0.3, samples=5, seed=4, keep_maps=True)
            assert np.array_equal(_png(a.heatmap_png), colorize(zeta.zeta, inline.heatmap_vmax)[0])
            assert b.render_url.endswith(f"/render_{b.index:04d}.png")


def test_selection_can_return_both_models_renders(svc_start, svc_model_files):
    server = svc_start()
    views = svc_cameras(3, phase=0.5)
    renderers = {key: GaussianRenderer(read_ply(svc_model_files[name]))
                 for key, name in (("a", "ply"), ("b", "ply_b"))}
    with PHDClient(server.url) as phd:
        a = phd.upload_model(svc_model_files["ply"], cameras=svc_cameras(3))
        b = phd.upload_model(svc_model_files["ply_b"], cameras=svc_cameras(4, phase=0.4))
        both = phd.select(a.id, b.id, views, samples=3, ratio_a=0.2, ratio_b=0.3, images="files", both_images=True)
        one = phd.select(a.id, b.id, views, samples=3, ratio_a=0.2, ratio_b=0.3, images="base64")
        assert [v.choice for v in both.views] == [v.choice for v in one.views]
        for view in both.views:
            other = "b" if view.choice == "a" else "a"
            full = {key: renderers[key].render(views[view.index])[0] for key in "ab"}
            assert np.array_equal(_png(phd.download(view.image_url)), _pixels(full[view.choice]))
            assert np.array_equal(_png(phd.download(view.other_image_url)), _pixels(full[other]))
            assert view.other_image_png is None
        assert all(v.other_image_png is None and v.other_image_url is None for v in one.views)


def test_page_files_hold_no_inline_code():
    """What the CSP forbids, checked in the files themselves (the browser tests check it live)."""
    html = (PAGE_DIR / "index.html").read_text()
    assert "<style" not in html and " style=" not in html and "javascript:" not in html
    assert html.count("<script") == html.count('<script src="app.js"') + html.count(
        '<script src="captures.js"') + html.count('<script type="module" src="view3d.js"') == 3
    for name in ("app.js", "captures.js", "view3d.js"):
        script = (PAGE_DIR / name).read_text()
        assert "innerHTML" not in script and "eval(" not in script and '"style"' not in script


def test_training_cameras_of_another_keys_model_are_not_found(svc_start, svc_model_files, tmp_path):
    keys = tmp_path / "keys.json"
    keys.write_text(json.dumps({"alice": "alice-key-1", "bob": "bob-key-22"}))
    server = svc_start(keys_file=keys)
    with PHDClient(server.url, api_key="alice-key-1") as alice, PHDClient(server.url, api_key="bob-key-22") as bob:
        info = alice.upload_model(svc_model_files["ply"], cameras=svc_cameras(2))
        assert len(alice.training_cameras(info.id)) == 2
        with pytest.raises(NotFoundError):
            bob.training_cameras(info.id)
