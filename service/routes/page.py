"""The web page and the API's own documentation, all served from files on this machine.

The page is one HTML file, its scripts, style sheets and icon from service/page/, and the 3D
view's vendored three.js from service/page/vendor/ (`PAGE_FILES`: the page loads nothing from
another host). It is a client of the REST API like any other (it sends the API
key the user types on every call), so these routes need no key: they serve static files only.
No inline scripts or styles, so a Content-Security-Policy of `script-src 'self'; style-src
'self'` holds.

/docs (Swagger UI) and /redoc (ReDoc) load their scripts from the `fastapi-offline` package
(its static/ folder ships swagger-ui-dist and redoc's standalone bundle, MIT), not from a CDN,
so both work on a machine without internet. ReDoc's bundle asks one outside host for the logo
of its menu footer; it is served with that address replaced by an empty image of its own.
"""

from __future__ import annotations

import importlib.util
from functools import cache
from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import FileResponse, HTMLResponse, RedirectResponse, Response

from ..errors import ServiceError

PAGE_DIR = Path(__file__).resolve().parent.parent / "page"
TYPES = {".js": "text/javascript", ".css": "text/css", ".svg": "image/svg+xml", ".json": "application/json",
         ".wasm": "application/wasm", ".png": "image/png"}
# Every file the page may load, by its path under /ui/: a fixed list made at start-up, so no path
# from a request ever reaches the file system.
PAGE_FILES = {p.relative_to(PAGE_DIR).as_posix(): p for p in sorted(PAGE_DIR.rglob("*"))
              if p.is_file() and p.suffix in TYPES}
_offline = importlib.util.find_spec("fastapi_offline")
DOCS_DIR = Path(_offline.origin).parent / "static" if _offline and _offline.origin else None
DOCS_FILES = ("swagger-ui-bundle.js", "swagger-ui.css", "redoc.standalone.js")
FAVICON = "/ui/favicon.svg"
REDOC_LOGO = b"https://cdn.redoc.ly/redoc/logo-mini.svg"      # the one outside address ReDoc's bundle loads
NO_IMAGE = b"data:image/svg+xml,%3Csvg xmlns='http://www.w3.org/2000/svg'/%3E"

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


@router.get("/ui/{name:path}")
async def asset(name: str) -> FileResponse:
    if name not in PAGE_FILES:
        raise ServiceError(404, "not_found", f"the page has no file '{name}'", "name")
    path = PAGE_FILES[name]
    cache = "public, max-age=86400" if name.startswith("vendor/") else "no-cache"   # vendored files never change
    return FileResponse(path, media_type=TYPES[path.suffix], headers={"Cache-Control": cache})


@router.get("/favicon.ico")
async def favicon() -> FileResponse:
    """Browsers ask for /favicon.ico on every page (the API's docs too): the page's icon."""
    return FileResponse(PAGE_FILES["favicon.svg"], media_type="image/svg+xml")


# ----------------------------------------------------------------------------- the API's documentation

def _docs_file(name: str) -> Path:
    if DOCS_DIR is None or name not in DOCS_FILES or not (DOCS_DIR / name).is_file():
        raise ServiceError(404, "not_found", f"no documentation asset '{name}' (pip install fastapi-offline)", "name")
    return DOCS_DIR / name


@cache
def _redoc_bundle() -> bytes:
    """ReDoc's bundle with its footer logo's outside address replaced by an empty image."""
    return _docs_file("redoc.standalone.js").read_bytes().replace(REDOC_LOGO, NO_IMAGE)


@router.get("/docs-assets/{name}")
async def docs_asset(name: str) -> Response:
    path = _docs_file(name)
    headers = {"Cache-Control": "max-age=86400"}
    if name == "redoc.standalone.js":
        return Response(_redoc_bundle(), media_type=TYPES[path.suffix], headers=headers)
    return FileResponse(path, media_type=TYPES[path.suffix], headers=headers)


@router.get("/docs")
async def swagger_ui(request: Request) -> HTMLResponse:
    return get_swagger_ui_html(openapi_url=request.app.openapi_url, title=request.app.title + " - Swagger UI",
                               oauth2_redirect_url="/docs/oauth2-redirect",
                               swagger_js_url="/docs-assets/swagger-ui-bundle.js",
                               swagger_css_url="/docs-assets/swagger-ui.css", swagger_favicon_url=FAVICON)


@router.get("/docs/oauth2-redirect")
async def swagger_ui_redirect() -> HTMLResponse:
    return get_swagger_ui_oauth2_redirect_html()


@router.get("/redoc")
async def redoc(request: Request) -> HTMLResponse:
    return get_redoc_html(openapi_url=request.app.openapi_url, title=request.app.title + " - ReDoc",
                          redoc_js_url="/docs-assets/redoc.standalone.js", redoc_favicon_url=FAVICON,
                          with_google_fonts=False)
