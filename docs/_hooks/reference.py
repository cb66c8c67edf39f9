"""MkDocs hook: reference tables rendered from the code itself at build time.

``<!-- cli-help -->`` (docs/cli.md) becomes ``burrforce … --help`` of every command and
subcommand; ``<!-- rest-routes -->`` (docs/rest.md) becomes the table of REST routes from the
control plane's routers. Neither is a hand-kept copy that drifts from the code.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Iterator

CLI_MARKER = "<!-- cli-help -->"
ROUTES_MARKER = "<!-- rest-routes -->"
#: Help is wrapped to this many columns (argparse reads COLUMNS).
COLUMNS = "100"
#: The routes ``server/api/app.py`` declares on the app itself, not on a router.
APP_ROUTES = (
    ("GET", "/v1/health", "Liveness of the hot loops and the control plane (no token)."),
    ("GET", "/metrics", "Prometheus metrics."),
    ("GET", "/docs, /redoc, /openapi.json", "The OpenAPI document and its pages."),
    ("GET", "/ui/", "The live view."),
)


def _walk(parser: argparse.ArgumentParser, words: tuple[str, ...]
          ) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    yield words, parser
    for action in parser._actions:  # argparse has no public walk over its subparsers
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from _walk(child, (*words, name))


def cli_help() -> str:
    from burrforce.server.cli import build_parser

    before = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = COLUMNS
    try:
        parts = []
        for words, parser in _walk(build_parser(), ("burrforce",)):
            level = "#" * min(len(words) + 1, 4)
            parts.append(f"{level} `{' '.join(words)}`\n\n```text\n{parser.format_help()}```\n")
        return "\n".join(parts)
    finally:
        if before is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = before


def _summary(route) -> str:
    """The handler's first paragraph, else its name in words (``list_sessions``)."""
    words = (route.endpoint.__doc__ or "").strip().split("\n\n")[0].split()
    text = " ".join(words) or route.name.replace("_", " ").capitalize() + "."
    return text.replace("|", "\\|")


def rest_routes() -> str:
    from burrforce.server.api.app import API_PREFIX, ROUTERS

    rows = [f"| {method} | `{path}` | {text} |" for method, path, text in APP_ROUTES]
    for router, _ in ROUTERS:
        for route in router.routes:
            methods = sorted(getattr(route, "methods", None) or ["WebSocket"])
            rows.append(f"| {', '.join(methods)} | `{API_PREFIX}{route.path}` | "
                        f"{_summary(route)} |")
    return "| Method | Path | What it does |\n|---|---|---|\n" + "\n".join(rows) + "\n"


def on_page_markdown(markdown: str, page, config, files) -> str:
    if CLI_MARKER in markdown:
        markdown = markdown.replace(CLI_MARKER, cli_help())
    if ROUTES_MARKER in markdown:
        markdown = markdown.replace(ROUTES_MARKER, rest_routes())
    return markdown
