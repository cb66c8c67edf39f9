"""The control plane's documentation pages, /docs (Swagger UI) and /redoc (ReDoc), with their
scripts, styles and favicon served by the app itself from the ``fastapi-offline`` package.

FastAPI's default pages load them from a CDN and Google Fonts: on the closed networks of
hospitals and labs those pages stay blank. Here every URL in the pages is the app's own.
"""

from __future__ import annotations

import base64
import hashlib
import re

from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

DOCS_URL = "/docs"
REDOC_URL = "/redoc"
#: Under /docs, so that a reverse proxy publishing /docs publishes its assets too.
ASSETS_URL = "/docs/assets"
#: What the pages may load: only the app's own URLs. ReDoc's sidebar footer fetches
#: Redocly's logo from their CDN whatever its options say; this makes the browser refuse it
#: (ReDoc then drops the image) and keeps any remote URL a later asset release adds from
#: leaving the machine. Scripts: the assets and the page's own inline script, by hash.
#: Styles: both UIs set inline styles. Workers: ReDoc's search runs in a blob: worker.
CSP = ("default-src 'none'; script-src 'self'{hashes}; style-src 'self' 'unsafe-inline'; "
       "img-src 'self' data:; font-src 'self' data:; connect-src 'self'; "
       "worker-src 'self' blob:; base-uri 'none'; form-action 'self'; "
       # The token is typed into these pages: no other site may frame them.
       "frame-ancestors 'none'")
_INLINE_SCRIPT = re.compile(r"<script>(.*?)</script>", re.DOTALL)
#: (package, folder) holding swagger-ui-bundle.js, swagger-ui.css, redoc.standalone.js and
#: favicon.png; Starlette finds the folder through the installed package, wherever it is.
ASSETS_PACKAGE = ("fastapi_offline", "static")


def add_docs_pages(app: FastAPI) -> None:
    """Serve ``/docs``, ``/redoc`` and their assets (``/docs/assets/…``) on ``app``.

    ``app`` is built with ``docs_url=None, redoc_url=None`` so FastAPI adds no CDN pages of
    its own. The pages need no token, like ``/openapi.json``: they show nothing the schema
    does not, and "Authorize" in Swagger UI is where a user enters the token.

    Raises:
        ValueError: the app publishes no OpenAPI document (``openapi_url=None``).
    """
    openapi_url = app.openapi_url
    if openapi_url is None:
        raise ValueError("the docs pages need the app's OpenAPI document (openapi_url)")
    # Raises at start-up, not at the first page view, when the package is missing.
    app.mount(ASSETS_URL, StaticFiles(packages=[ASSETS_PACKAGE]), name="docs-assets")

    def urls(request: Request) -> tuple[str, str]:
        # Behind a proxy that strips a prefix (uvicorn --root-path), the browser needs it back.
        root = str(request.scope.get("root_path", "")).rstrip("/")
        return root + openapi_url, root + ASSETS_URL

    @app.get(DOCS_URL, include_in_schema=False)
    async def swagger_ui(request: Request) -> HTMLResponse:
        spec, assets = urls(request)
        # No oauth2_redirect_url: the API's only scheme is a bearer token, typed in by hand.
        return _self_only(get_swagger_ui_html(
            openapi_url=spec, title=f"{app.title} - Swagger UI",
            swagger_js_url=f"{assets}/swagger-ui-bundle.js",
            swagger_css_url=f"{assets}/swagger-ui.css",
            swagger_favicon_url=f"{assets}/favicon.png",
            # No validator badge: it is fetched from swagger.io for non-local hosts.
            swagger_ui_parameters={**(app.swagger_ui_parameters or {}),
                                   "validatorUrl": None}))

    @app.get(REDOC_URL, include_in_schema=False)
    async def redoc(request: Request) -> HTMLResponse:
        spec, assets = urls(request)
        return _self_only(get_redoc_html(
            openapi_url=spec, title=f"{app.title} - ReDoc",
            redoc_js_url=f"{assets}/redoc.standalone.js",
            redoc_favicon_url=f"{assets}/favicon.png", with_google_fonts=False))


def _self_only(page: HTMLResponse) -> HTMLResponse:
    """``page`` with a Content-Security-Policy that lets it load from its own origin only."""
    hashes = "".join(
        f" 'sha256-{base64.b64encode(hashlib.sha256(body.encode()).digest()).decode()}'"
        for body in _INLINE_SCRIPT.findall(bytes(page.body).decode()))
    page.headers["Content-Security-Policy"] = CSP.format(hashes=hashes)
    return page
