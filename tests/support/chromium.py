"""Headless Debian chromium, the one set of flags for every harness that drives a browser (the
browser tests, the live-view part of the project's latency page: ``benchmarks.latency_page``):
no way out of the machine but loopback."""

from __future__ import annotations

from pathlib import Path
from typing import Any

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    # Nothing but loopback resolves: a CDN fetch that slipped past page.route still fails.
    "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",
]
#: Pages without WebGL.
NO_GPU_ARGS = ["--disable-gpu"]
#: WebGL in software (SwiftShader through ANGLE): no GPU on CI machines. The page itself is
#: composited in software, as a browser without a usable GPU does: compositing through
#: SwiftShader as well took 47 % of a core against 28 % for the same live view.
WEBGL_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
              "--disable-gpu-compositing"]


def missing() -> str | None:
    """Why chromium cannot be driven here (playwright or the binary absent), else None."""
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "playwright is not installed (pip install 'burrforce[test]')"
    if not CHROMIUM.exists():
        return f"{CHROMIUM} is missing (Debian: apt-get install chromium)"
    return None


def launch(playwright: Any, extra: list[str]) -> Any:
    """Headless chromium with the common flags and ``extra`` (``NO_GPU_ARGS``, ``WEBGL_ARGS``),
    from a started ``sync_playwright()``; returns its ``Browser``."""
    return playwright.chromium.launch(executable_path=str(CHROMIUM), headless=True,
                                      args=CHROMIUM_ARGS + extra)
