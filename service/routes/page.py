"""The web page: one HTML file, one script and one style sheet from service/page/.

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
FILES = {"app.js": "text/javascript", "app.css": "text/css"}

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


@router.get("/ui/{name}")
async def asset(name: str) -> FileResponse:
    if name not in FILES:   # a fixed list: no path from the request ever reaches the file system
        raise ServiceError(404, "not_found", f"the page has no file '{name}'", "name")
    return FileResponse(PAGE_DIR / name, media_type=FILES[name], headers={"Cache-Control": "no-cache"})
