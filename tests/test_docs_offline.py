"""/docs and /redoc work with no way out of the machine: the real stack (hot loop, uvicorn on
127.0.0.1), opened in headless Debian chromium whose host resolver and page both refuse every
host but 127.0.0.1. The pages must render from the server's own assets alone."""

from __future__ import annotations

import re
from collections.abc import Iterator
from urllib.parse import urlsplit

import httpx
import pytest
from browser import LOOPBACK, NO_GPU_ARGS, RENDER_TIMEOUT_MS, OfflinePage, chromium

from burrforce.server.api.config import ServeConfig
from burrforce.server.api.stack import ServerStack

TOKEN = "docs-token-0123456789abcdef"
URL = re.compile(r"""https?://[^\s"'<>()]+""")
#: ReDoc 2.x always shows Redocly's logo from their CDN in its sidebar footer (no option
#: hides it); the pages' policy refuses it, and ReDoc then leaves the image out.
REDOCLY_LOGO = frozenset({"https://cdn.redoc.ly/redoc/logo-mini.svg"})


@pytest.fixture(scope="module")
def stack(tmp_path_factory) -> Iterator[ServerStack]:
    config = ServeConfig(http_port=0, udp_port=0, workers=1,
                         data_dir=tmp_path_factory.mktemp("docs-data"))
    with ServerStack(config, TOKEN, journal=False) as s:
        yield s


@pytest.fixture(scope="module")
def browser() -> Iterator:
    # Only the browser tests skip: the pages' HTML and headers are checked without one.
    with chromium(NO_GPU_ARGS) as b:
        yield b


@pytest.fixture
def offline(browser) -> Iterator[OfflinePage]:
    page = OfflinePage(browser)
    try:
        yield page
    finally:
        page.close()


def remote_urls(html: str) -> list[str]:
    return [u for u in URL.findall(html) if urlsplit(u).hostname not in LOOPBACK]


@pytest.mark.parametrize("path", ["/docs", "/redoc"])
def test_the_pages_name_no_remote_url(stack, path):
    r = httpx.get(stack.url + path, timeout=30.0)
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/html")
    assert remote_urls(r.text) == []
    assert "/docs/assets/" in r.text
    policy = r.headers["content-security-policy"]
    assert "default-src 'none'" in policy and "https:" not in policy and "*" not in policy


def test_the_pages_and_assets_need_no_token_like_the_schema(stack):
    with httpx.Client(base_url=stack.url, timeout=30.0) as anon:
        for path in ("/openapi.json", "/docs", "/redoc", "/docs/assets/swagger-ui-bundle.js",
                     "/docs/assets/swagger-ui.css", "/docs/assets/redoc.standalone.js",
                     "/docs/assets/favicon.png"):
            assert anon.get(path).status_code == 200, path
        # The API itself still asks for it.
        assert anon.get("/v1/sessions").status_code == 401
        # Not in the published schema: they are pages, not API.
        paths = anon.get("/openapi.json").json()["paths"]
        assert not any(p.startswith(("/docs", "/redoc")) for p in paths)


def test_swagger_ui_renders_offline(stack, offline):
    page = offline.page
    page.goto(stack.url + "/docs", wait_until="load")
    page.locator(".opblock").first.wait_for(timeout=RENDER_TIMEOUT_MS)
    assert "burrforce control plane" in page.locator(".info .title").inner_text()
    health = page.locator(".opblock-get", has=page.locator(
        ".opblock-summary-path", has_text=re.compile(r"^/v1/health$")))
    assert health.count() == 1
    assert page.locator(".opblock").count() >= 10
    assert page.title() == "burrforce control plane - Swagger UI"
    offline.settle()
    offline.check()


def test_redoc_renders_offline(stack, offline):
    page = offline.page
    page.goto(stack.url + "/redoc", wait_until="load")
    page.locator("[role=menuitem]").first.wait_for(timeout=RENDER_TIMEOUT_MS)
    assert page.locator("[role=menuitem]").count() >= 10
    assert "burrforce control plane" in page.locator("h1").first.inner_text()
    assert page.title() == "burrforce control plane - ReDoc"
    offline.settle(refused=len(REDOCLY_LOGO))
    # ReDoc drops the image whose load failed.
    page.locator("img[alt='redocly logo']").wait_for(state="detached",
                                                      timeout=RENDER_TIMEOUT_MS)
    offline.check(refused=REDOCLY_LOGO)
