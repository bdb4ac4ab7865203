"""`python -m fit.sweep`: fits a data_gen sample with the model its target was made with."""

import numpy as np
import pytest

import dofjax
from data_gen import load_config
from data_gen._run import read_manifest, run
from fit.sweep import fit_record, true_camera

# one noise-free occluders sample: data_gen makes its target from the sharp render's peeled
# layers (config.target.layers, 2 by default), which write_rgbd stores in the sharp file
CONFIG = {
    "size": [40, 30],
    "kinds": {"occluders": 1.0},
    "scene": {"texture_size": 32},
    "camera": {"max_coc_px": 6.0},
    "noise": [{"model": "none", "weight": 1.0}],
}


@pytest.mark.slow
def test_sweep_fits_the_peeled_layers_the_target_was_made_with(tmp_path):
    out = str(tmp_path / "ds")
    run(out, 1, 5, load_config(CONFIG), progress=False)
    (rec,) = read_manifest(out)
    truth = rec["truth"]
    sharp, _ = dofjax.read_rgbd(f"{out}/{rec['files']['sharp']}")
    assert sharp.layers is not None
    target, _, _ = dofjax.read_exr(f"{out}/{rec['files']['target']}")
    # the premise: without its layers the model misses this target at the truth (so a sweep
    # that fitted colour and depth alone would be biased)
    true = true_camera(truth, 40, 30)
    single = np.asarray(dofjax.defocus(sharp.rgb, sharp.depth, true, window=16.0))
    assert np.sqrt(np.mean((single - target) ** 2)) > 1e-3
    row = fit_record(rec, out, np.random.default_rng(0), 16.0, 4, crb=False)
    assert abs(row["rel_err_focus_distance"]) < 1e-3, row
    assert abs(row["rel_err_aperture_radius"]) < 1e-3, row
