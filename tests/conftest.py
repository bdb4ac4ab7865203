"""Tests run in float64 so gradient checks against finite differences are meaningful.

Forward accuracy in float32 is tested explicitly where it matters (`dtype` arguments,
`jnp.float32`).

JAX's persistent compilation cache is off by default, so every run compiles from cold; set
`DOFJAX_TEST_JAX_CACHE` to a directory to use one (the command-line tools the tests run
inherit it).
"""

import gc
import os

import jax
import pytest

jax.config.update("jax_enable_x64", True)


_CACHE = os.environ.get("DOFJAX_TEST_JAX_CACHE", "")
# the command-line tools the tests run (in this process or as subprocesses) use the same setting
# instead of their default cache directory
os.environ["DOFJAX_JAX_CACHE"] = _CACHE
if _CACHE:
    _settings = {"jax_compilation_cache_dir": _CACHE,
                 "jax_persistent_cache_min_compile_time_secs": 0.2,
                 "jax_persistent_cache_min_entry_size_bytes": 0}
    for name, value in _settings.items():
        jax.config.update(name, value)
        os.environ.setdefault(name.upper(), str(value))


# Every program XLA's CPU backend compiles keeps its machine code in a few memory maps for as
# long as JAX's caches hold it, and a test worker compiles thousands. Past Linux's per-process
# limit (vm.max_map_count, 65530 by default) LLVM cannot map the next program's code and the
# worker dies while compiling ("Unable to allocate section memory", or SIGSEGV). So the caches
# are cleared after any test that leaves more than half the limit in use.
def _map_count() -> int | None:
    try:
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:  # not Linux
        return None


def _map_limit() -> int:
    try:
        with open("/proc/sys/vm/max_map_count") as f:
            return int(f.read())
    except (OSError, ValueError):
        return 65530


_MAP_BUDGET = _map_limit() // 2


@pytest.fixture(autouse=True)
def _release_compiled_programs():
    yield
    count = _map_count()
    if count is not None and count > _MAP_BUDGET:
        jax.clear_caches()
        gc.collect()


# Should a worker still crash, xdist's file scheduler re-runs the rest of the crashed file on
# another worker, the crashed test included, but counts the crash as a failure; and a test that
# crashes every time makes it hang. So: the first crash of a test is reported as a re-run (that
# re-run decides the test's outcome) and listed at the end; a second crash of the same test
# ends the session.
_CRASHES: dict[str, int] = {}


@pytest.hookimpl(optionalhook=True)
def pytest_handlecrashitem(crashitem, report, sched):
    _CRASHES[crashitem] = _CRASHES.get(crashitem, 0) + 1
    if _CRASHES[crashitem] == 1:
        report.outcome = "rerun"
    else:
        pytest.exit(f"{crashitem} crashed its test worker twice", returncode=1)


def pytest_report_teststatus(report):
    if report.outcome == "rerun":
        return "rerun", "R", ("RERUN", {"yellow": True})
    return None


def pytest_terminal_summary(terminalreporter):
    if _CRASHES:
        terminalreporter.write_sep("=", "test workers that crashed", yellow=True)
        for nodeid, count in _CRASHES.items():
            outcome = ("the re-run is its reported outcome" if count == 1
                       else "the run was ended")
            terminalreporter.write_line(f"{nodeid}: crashed its worker {count}x; {outcome}")
