"""`python -m fit.sweep`: fits a data_gen sample with the model its target was made with."""

import json
import sys

import numpy as np
import pytest

import dofjax
from data_gen import load_config
from data_gen._run import read_manifest, run
from fit import sweep
from fit._clipped import clipped_mask, unclipped
from fit.sweep import fit_record, true_camera

# one noise-free occluders sample: data_gen makes its target from the sharp render's peeled
# layers (config.target.layers, 2 by default), which write_rgbd stores in the sharp file
CONFIG = {
    "size": [40, 30],
    "kinds": {"occluders": 1.0},
    "scene": {"texture_size": 32},
    "camera": {"max_coc_px": 6.0},
    "target": {"method": "defocus"},
    "noise": [{"model": "none", "weight": 1.0}],
}


@pytest.mark.slow
def test_sweep_fits_the_peeled_layers_the_target_was_made_with(tmp_path, monkeypatch, capsys):
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
    # the whole command where matplotlib (the bench extra) is not installed: the results are
    # written, the plots skipped with a note, and it ends normally
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # `import matplotlib` raises
    result = tmp_path / "sweep"
    sweep.main([f"{out}/manifest.jsonl", "--window", "16", "--starts", "4", "--no-crb",
                "--out", str(result)])
    printed = capsys.readouterr()
    assert "sweep: no plots (matplotlib is not installed" in printed.err
    assert f"wrote {result}/sweep.jsonl, sweep.md" in printed.out
    assert (result / "sweep.md").exists() and not (result / "sweep_noise.png").exists()
    with open(result / "sweep.jsonl") as f:
        (line,) = f.read().splitlines()
    assert abs(json.loads(line)["rel_err_focus_distance"]) < 1e-3


def test_clipped_pixels_are_left_out_of_the_fit():
    # the noise models that clip at 1 (8-bit sRGB, quantize, a saturating sensor) mark the
    # pixels where any channel reached it; the others clip nothing
    target = np.full((2, 3, 3), 0.5)
    target[0, 0] = (1.0, 0.2, 0.2)  # one channel at the 8-bit maximum
    target[1, 2] = 0.9995  # within 4 read-noise sigmas of a full well
    expect = np.ones((2, 3), bool)
    expect[0, 0] = False
    for noise in ({"model": "srgb8"}, {"model": "gaussian", "sigma": 0.01, "quantize": True}):
        np.testing.assert_array_equal(unclipped(target, noise), expect)
    expect[1, 2] = False
    saturating = {"model": "poisson_gaussian", "full_well": 1000.0, "read_noise": 2.0,
                  "saturate": True}
    np.testing.assert_array_equal(unclipped(target, saturating), expect)
    for noise in ({"model": "none"}, {"model": "gaussian", "sigma": 0.01},
                  {**saturating, "saturate": False}):
        assert unclipped(target, noise) is None
    # fit.recover: an explicit level wins, else a data_gen target's noise metadata, else none
    np.testing.assert_array_equal(clipped_mask(target, 0.6, {"model": "none"}),
                                  np.all(target < 0.6, axis=-1))
    np.testing.assert_array_equal(clipped_mask(target, None, saturating), expect)
    assert clipped_mask(target, None, None) is None


def test_default_aperture_bound_holds_a_data_gen_truth():
    # data_gen sample 47 of seed 11 at 256 x 256: depths 1.08-7.52, focus 4.05, largest CoC
    # 14.95 px (config max 16). The bound's reach is the CoC at the focus that blurs the scene
    # most (half the nearest depth), 2.5x the truth's here: 32 px (the old default) put its
    # aperture out of bounds and the fit ended at the bound (d +643 %); 8 windows hold it.
    from fit.sweep import guess_and_bounds, reach

    depth = np.linspace(1.08, 7.52, 64 * 256).reshape(64, 256)
    fov, d = 50.0, 4.05
    k = 256 / (2.0 * np.tan(np.radians(fov) / 2.0))
    true_a = 14.95 / (k * max(abs(1 / d - 1 / 1.08), abs(1 / d - 1 / 7.52)))
    rng = np.random.default_rng(0)
    assert guess_and_bounds(rng, depth, fov, 32.0)[2]["aperture_radius"][1] < true_a
    assert reach(None, 16.0) == 128.0 and reach(40.0, 16.0) == 40.0
    lo, hi = guess_and_bounds(rng, depth, fov, reach(None, 16.0))[2]["aperture_radius"]
    assert lo < true_a < hi


