"""Shared fixtures: the thesis's cases and their converged references (computed once); the
test tiers and the Hypothesis profile they run with; CI's rule that a test skipped for want of
a system part fails.

Tiers: a bare ``pytest`` runs the fast tier, every test without a tier marker (below); ``pytest
--all`` runs everything, ``pytest --rest`` only what the fast tier leaves out (``.ci/run`` runs
the two). Naming test files or folders, or choosing with ``-m``, runs what is named, every tier.
The markers are applied here, from what a test starts (its fixtures, its own code, its folder
or module), so a new test lands in its tier without being tagged by hand.
"""

from __future__ import annotations

import inspect
import os
from pathlib import Path

import hypothesis_profiles
import pytest

from burrforce.server import compile_cache

# Before numba is imported: the tests and the `burrforce` processes they start then share the
# command's cache, instead of a fresh machine compiling every kernel twice.
compile_cache.configure()

from burrforce.server.model import CuttingParams, thesis_cases  # noqa: E402
from burrforce.server.model.reference import reference_case  # noqa: E402


@pytest.fixture(scope="session")
def thesis_params() -> CuttingParams:
    return CuttingParams()


@pytest.fixture(scope="session")
def nine_cases():
    return list(thesis_cases())


@pytest.fixture(scope="session")
def nine_references(nine_cases, thesis_params):
    return [reference_case(c, thesis_params) for c in nine_cases]


#: Set by .ci/run, which installs everything the tests need (umockdev, PortAudio, JACK, ...):
#: there a skip means a missing install step, so it fails — unless its reason says the skip
#: is about this machine's state, not its software ("(allowed in CI)").
STRICT_SKIPS = os.environ.get("BURRFORCE_STRICT_SKIPS") == "1"
ALLOWED_SKIP = "(allowed in CI)"


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if STRICT_SKIPS and report.skipped and not hasattr(report, "wasxfail"):
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else \
            str(report.longrepr)
        if ALLOWED_SKIP not in reason:
            report.outcome = "failed"
            report.longrepr = (f"skipped in CI, where .ci/run installs everything the tests "
                               f"need: {reason}")


# -- tiers ---------------------------------------------------------------------------------------
#: The markers that take a test out of the fast tier (registered in pyproject.toml).
TIER_MARKERS = ("toolchain", "container", "browser", "usb", "slow")
FAST_TIER = " and ".join(f"not {m}" for m in TIER_MARKERS)
TESTS = Path(__file__).resolve().parent

#: What starts each tier's external part. ``folders``/``modules``: every test there (paths
#: relative to tests/, modules by file name); ``fixtures``: tests that request one;
#: ``calls``: tests whose own code names one (the harness they start, or its availability
#: check before they start it).
TIER_SIGNALS: dict[str, dict[str, tuple[str, ...]]] = {
    # g++/clang/CMake, Mono, Godot 3: the engine SDKs built and run against a live server.
    "toolchain": {"folders": ("sdk",)},
    # podman builds and runs the server image (tests/support/podman.py); the Dockerfile's and
    # compose file's static checks need no engine and stay in the fast tier.
    "container": {"fixtures": ("podman",)},
    # Headless Debian chromium through playwright (tests/browser.py, tests/support/chromium.py).
    "browser": {"fixtures": ("browser",), "calls": ("chromium.missing(",)},
    # umockdev's emulated USB devices (tests/support/emulation).
    "usb": {"modules": ("test_falcon_emulated.py",),
            "fixtures": ("emulated_usb", "falcon_loop"),
            "calls": ("EmulatedUsb(", "emulation_unavailable_reason(")},
}

