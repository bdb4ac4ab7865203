"""How the suite keeps its pytest-xdist workers alive (tests/conftest.py): compiled programs
are released before a worker runs out of memory maps; a test that crashes its worker once is
re-run and reported; one that crashes it every time ends the session instead of hanging it."""

import os
import shutil
import subprocess
import sys

import pytest

pytest.importorskip("xdist")

_TEST = """
import os, signal

def test_before():
    pass

def test_crashes():
    if os.environ.get("ALWAYS") or not os.path.exists("crashed"):
        open("crashed", "w").close()
        os.kill(os.getpid(), signal.SIGSEGV)

def test_after():
    pass
"""


def _run(tmp_path, always):
    shutil.copy(os.path.join(os.path.dirname(__file__), "conftest.py"), tmp_path)
    (tmp_path / "test_a.py").write_text(_TEST)
    (tmp_path / "test_b.py").write_text("def test_other():\n    pass\n")
    env = dict(os.environ, ALWAYS="1" if always else "")
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "2",
         "--dist", "loadfile", "."],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)


def test_a_crash_once_is_rerun_and_listed(tmp_path):
    run = _run(tmp_path, always=False)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "4 passed, 1 rerun" in run.stdout
    assert "test_a.py::test_crashes: crashed its worker 1x" in run.stdout


def test_a_crash_every_time_ends_the_session(tmp_path):
    run = _run(tmp_path, always=True)
    assert run.returncode == 1, run.stdout + run.stderr
    assert "test_a.py::test_crashes crashed its test worker twice" in run.stdout + run.stderr


_MAPS_TEST = """
import jax, jax.numpy as jnp
import conftest

f = jax.jit(jnp.sin)

def test_compiles_with_the_maps_over_budget():
    f(jnp.ones(3))
    assert f._cache_size() == 1
    conftest._MAP_BUDGET = 0  # every process is over it

def test_the_previous_programs_were_released():
    assert conftest._map_count() > 0
    assert f._cache_size() == 0
"""


def test_compiled_programs_are_released_past_the_map_budget(tmp_path):
    shutil.copy(os.path.join(os.path.dirname(__file__), "conftest.py"), tmp_path)
    (tmp_path / "test_maps.py").write_text(_MAPS_TEST)
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
         "test_maps.py"], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "2 passed" in run.stdout