def test_fit_model_options_are_checked_before_any_fit(tmp_path, capsys):
    from fit import sweep

    for argv, msg in ((["--samples", "64"], "--samples is for --method lens only"),
                      (["--method", "lens", "--subapertures", "4"],
                       "--subapertures is for --method sliced only")):
        with pytest.raises(SystemExit):
            sweep.main([str(tmp_path / "manifest.jsonl")] + argv)
        assert msg in capsys.readouterr().err


@pytest.mark.slow
def test_sweep_fits_a_sharp_file_with_a_guard_band(tmp_path):
    """config.target.margin: the sharp file covers a guard band beyond the frame (recorded in
    the manifest); the target is made with it and the sweep fits with it (fit_focus margin=)
    and a Cramer-Rao bound that takes no information from the band."""
    out = str(tmp_path / "ds")
    noisy = {**CONFIG, "noise": [{"model": "gaussian", "weight": 1.0, "sigma": 0.01}],
             "target": {"method": "defocus", "margin": 5}}
    run(out, 1, 5, load_config(noisy), progress=False)
    (rec,) = read_manifest(out)
    assert rec["truth"]["margin"] == 5
    sharp, meta = dofjax.read_rgbd(f"{out}/{rec['files']['sharp']}")
    assert np.shape(sharp.depth) == (40, 50) and meta["margin"] == 5
    clean = dofjax.read_exr_layers(f"{out}/{rec['files']['target']}")["clean"]
    true = true_camera(rec["truth"], 40, 30)
    np.testing.assert_allclose(dofjax.defocus(sharp, true, margin=5, window=16.0), clean,
                               atol=1e-5)
    row = fit_record(rec, out, np.random.default_rng(0), 16.0, 4)
    for name in ("focus_distance", "aperture_radius"):
        assert 0 < row[f"rel_crb_{name}"] < 0.05
        assert abs(row[f"rel_err_{name}"]) < 4 * row[f"rel_crb_{name}"], row


def test_data_gen_guard_band_defaults_to_reference_targets_only():
    from data_gen._config import sharp_margin

    cfg = load_config(CONFIG)
    assert cfg["target"]["margin"] == "auto" and sharp_margin(cfg) == 0
    ref = load_config({**CONFIG, "target": {"method": "reference"}})
    assert sharp_margin(ref) == 6 + 2  # ceil(camera.max_coc_px) + 2
    with pytest.raises(ValueError, match="config.target.margin"):
        load_config({**CONFIG, "target": {"margin": -1}})


def test_summary_reports_how_often_an_ok_fit_is_within_3_standard_errors():
    from fit.sweep import summarise

    def row(err_d, se_d, err_a, se_a, identifiable=True, converged=True):
        r = {"kind": "planes", "noise": "none", "sigma": float("nan"), "method": "reference",
             "result": {"identifiable": identifiable, "converged": converged,
                        "ok": identifiable and converged, "ambiguous": False}}
        for name, e, se in (("focus_distance", err_d, se_d), ("aperture_radius", err_a, se_a)):
            r.update({f"rel_err_{name}": e, f"rel_se_{name}": se, f"rel_se_tiles_{name}": se,
                      f"rel_crb_{name}": float("nan")})
        return r

    rows = [row(0.01, 0.01, -0.02, 0.01),  # within 3 SE: z = 1, -2
            row(0.05, 0.01, 0.0, 0.01),  # d 5 SE off
            row(0.01, float("nan"), 0.0, 0.01),  # no SE: never within
            row(0.5, 0.01, 0.5, 0.01, identifiable=False)]  # flagged: not counted
    line = next(ln for ln in summarise(rows).splitlines() if "planes" in ln)
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[-4:-2] == ["75%", "1/3"]
    # rms of z over the ok fits: d (1, 5, inf) -> inf; A (-2, 0, 0) -> sqrt(4 / 3)
    assert cells[-2] == "inf" and cells[-1] == f"{(4 / 3) ** 0.5:.2f}"