#: Long runs (over ~5 s each on 2 cores, measured with --durations=0) whose module keeps a
#: faster test of the same behaviour in the fast tier: "module" or "module::test name" (the
#: name without its parameters covers every parametrisation).
SLOW: tuple[str, ...] = (
    # numba types (and compiles) the kernels anew for a signature no cache holds: minutes.
    "test_bone_step_raw.py::test_numba_dispatch_answers_as_the_bound_call_to_the_last_bit",
    "test_bone_shared.py::test_a_tick_that_raises_still_closes_the_seqlock",
    # `burrforce compile` into an empty cache (every kernel, minutes) and what loads from it;
    # the cache's digest and location tests stay in the fast tier.
    "test_compile_cache.py::test_compile_fills_the_cache_it_is_given",
    "test_compile_cache.py::test_after_compile_processes_only_load_even_two_at_once",
    "test_compile_cache.py::test_serve_and_its_hot_loop_load_every_kernel_from_the_compiled_cache",
    "test_compile_cache.py::test_a_report_after_compile_loads_every_kernel_and_says_nothing_of_it",
    # serve on an empty cache until its background compile is done, then again; the jobs,
    # their progress and the tool change after a first start stay in the fast tier.
    "test_first_start.py::test_a_first_serve_compiles_with_progress_then_the_rest_behind_it",
    "test_first_start.py::test_after_the_first_start_jobs_a_hot_loop_and_the_default_bone_"
    "compile_nothing",
    "test_first_start.py::test_the_round_ticks_bone_and_parts_compiled_elsewhere_are_loaded_"
    "and_change_nothing",
    # 100 000 datagrams; the live server's other tests stay.
    "test_hotloop_live.py::test_fuzz_100k_datagrams_against_the_live_server",
    # The schema fuzzers (schemathesis over every route); the module's token test stays.
    "test_api_schema.py::test_no_server_errors",
    "test_api_schema.py::test_answers_match_the_schema",
    # serve --demo until its groove has cut; the REST end-to-end test of serve stays.
    "test_serve_e2e.py::test_serve_demo_prints_the_live_view_and_keeps_cutting",
    # A full accuracy bench through the CLI; the other CLI tests stay.
    "test_cli.py::test_bench_accuracy_json_and_results_file",
    # JACK's dummy driver run for a minute; the ALSA file plugin test covers the same output.
    "test_actuator_audio.py::test_audio_jack_callback_keeps_up_and_watchdog",
    # Gigabyte-sized float64 CTs and 8 GiB gzip bombs against serve (a minute of writing and
    # loading); the loaders' budget, streaming and bomb refusal stay in the fast tier
    # (test_load_streaming.py).
    "test_load_memory.py",
    # The session bench's variants; its rows and counts stay in the fast tier.
    "test_bench_sessions.py::test_reading_each_reply_as_it_comes_from_loops_that_do_not_wake_ahead",
    "test_bench_sessions.py::test_realtime_reaches_serve_and_the_generator",
    # serve killed with SIGKILL and started again on its journal; the hot-loop kills, the
    # deleted session and the journal's own tests stay in the fast tier.
    "test_crash_recovery.py::test_serve_killed_with_sigkill_resumes_its_sessions_and_carving",
    # A wheel built and listed (CI also builds one offline); the layout tests stay.
    "test_packaging.py::test_non_editable_wheel_has_the_namespace_layout",
    # A recording over REST replayed through the CLI; test_record's replays stay.
    "test_api.py::test_recording_replays_exactly",
    # `bench device` measuring the simulated device; its refusals and `device test` stay.
    "test_cli_device.py::test_bench_device_json_rows",
)


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("burrforce tiers")
    group.addoption("--all", action="store_true", dest="all_tiers",
                    help="run every tier (the fast tier and " + ", ".join(TIER_MARKERS)
                         + ") with the ci Hypothesis profile")
    group.addoption("--rest", action="store_true", dest="rest_tiers",
                    help="run only what the fast tier leaves out, with the ci Hypothesis "
                         "profile (.ci/run, after the fast tier)")


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's own (also tryfirst; registered earlier)
def pytest_cmdline_main(config: pytest.Config) -> None:
    """The fast tier, run as the README types it, spreads over every core (pytest-xdist), a
    module's tests on one worker so its module-scoped servers start once: most of its tests
    wait on sockets and processes, not the CPU (on 2 cores it takes about two thirds of the
    time it takes in one process). ``-n 0`` runs it in one process; ``--rest``, ``--all`` and
    named tests run in one unless ``-n`` says otherwise (compilers, containers and
    timing-sensitive device runs)."""
    if (hasattr(config, "workerinput") or not config.pluginmanager.hasplugin("xdist")
            or config.getoption("numprocesses", None) is not None
            or config.getoption("collectonly") or _tier_filter(config) != FAST_TIER):
        return
    if config.getoption("cov_source", None):
        # pytest-cov chose its mode (one process) before this hook: with --cov, spreading
        # takes an explicit -n (as .ci/run gives it).
        return
    config.option.numprocesses = "auto"
    if config.option.dist == "no":
        config.option.dist = "loadscope"


