"""The documentation site: `mkdocs build --strict` passes offline (a broken link, a missing
anchor or a page left out of the nav fails it), the site has the sections issue 42 asks for,
the generated pages are included rather than copied, and no hand-written page quotes a
benchmark's figures (those live in the pages the benchmarks write)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

pytest.importorskip("mkdocs", reason="mkdocs is not installed (the `docs` extra; `test` has it)")
yaml = pytest.importorskip("yaml", reason="PyYAML comes with mkdocs")

#: A hand-quoted measurement: a percentile with its value ("p99 288 µs", "p50: 149"), a pair of
#: timings ("149 / 288 µs"), or a timing called a run's result ("latest … 1.2 ms").
FIGURE = re.compile(
    r"\bp(?:50|90|95|99|99\.9)\b[ :=]*~?\d"
    r"|\d(?:\.\d+)? ?/ ?\d[\d ]*(?:\.\d+)? ?(?:µs|ms)\b"
    r"|\b(?:latest|measured[,:]|the run before|in the last runs?)[^.]{0,60}?\d ?(?:µs|ms)\b",
    re.IGNORECASE)


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir",
                          str(out)], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr
    return out


def _nav() -> dict[str, object]:
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text(encoding="utf-8"))
    return {title: value for entry in config["nav"] for title, value in entry.items()}


def _pages(section: object) -> list[str]:
    if isinstance(section, str):
        return [section]
    return [page for entry in section for value in entry.values() for page in _pages(value)]


def test_the_site_has_the_sections():
    nav = _nav()
    for section in ("Getting started", "Concepts", "Guides", "Reference", "Benchmarks",
                    "Troubleshooting"):
        assert section in nav, section
    assert {"model.md", "voxels.md", "haptics.md", "frames.md"} <= set(_pages(nav["Concepts"]))
    assert {"engines.md", "devices.md", "deployment.md", "calibration.md", "reports.md",
            "ui.md"} <= set(_pages(nav["Guides"]))
    assert {"cli.md", "rest.md", "proto/SPEC.md", "proto/MESH.md", "configuration.md",
            "api.md"} <= set(_pages(nav["Reference"]))


def test_every_results_page_is_in_the_benchmarks_section():
    listed = set(_pages(_nav()["Benchmarks"]))
    generated = {p.relative_to(ROOT).as_posix() for p in (ROOT / "benchmarks").rglob("*.md")}
    assert generated <= listed, generated - listed


def test_included_pages_are_not_copied_into_docs():
    for name in ("SPEC.md", "MESH.md"):
        assert not list(DOCS.rglob(name)), name
    for page in (ROOT / "benchmarks").glob("*.md"):
        assert not (DOCS / "benchmarks" / page.name).exists(), page.name


def test_strict_build_renders_the_reference(site):
    cli = (site / "cli" / "index.html").read_text(encoding="utf-8")
    for command in ("burrforce serve", "burrforce client demo", "burrforce bench latency",
                    "burrforce device list", "--wake-ahead-us"):
        assert command in cli, command
    rest = (site / "rest" / "index.html").read_text(encoding="utf-8")
    assert "/v1/sessions/{session_id}/parameters" in rest
    assert "http://127.0.0.1:47811/docs" in rest  # the OpenAPI page
    assert "CuttingModel" in (site / "api" / "index.html").read_text(encoding="utf-8")
    assert (site / "proto" / "SPEC" / "index.html").exists()
    assert (site / "benchmarks" / "latency" / "index.html").exists()
    assert (site / "benchmarks" / "accuracy.png").exists()


def test_the_site_fetches_nothing(site):
    for page in site.rglob("*.html"):
        text = page.read_text(encoding="utf-8")
        assert "fonts.googleapis.com" not in text and "fonts.gstatic.com" not in text, page


def test_no_hand_written_page_quotes_benchmark_figures():
    quoted = []
    for page in [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]:
        for number, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
            if FIGURE.search(line):
                quoted.append(f"{page.relative_to(ROOT)}:{number}: {line.strip()}")
    assert not quoted, "figures belong in the benchmarks' pages:\n" + "\n".join(quoted)


def test_readme_is_a_front_door():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 200
    commands = [line for line in lines if line.startswith("python3 -m venv .venv")]
    assert commands[:2] == [
        "python3 -m venv .venv && .venv/bin/pip install -e . && .venv/bin/burrforce serve --demo",
        "python3 -m venv .venv && .venv/bin/pip install -e '.[test]' && .venv/bin/pytest",
    ]


def _shell_lines(page: Path) -> list[str]:
    """The lines of a page's shell code blocks."""
    lines, inside = [], False
    for line in page.read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            inside = not inside and line.strip() in ("```bash", "```sh", "```shell")
        elif inside:
            lines.append(line)
    return lines


def test_shell_blocks_run_as_typed_from_the_checkout():
    """Nothing activates the virtualenv: a bare `burrforce` command would not be found."""
    for page in [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]:
        bare = [line for line in _shell_lines(page) if re.match(r"\s*burrforce\s", line)]
        assert not bare, (page, bare)


def test_serve_prints_commands_that_run_as_typed(tmp_path, monkeypatch):
    """serve's banner names `burrforce` as PATH finds this installation, else by its path."""
    from burrforce.server.cli.invocation import burrforce_command

    venv_bin = tmp_path / "venv" / "bin"
    venv_bin.mkdir(parents=True)
    script = venv_bin / "burrforce"
    script.write_text("#!/bin/sh\n")
    script.chmod(0o755)
    monkeypatch.setattr(sys, "executable", str(venv_bin / "python"))
    monkeypatch.setenv("PATH", "/usr/bin:/bin")  # the venv not activated
    assert burrforce_command() == str(script)
    monkeypatch.setenv("PATH", f"{venv_bin}:/usr/bin:/bin")  # activated
    assert burrforce_command() == "burrforce"
    other = tmp_path / "other"
    other.mkdir()
    (other / "burrforce").write_text("#!/bin/sh\n")
    (other / "burrforce").chmod(0o755)
    monkeypatch.setenv("PATH", f"{other}:{venv_bin}")  # another installation first on PATH
    assert burrforce_command() == str(script)
    script.unlink()  # run as `python -m burrforce.server.cli`: no script beside python
    assert burrforce_command().endswith(" -m burrforce.server.cli")
