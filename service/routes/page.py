"""The web page: one HTML file, its scripts and style sheets from service/page/, and the
3D view's vendored three.js from service/page/vendor/ (local files: the page loads nothing
from another host).

The page is a client of the REST API like any other (it sends the API key the user types
on every call), so these routes need no key: they serve static files only. No inline
scripts or styles, so a Content-Security-Policy of `script-src 'self'; style-src 'self'`
holds.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse, RedirectResponse

from ..errors import ServiceError

PAGE_DIR = Path(__file__).resolve().parent.parent / "page"
FILES = {"app.js": "text/javascript", "app.css": "text/css", "view3d.js": "text/javascript", "view3d.css": "text/css"}
VENDOR = {"three.module.min.js": "text/javascript", "OrbitControls.js": "text/javascript"}

router = APIRouter(include_in_schema=False)


@router.get("/")
async def root() -> RedirectResponse:
    return RedirectResponse("/ui/")


@router.get("/ui")
async def page_no_slash() -> RedirectResponse:
    return RedirectResponse("/ui/")   # relative links in the page (app.js) resolve under /ui/


@router.get("/ui/")
async def page() -> FileResponse:
    return FileResponse(PAGE_DIR / "index.html", media_type="text/html", headers={"Cache-Control": "no-cache"})


@router.get("/ui/vendor/{name}")
async def vendored(name: str) -> FileResponse:
    if name not in VENDOR:  # a fixed list, as below
        raise ServiceError(404, "not_found", f"the page has no vendored file '{name}'", "name")
    return FileResponse(PAGE_DIR / "vendor" / name, media_type=VENDOR[name],
                        headers={"Cache-Control": "public, max-age=86400"})


@router.get("/ui/{name}")
async def asset(name: str) -> FileResponse:
    if name not in FILES:   # a fixed list: no path from the request ever reaches the file system
        raise ServiceError(404, "not_found", f"the page has no file '{name}'", "name")
    return FileResponse(PAGE_DIR / name, media_type=FILES[name], headers={"Cache-Control": "no-cache"})
