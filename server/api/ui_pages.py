"""The live view, ``/ui/``: a page the control plane serves with its scripts (no CDN).

The page and its assets need no token, like ``/docs``: they hold no data. The page asks for
the REST token (or takes it from the ``#token=`` fragment of the link ``serve`` prints, which
browsers never send to the server) and sends it with every API call and WebSocket.
"""

from __future__ import annotations

import base64
import hashlib
import re

from fastapi import FastAPI, Request
from fastapi.responses import HTMLResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles

from ..ui import STATIC_DIR, UI_DIR, VENDOR_DIR, vendor_missing

UI_URL = "/ui/"
#: Only the app's own URLs. Scripts: the page's files and its inline import map, by hash.
#: connect-src 'self' covers the page's WebSockets to the same host and port (CSP 3).
#: Styles: uPlot sets inline styles. blob: images and links: exports handed to the browser.
CSP = ("default-src 'none'; script-src 'self' {hashes}; style-src 'self' 'unsafe-inline'; "
       "img-src 'self' data: blob:; connect-src 'self'; base-uri 'none'; form-action 'self'; "
       "frame-ancestors 'none'")
_INLINE_SCRIPT = re.compile(r"<script(?: type=\"importmap\")?>(.*?)</script>", re.DOTALL)


def _page() -> tuple[str, str]:
    # Beside static/, not in it: served only here, with its policy.
    html = (UI_DIR / "index.html").read_text(encoding="utf-8")
    hashes = " ".join(
        f"'sha256-{base64.b64encode(hashlib.sha256(body.encode()).digest()).decode()}'"
        for body in _INLINE_SCRIPT.findall(html))
    return html, CSP.format(hashes=hashes)


def add_ui_pages(app: FastAPI) -> None:
    """Serve ``/ui/`` (the page), ``/ui/static/…`` (its own files) and ``/ui/vendor/…``
    (three.js and uPlot, committed in server/ui/vendor/ and shipped in the wheel)."""
    app.mount("/ui/static", StaticFiles(directory=STATIC_DIR), name="ui-static")
    # A tree whose vendor folder was deleted: its files are then 404s, and the page a 503
    # that says why.
    if VENDOR_DIR.is_dir():
        app.mount("/ui/vendor", StaticFiles(directory=VENDOR_DIR), name="ui-vendor")
    html, csp = _page()

    @app.get("/ui", include_in_schema=False)
    async def ui_redirect(request: Request) -> RedirectResponse:
        root = str(request.scope.get("root_path", "")).rstrip("/")
        return RedirectResponse(f"{root}{UI_URL}", status_code=307)

    @app.get(UI_URL, include_in_schema=False)
    async def ui_page() -> HTMLResponse:
        missing = vendor_missing()
        if missing:
            return HTMLResponse(
                "<!doctype html><title>burrforce live view</title><h1>The live view's scripts "
                "are missing</h1><p>This installation lacks them: "
                + ", ".join(missing) + ". They are part of burrforce's sources "
                "(<code>server/ui/vendor/</code>): reinstall burrforce from a complete "
                "checkout or sdist, or restore them from npm with "
                "<code>python server/ui/vendor.py</code> (BURRFORCE_NPM_REGISTRY names a "
                "mirror).</p>", status_code=503,
                headers={"Content-Security-Policy": CSP.format(hashes="")})
        return HTMLResponse(html, headers={"Content-Security-Policy": csp,
                                           "Cache-Control": "no-cache"})
