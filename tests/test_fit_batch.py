"""fit_focus_batch sharded over 2 (forced) host devices gives the same results as on one device.

XLA_FLAGS must be set before jax initialises, so the check runs in a subprocess.
"""

import os
import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent(
    """
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np
    from dofjax import Camera, fit_focus_batch
    from tests.test_fit import KW, blur_model, scene

    assert len(jax.devices()) == 2, jax.devices()
    rgb, depth = scene()
    cam = Camera(width=32, height=32, fov=60.0, focus_distance=2.5, aperture_radius=0.05)
    truths = [(1.7, 0.08), (3.0, 0.06), (1.2, 0.03)]  # odd B: padded to 4 on 2 devices
    targets = jnp.stack([blur_model(rgb, depth, cam.replace(focus_distance=d, aperture_radius=a))
                         for d, a in truths])
    # fixed noise: at a noise-free optimum the loss (and so every standard error) is float
    # rounding, which differs in its last digits between two compiled programs
    noise = np.random.default_rng(0).normal(0.0, 1e-3, targets.shape)
    targets = targets + noise
    kw = dict(KW, starts=8)  # more than 4 starts deadlocked with LAPACK QR (dofjax._linalg)
    sharded = fit_focus_batch(targets, rgb, depth, cam, **kw)
    single = fit_focus_batch(targets, rgb, depth, cam, devices=jax.devices()[:1], **kw)
    for name in ("focus_distance", "aperture_radius", "focus_distance_se",
                 "focus_distance_se_tiles", "loss", "steps"):
        a, b = np.asarray(getattr(sharded, name)), np.asarray(getattr(single, name))
        assert a.shape == (3,), (name, a.shape)
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-300, err_msg=name)
    # within 4 standard errors of the truth (noise 1e-3 moves the estimates by about one)
    err = np.abs(np.asarray(sharded.focus_distance) - [1.7, 3.0, 1.2])
    assert np.all(err < 4.0 * np.asarray(sharded.focus_distance_se)), (err, sharded)
    assert sharded.message == single.message
    print("OK")
    """
)


def test_sharded_equals_unsharded():
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
               JAX_PLATFORMS="cpu", PYTHONPATH=root)
    try:  # ~40 s on 2 cores; a deadlock (idle CPU) must fail, not stall the suite
        out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, cwd=root,
                             capture_output=True, text=True, timeout=400)
    except subprocess.TimeoutExpired:
        pytest.fail("fit_focus_batch on 2 host devices did not finish in 400 s (deadlock?)")
    assert out.returncode == 0, out.stderr[-4000:]
    assert out.stdout.strip().endswith("OK")
