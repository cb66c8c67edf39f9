"""MkDocs hook: serve pages that live elsewhere in the repository as they are, not copied.

The wire protocol (``proto/SPEC.md``, ``proto/MESH.md``) belongs beside its code and the
results pages (``benchmarks/*.md`` and their plots) are written by ``burrforce bench … --out
benchmarks``; a copy under ``docs/`` would go stale on the next run. Each such file joins the
site at its repository path (``proto/SPEC.md`` → ``/proto/SPEC/``), so the links between them
stay valid. A page under ``docs/`` links them by their repository path, as it does on a
forge (``../benchmarks/latency.md``); ``on_page_markdown`` points such links at the site's copy.
"""

from __future__ import annotations

import posixpath
import re
from collections.abc import Iterator
from pathlib import Path

from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parents[2]
DOCS = "docs"
#: The repository files the site takes in, as globs from the repository root.
INCLUDED = ("proto/SPEC.md", "proto/MESH.md", "benchmarks/**/*.md", "benchmarks/**/*.png")

# A Markdown link or image target: ](target) or ](target "title").
LINK = re.compile(r"\]\(([^)\s]+)((?:\s+\"[^\"]*\")?)\)")


def included() -> Iterator[str]:
    """The included files' repository paths (POSIX), sorted within each glob."""
    for pattern in INCLUDED:
        for path in sorted(ROOT.glob(pattern)):
            yield path.relative_to(ROOT).as_posix()


def on_files(files: Files, config) -> Files:
    for rel in included():
        files.append(File(rel, src_dir=str(ROOT), dest_dir=config["site_dir"],
                          use_directory_urls=config["use_directory_urls"]))
    return files


def on_page_markdown(markdown: str, page, config, files: Files) -> str:
    if page.file.src_dir is None or Path(page.file.src_dir).resolve() == ROOT:
        return markdown  # an included page: its links are already repository-relative
    here = posixpath.dirname(page.file.src_uri)
    targets = set(included())

    def relink(match: re.Match) -> str:
        url, title = match.group(1), match.group(2)
        if "://" in url or url.startswith(("#", "/", "mailto:")):
            return match.group(0)
        path, _, fragment = url.partition("#")
        repo_path = posixpath.normpath(posixpath.join(DOCS, here, path))
        if repo_path not in targets:
            return match.group(0)
        site_url = posixpath.relpath(repo_path, here or ".")
        return f"]({site_url}{'#' + fragment if fragment else ''}{title})"

    return LINK.sub(relink, markdown)
