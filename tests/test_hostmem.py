"""dofjax.tune_host_memory: what it sets, when it refuses, and that results do not change.

Each case runs in a fresh interpreter: the XLA part only applies before JAX starts its backend,
and the allocator settings are process-wide.
"""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from dofjax._hostmem import FLAG, HEAP_BYTES

# a small defocus and its gradient (printed as JSON), after tune_host_memory() or not
PROGRAM = """
import json, os, sys, warnings
import numpy as np
import dofjax
out = {}
if sys.argv[1] == "tune":
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out["tuned"] = dofjax.tune_host_memory()
    out["warnings"] = [str(w.message) for w in caught]
out["xla_flags"] = os.environ.get("XLA_FLAGS", "")
import jax, jax.numpy as jnp
rng = np.random.default_rng(0)
rgb = rng.random((40, 48, 3)).astype(np.float32)
depth = np.where(np.arange(48)[None, :] < 20, 1.5, 4.0).astype(np.float32) * np.ones((40, 1))
cam = dofjax.Camera(width=48, height=40, fov=40.0, focus_distance=2.0, aperture_radius=0.05)
f = dofjax.defocus_fn(rgb, depth, cam, window=8.0, method="sliced", hidden=True)
img = jax.jit(lambda p: f(p[0], p[1]))(jnp.asarray([2.0, 0.05]))
g = jax.jit(jax.grad(lambda p: jnp.mean(f(p[0], p[1]) ** 2)))(jnp.asarray([2.0, 0.05]))
out["image"] = np.asarray(img).ravel().tolist()
out["grad"] = np.asarray(g).tolist()
if len(sys.argv) > 2:  # a second call, after the backend started
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out["again"] = dofjax.tune_host_memory()
    out["again_warnings"] = [str(w.message) for w in caught]
print(json.dumps(out))
"""


def _run(*args, xla_flags=""):
    env = dict(os.environ, XLA_FLAGS=xla_flags, JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", PROGRAM, *args], env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def plain():
    return _run("plain")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt: Linux only")
def test_sets_the_xla_heap_limit_and_the_allocator_before_jax_starts(plain):
    out = _run("tune", "again")
    assert out["tuned"] == {"xla": True, "allocator": True}
    assert out["warnings"] == []
    assert f"{FLAG}={HEAP_BYTES}" in out["xla_flags"].split()
    # only where buffers live changes: the same image and gradient, bit for bit
    assert np.array_equal(out["image"], plain["image"])
    assert np.array_equal(out["grad"], plain["grad"])
    assert np.all(np.isfinite(out["grad"])) and np.any(np.asarray(out["grad"]) != 0.0)
    # called again once JAX runs: the flag is already there, so nothing to warn about
    assert out["again"]["xla"] and out["again_warnings"] == []


def test_after_jax_started_it_warns_and_reports_the_xla_part_missing():
    out = _run("plain", "again")
    assert out["again"]["xla"] is False
    assert len(out["again_warnings"]) == 1
    message = out["again_warnings"][0]
    assert "already started" in message and f"{FLAG}={HEAP_BYTES}" in message


def test_keeps_a_heap_limit_the_user_set():
    mine = f"{FLAG}=8388608"
    out = _run("tune", xla_flags=mine)
    assert out["tuned"]["xla"] is True and out["warnings"] == []
    assert out["xla_flags"] == mine
