"""Headless Debian chromium for the browser tests, with no way out of the machine: its host
resolver knows only 127.0.0.1, and each page aborts and records any other request."""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from contextlib import contextmanager
from urllib.parse import urlsplit

import pytest

from support.chromium import (  # noqa: F401 - the tests import them from here
    CHROMIUM,
    NO_GPU_ARGS,
    WEBGL_ARGS,
    launch,
)

LOOPBACK = ("127.0.0.1", "localhost")
RENDER_TIMEOUT_MS = 15_000
CSP_REFUSAL = re.compile(r"'([^']+)' violates the following Content Security Policy")

try:
    from playwright.sync_api import Browser, Page, Route, sync_playwright
except ImportError:  # pragma: no cover - depends on the machine
    sync_playwright = None


@contextmanager
def chromium(extra_args: list[str]) -> Iterator[Browser]:
    """Headless Debian chromium driven by playwright; skips where either is missing."""
    if sync_playwright is None:
        pytest.skip("playwright is not installed (pip install 'burrforce[test]')")
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is missing (Debian: apt-get install chromium)")
    with sync_playwright() as p:
        b = launch(p, extra_args)
        try:
            yield b
        finally:
            b.close()


class OfflinePage:
    """A page that aborts and records every request leaving loopback, and records failed
    requests, failed responses, console errors and uncaught exceptions; apart, the loads the
    pages' Content-Security-Policy refused (never sent: the policy allows only loopback)."""

    def __init__(self, browser: Browser, **context_options) -> None:
        self.context = browser.new_context(service_workers="block", **context_options)
        self.page: Page = self.context.new_page()
        self.left_loopback: list[str] = []
        self.failed: list[str] = []
        self.errors: list[str] = []
        self.refused: set[str] = set()
        self.aborted: list[str] = []
        self.context.route("**/*", self._route)
        self.page.on("requestfailed", self._request_failed)
        self.page.on("response", self._response)
        self.page.on("console", self._console)
        self.page.on("pageerror", lambda e: self.errors.append(f"page: {e}"))
        #: HTTP errors the page is expected to meet (status, path): not failures.
        self.expected_http: set[tuple[int, str]] = set()

    def _route(self, route: Route) -> None:
        url = route.request.url
        if urlsplit(url).scheme in ("data", "blob") or urlsplit(url).hostname == "127.0.0.1":
            route.continue_()
        else:
            self.left_loopback.append(url)
            route.abort("blockedbyclient")

    def _response(self, response) -> None:
        if response.status >= 400 and (response.status, urlsplit(response.url).path) \
                not in self.expected_http:
            self.failed.append(f"{response.url}: HTTP {response.status}")

    def _request_failed(self, request) -> None:
        if request.failure == "csp":
            self.refused.add(request.url)
        elif request.failure == "net::ERR_ABORTED":
            # Cancelled by the page itself (a reload or navigation while a poll was in
            # flight): not an error of the server's.
            self.aborted.append(request.url)
        else:
            self.failed.append(f"{request.url}: {request.failure}")

    def _console(self, message) -> None:
        refused = CSP_REFUSAL.search(message.text)
        if refused:
            self.refused.add(refused.group(1))
        elif message.type == "error" and not (
                # The browser's own line for an HTTP error the test expected.
                "Failed to load resource" in message.text and self.expected_http):
            self.errors.append(f"console: {message.text}")

    def settle(self, refused: int = 0) -> None:
        """Wait (bounded) for the network to go quiet and ``refused`` refusals to be seen."""
        self.page.wait_for_load_state("networkidle", timeout=RENDER_TIMEOUT_MS)
        deadline = time.monotonic() + RENDER_TIMEOUT_MS / 1000
        while len(self.refused) < refused and time.monotonic() < deadline:
            self.page.wait_for_timeout(50)

    def check(self, refused: frozenset[str] = frozenset()) -> None:
        """Nothing left loopback or failed; the policy refused exactly ``refused``."""
        assert self.left_loopback == [], f"requests left loopback: {self.left_loopback}"
        assert self.failed == [], f"requests failed: {self.failed}"
        assert self.errors == [], f"the page reported errors: {self.errors}"
        assert self.refused == refused, "the pages' policy refused other loads than expected"

    def close(self) -> None:
        self.context.close()