def _full_run(config: pytest.Config) -> bool:
    return bool(config.getoption("all_tiers") or config.getoption("rest_tiers"))


def pytest_configure(config: pytest.Config) -> None:
    # Before the test modules are imported: their @settings(max_examples=examples(n)) read it.
    hypothesis_profiles.load(_full_run(config))


def pytest_sessionstart(session: pytest.Session) -> None:
    """Fill the kernel cache first if ``burrforce compile`` has not (a fresh machine): once,
    in its parallel processes, instead of in whichever test first needs each kernel — there
    a hot loop starting on a cold cache would compile for longer than the test waits. Outside
    coverage (pytest-cov's COV_CORE_* would trace numba's compiler: several times slower)."""
    if compile_cache.is_complete():
        return
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if not k.startswith("COV_CORE_")}
    print("\nburrforce: compiling the kernels into the test cache first (once)...", flush=True)
    done = subprocess.run([sys.executable, "-m", "burrforce.server.cli", "compile", "--quiet"],
                          env=env, capture_output=True, text=True, timeout=900)
    if done.returncode != 0:
        pytest.exit(f"burrforce compile failed:\n{done.stdout}{done.stderr}", returncode=3)
    print(f"burrforce: {done.stdout.strip()}", flush=True)


def pytest_report_header(config: pytest.Config) -> str:
    from hypothesis import settings

    workers = config.getoption("numprocesses", None)
    spread = (f"; {workers} workers (pytest-xdist; -n 0: one process)"
              if isinstance(workers, int) and workers > 0 else "")
    return (f"burrforce: {_tier_filter(config) or 'every tier'}{spread}; hypothesis "
            f"max_examples={settings.default.max_examples} by default "
            f"(${hypothesis_profiles.ENV} picks a profile: ci, dev)")


def _tier_filter(config: pytest.Config) -> str | None:
    """The marker expression the run is narrowed to, or None for every test collected."""
    if config.getoption("rest_tiers"):
        return " or ".join(TIER_MARKERS)
    if config.getoption("all_tiers") or config.getoption("markexpr"):
        return None
    # Files or folders named on the command line: run what was named.
    if config.args_source != pytest.Config.ArgsSource.TESTPATHS:
        return None
    return FAST_TIER


def _tiers_of(item: pytest.Item) -> set[str]:
    path = Path(str(item.path)).resolve()
    relative = path.relative_to(TESTS).as_posix() if path.is_relative_to(TESTS) else ""
    try:
        own_code = inspect.getsource(item.function) if isinstance(item, pytest.Function) \
            else ""
    except (OSError, TypeError):
        own_code = ""
    fixtures = set(getattr(item, "fixturenames", ()))
    tiers = set()
    for tier, signals in TIER_SIGNALS.items():
        if (any(relative.startswith(f + "/") for f in signals.get("folders", ()))
                or path.name in signals.get("modules", ())
                or fixtures & set(signals.get("fixtures", ()))
                or any(c in own_code for c in signals.get("calls", ()))):
            tiers.add(tier)
    name = item.originalname if isinstance(item, pytest.Function) else item.name
    if path.name in SLOW or f"{path.name}::{name}" in SLOW:
        tiers.add("slow")
    return tiers


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        for tier in sorted(_tiers_of(item)):
            item.add_marker(tier)
    wanted = _tier_filter(config)
    if wanted is None:
        return
    in_fast_tier = wanted == FAST_TIER
    keep, drop = [], []
    for item in items:
        outside_fast = any(item.get_closest_marker(m) for m in TIER_MARKERS)
        (keep if outside_fast != in_fast_tier else drop).append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = keep
