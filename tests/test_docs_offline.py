"""/docs and /redoc work with no way out of the machine: the real stack (hot loop, uvicorn on
127.0.0.1), opened in headless Debian chromium whose host resolver and page both refuse every
host but 127.0.0.1. The pages must render from the server's own assets alone."""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import urlsplit

import httpx
import pytest

from burrforce.server.api.config import ServeConfig
from burrforce.server.api.stack import ServerStack

CHROMIUM = Path("/usr/bin/chromium")
TOKEN = "docs-token-0123456789abcdef"
LOOPBACK = ("127.0.0.1", "localhost")
RENDER_TIMEOUT_MS = 15_000
CHROMIUM_ARGS = [
    "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    # Nothing but loopback resolves: a CDN fetch that slipped past page.route still fails.
    "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",
]
URL = re.compile(r"""https?://[^\s"'<>()]+""")
CSP_REFUSAL = re.compile(r"'([^']+)' violates the following Content Security Policy")
#: ReDoc 2.x always shows Redocly's logo from their CDN in its sidebar footer (no option
#: hides it); the pages' policy refuses it, and ReDoc then leaves the image out.
REDOCLY_LOGO = frozenset({"https://cdn.redoc.ly/redoc/logo-mini.svg"})

try:
    from playwright.sync_api import Browser, Page, Route, sync_playwright
except ImportError:  # pragma: no cover - depends on the machine
    sync_playwright = None


@pytest.fixture(scope="module")
def stack(tmp_path_factory) -> Iterator[ServerStack]:
    config = ServeConfig(http_port=0, udp_port=0, workers=1,
                         data_dir=tmp_path_factory.mktemp("docs-data"))
    with ServerStack(config, TOKEN, journal=False) as s:
        yield s


@pytest.fixture(scope="module")
def browser() -> Iterator[Browser]:
    # Only the browser tests skip: the pages' HTML and headers are checked without one.
    if sync_playwright is None:
        pytest.skip("playwright is not installed (pip install 'burrforce[test]')")
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is missing (Debian: apt-get install chromium)")
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


class OfflinePage:
    """A page that aborts and records every request leaving loopback, and records failed
    requests, failed responses, console errors and uncaught exceptions; apart, the loads the
    pages' Content-Security-Policy refused (never sent: the policy allows only loopback)."""

    def __init__(self, browser: Browser) -> None:
        self.context = browser.new_context(service_workers="block")
        self.page: Page = self.context.new_page()
        self.left_loopback: list[str] = []
        self.failed: list[str] = []
        self.errors: list[str] = []
        self.refused: set[str] = set()
        self.page.route("**/*", self._route)
        self.page.on("requestfailed", self._request_failed)
        self.page.on("response", lambda r: r.status >= 400 and
                     self.failed.append(f"{r.url}: HTTP {r.status}"))
        self.page.on("console", self._console)
        self.page.on("pageerror", lambda e: self.errors.append(f"page: {e}"))

    def _route(self, route: Route) -> None:
        url = route.request.url
        if urlsplit(url).scheme in ("data", "blob") or urlsplit(url).hostname == "127.0.0.1":
            route.continue_()
        else:
            self.left_loopback.append(url)
            route.abort("blockedbyclient")

    def _request_failed(self, request) -> None:
        if request.failure == "csp":
            self.refused.add(request.url)
        else:
            self.failed.append(f"{request.url}: {request.failure}")

    def _console(self, message) -> None:
        refused = CSP_REFUSAL.search(message.text)
        if refused:
            self.refused.add(refused.group(1))
        elif message.type == "error":
            self.errors.append(f"console: {message.text}")

    def settle(self, refused: int = 0) -> None:
        """Wait (bounded) for the network to go quiet and ``refused`` refusals to be seen."""
        self.page.wait_for_load_state("networkidle", timeout=RENDER_TIMEOUT_MS)
        deadline = time.monotonic() + RENDER_TIMEOUT_MS / 1000
        while len(self.refused) < refused and time.monotonic() < deadline:
            self.page.wait_for_timeout(50)

    def check(self, refused: frozenset[str] = frozenset()) -> None:
        """Nothing left loopback or failed; the policy refused exactly ``refused``."""
        assert self.left_loopback == [], "requests left loopback"
        assert self.failed == [], "requests failed"
        assert self.errors == [], "the page reported errors"
        assert self.refused == refused, "the pages' policy refused other loads than expected"

    def close(self) -> None:
        self.context.close()


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
