"""data_gen: config errors, noise statistics, seeds, determinism, resume, metadata, re-rendering.

The generating tests share one small data set (32x32, the two cheapest kinds) made once per module,
because each scene kind costs one ray-caster compile.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil

import numpy as np
import pytest

import data_gen
from data_gen import ConfigError, apply_noise, draw_noise_params, load_config, sample_rng
from data_gen._noise import quantize_srgb8, srgb_decode, srgb_encode
from data_gen._run import dry_run, finished_record, plan_sample, read_manifest, run, sample_files

SMALL = {
    "size": [32, 32],
    "kinds": {"single_plane": 1.0, "planes": 1.0},
    "scene": {"texture_size": 32},
    "camera": {"max_coc_px": 3.0},
    "target": {"method": "defocus"},  # the model's own targets: exact self-consistency
    "noise": [
        {"model": "none", "weight": 1.0},
        {"model": "gaussian", "weight": 1.0, "sigma": [0.01, 0.02]},
        {"model": "poisson_gaussian", "weight": 1.0, "full_well": 1000.0, "read_noise": 2.0},
        {"model": "srgb8", "weight": 1.0},
    ],
}
COUNT = 4
SEED = 7


def _digest(root: str) -> dict[str, str]:
    """sha256 of every file under root, by relative path."""
    out = {}
    for dirpath, _, names in os.walk(root):
        for name in names:
            p = os.path.join(dirpath, name)
            with open(p, "rb") as f:
                out[os.path.relpath(p, root)] = hashlib.sha256(f.read()).hexdigest()
    return out


def _lines(path: str) -> list[str]:
    with open(path) as f:
        return f.read().splitlines()


@pytest.fixture(scope="module")
def small_cfg():
    return load_config(SMALL)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, small_cfg):
    out = str(tmp_path_factory.mktemp("dg") / "a")
    summary = run(out, COUNT, SEED, small_cfg, progress=False)
    return out, summary


# ------------------------------------------------------------------------------------------------
# Config and dry run (no rendering)


def test_default_config_validates():
    cfg = load_config()
    assert cfg["size"] == [256, 256]
    assert cfg["target"]["method"] == "reference"  # lens-sampled, as a photograph
    assert set(cfg["kinds"]) == set(data_gen.KINDS)


@pytest.mark.parametrize(
    "user, needle",
    [
        ({"kinds": {"planes": 1, "bogus": 1}}, "config.kinds: unknown key(s) ['bogus']"),
        ({"kinds": {"planes": 0, "mirror": 0}}, "config.kinds: weights must sum to > 0"),
        ({"kinds": {"planes": -1}}, "config.kinds.planes: weight must be >= 0"),
        ({"colour": 1}, "config: unknown key(s) ['colour']; allowed keys are"),
        ({"camera": {"aperture_radius": [0.1, 0.01]}}, "config.camera.aperture_radius: lo must be"),
        ({"camera": {"fov": [10, 200]}}, "config.camera.fov: both ends must be in (0, 180)"),
        ({"camera": {"focus_distance": -1}}, "config.camera.focus_distance: must be > 0"),
        ({"camera": {"model": "pinhole"}}, "config.camera.model: must be one of"),
        ({"camera": {"model": "photographic", "fov": 40}}, "unknown key(s) ['fov']"),
        ({"camera": {"model": "photographic", "focus_distance": 0.05}},
         "config.camera.focus_distance: must exceed the focal length"),
        ({"scene": {"depth_range": [5, 10]}}, "config.scene.depth_range: need hi >= 4 lo"),
        ({"scene": {"depth_range": [5]}}, "config.scene.depth_range: a range must be [lo, hi]"),
        ({"camera": {"min_coc_px": 8, "max_coc_px": 4}}, "min_coc_px: must be <= max_coc_px"),
        ({"camera": {"max_coc_px": [1, 2]}}, "config.camera.max_coc_px: must be a number or null"),
        ({"scene": {"skimage_fraction": 1.0, "skimage_textures": ["brick", "moon"]}},
         "a scene needs up to 5 distinct images"),
        ({"scene": {"skimage_textures": ["nosuchimage"]}}, "'nosuchimage' is not a scikit-image"),
        ({"scene": {"procedural_textures": ["plaid"]}}, "unknown pattern 'plaid'"),
        ({"target": {"method": "magic"}}, "config.target.method: must be one of"),
        ({"target": {"layers": 0}}, "config.target.layers: must be an integer >= 1"),
        ({"target": {"window": 0}}, "config.target.window: must be > 0"),
        ({"target": {"window": 8}}, "config.target.window: must be >= config.camera.max_coc_px"),
        ({"noise": []}, "config.noise: must be a non-empty list"),
        ({"noise": [{"model": "salt"}]}, "config.noise[0].model: must be one of"),
        ({"noise": [{"model": "gaussian"}]}, "missing parameter 'sigma'"),
        ({"noise": [{"model": "gaussian", "sigma": 0.1, "mu": 1}]}, "unknown key(s) ['mu']"),
        ({"noise": [{"model": "none", "weight": 0}]}, "config.noise: weights must sum to > 0"),
        ({"size": [0, 32]}, "config.size[0] (width): must be an integer >= 1"),
    ],
)
def test_config_errors(user, needle):
    with pytest.raises(ConfigError) as info:
        load_config(user)
    assert needle in str(info.value)


def test_config_file_errors(tmp_path):
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(str(tmp_path / "missing.json"))
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ConfigError, match="is not valid JSON"):
        load_config(str(bad))


def test_photographic_config_merges_its_own_defaults():
    cfg = load_config({"camera": {"model": "photographic", "f_number": 2.8}})
    assert cfg["camera"]["f_number"] == 2.8
    assert cfg["camera"]["focal_length"] == [0.024, 0.085]
    assert "fov" not in cfg["camera"] and "aperture_radius" not in cfg["camera"]


def test_dry_run_counts_match_the_generator_plan(small_cfg, capsys):
    text = dry_run(small_cfg, 50, SEED)
    kinds = [plan_sample(small_cfg, SEED, i)["kind"] for i in range(50)]
    for kind in ("single_plane", "planes"):
        line = next(line for line in text.splitlines() if line.strip().startswith(kind))
        assert int(line.split()[1]) == kinds.count(kind)
    assert "32x32 px" in text and "target: defocus" in text
    assert "poisson_gaussian" in text and "'full_well': 1000.0" in text
    # The CLI prints the same plan and renders nothing.
    from data_gen.__main__ import main

    assert main(["--out", "unused", "--count", "50", "--seed", str(SEED), "--size", "32x32",
                 "--dry-run"]) == 0
    assert "data_gen plan: 50 samples" in capsys.readouterr().out
    assert not os.path.exists("unused")


def test_cli_reports_config_errors(tmp_path, capsys):
    from data_gen.__main__ import main

    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps({"kinds": {"volcano": 1}}))
    assert main(["--out", str(tmp_path / "o"), "--count", "1", "--seed", "0", "--config",
                 str(cfg)]) == 2
    assert "config.kinds: unknown key(s) ['volcano']" in capsys.readouterr().err
    assert main(["--out", "o", "--count", "1", "--seed", "0", "--size", "32by32"]) == 2
    assert "--size: expected WxH" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------
# Seeds and noise (numpy only)


def test_sample_streams_are_order_independent_and_distinct():
    a = sample_rng(5, 3, "noise").standard_normal(4)
    sample_rng(5, 2, "noise").standard_normal(100)  # drawing other samples changes nothing
    b = sample_rng(5, 3, "noise").standard_normal(4)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, sample_rng(5, 4, "noise").standard_normal(4))
    assert not np.array_equal(a, sample_rng(6, 3, "noise").standard_normal(4))
    assert not np.array_equal(a, sample_rng(5, 3, "scene").standard_normal(4))


def test_noise_none_is_identity():
    x = np.random.default_rng(0).uniform(0, 3, (8, 8, 3)).astype(np.float32)
    np.testing.assert_array_equal(apply_noise(x, {"model": "none"}, sample_rng(0, 0, "noise")), x)


def test_gaussian_noise_statistics():
    x = np.full((200, 200, 3), 0.4)
    sigma = 0.05
    y = apply_noise(x, {"model": "gaussian", "sigma": sigma}, sample_rng(1, 0, "noise"))
    r = y.astype(np.float64) - x
    n = r.size
    # Mean within 5 standard errors; variance within 5 standard errors (var of s^2 = 2 s^4 / n).
    assert abs(r.mean()) < 5 * sigma / np.sqrt(n)
    assert abs(r.var() - sigma**2) < 5 * sigma**2 * np.sqrt(2 / n)


@pytest.mark.parametrize("level", [0.02, 0.5, 3.0])
def test_poisson_gaussian_noise_statistics(level):
    full_well, read = 2000.0, 5.0
    x = np.full((200, 200, 3), level)
    params = {"model": "poisson_gaussian", "full_well": full_well, "read_noise": read,
              "saturate": False, "quantize": False}
    y = apply_noise(x, params, sample_rng(2, 0, "noise")).astype(np.float64)
    n = y.size
    var = level / full_well + (read / full_well) ** 2  # shot + read noise, in image units
    assert abs(y.mean() - level) < 5 * np.sqrt(var / n)
    # Var of the sample variance ~ 2 var^2 / n for near-Gaussian data (Poisson at these counts).
    assert abs(y.var() - var) < 6 * var * np.sqrt(2 / n)


def test_poisson_shot_noise_scales_with_signal_and_saturates():
    rng = sample_rng(3, 0, "noise")
    params = {"model": "poisson_gaussian", "full_well": 500.0, "read_noise": 0.0,
              "saturate": True, "quantize": False}
    y = apply_noise(np.full((100, 100, 3), 2.0), params, rng)
    assert y.max() <= 1.0  # electron counts clip at the full well
    lo = apply_noise(np.full((200, 200, 3), 0.1), params, rng).astype(np.float64)
    # Pure shot noise: electron counts are integers and their variance equals their mean.
    e = lo * 500.0
    np.testing.assert_allclose(e, np.round(e), atol=1e-3)
    assert abs(e.var() / e.mean() - 1.0) < 0.05


def test_srgb8_quantisation():
    x = np.linspace(-0.1, 1.5, 4001)[:, None, None] * np.ones((1, 1, 3))
    y = apply_noise(x, {"model": "srgb8"}, sample_rng(0, 0, "noise")).astype(np.float64)
    codes = srgb_encode(y) * 255.0
    np.testing.assert_allclose(codes, np.round(codes), atol=1e-3)  # only 8-bit code values
    assert y.min() == 0.0 and y.max() == pytest.approx(1.0)  # clipped to [0, 1]
    inside = (x > 0.01) & (x < 0.99)
    err = srgb_encode(y[inside]) - srgb_encode(x[inside])
    # Rounding to the nearest code: error at most half a code, mean ~0, variance ~1/12 code^2.
    assert np.abs(err).max() <= 0.5 / 255 + 1e-9
    assert abs(err.mean()) < 0.05 / 255
    assert abs(err.var() * 255**2 - 1 / 12) < 0.01
    np.testing.assert_allclose(srgb_decode(srgb_encode(x.clip(0, 1))), x.clip(0, 1), atol=1e-12)
    np.testing.assert_array_equal(quantize_srgb8(y).astype(np.float32), y)  # idempotent


def test_noise_params_drawn_in_range():
    spec = {"model": "gaussian", "weight": 1.0, "sigma": [0.001, 0.1], "quantize": True}
    vals = [draw_noise_params(spec, sample_rng(0, i, "noise"))["sigma"] for i in range(300)]
    assert min(vals) >= 0.001 and max(vals) <= 0.1
    # Log-uniform: the median of log sigma is near the middle of the log range.
    assert abs(np.median(np.log(vals)) - np.log(0.01)) < 0.4
    p = draw_noise_params(spec, sample_rng(0, 0, "noise"))
    assert p["model"] == "gaussian" and p["quantize"] is True


# ------------------------------------------------------------------------------------------------
# Generated data sets


def test_dataset_layout_and_manifest(dataset, small_cfg):
    out, summary = dataset
    assert summary.generated == COUNT and summary.skipped == 0
    assert summary.bytes_on_disk > 0 and summary.samples_per_second > 0
    records = read_manifest(out)
    assert [r["index"] for r in records] == list(range(COUNT))
    for r in records:
        for role in ("scene", "sharp", "target"):
            assert not os.path.isabs(r["files"][role])
            assert os.path.getsize(os.path.join(out, r["files"][role])) == r["bytes"][role]
        assert r["kind"] == plan_sample(small_cfg, SEED, r["index"])["kind"]
        assert r["identifiable"] == (r["kind"] != "single_plane")
        t = r["truth"]
        assert t["width"] == 32 and t["height"] == 32
        # The largest blur lies in [min_coc_px, max_coc_px] unless the aperture range is too
        # small to reach min_coc_px (then the aperture is the configured maximum).
        assert t["max_coc_px"] <= 3.0 * (1 + 1e-6)
        assert t["max_coc_px"] >= 1.0 * (1 - 1e-6) or t["aperture_radius"] == np.float32(0.5)
        assert t["depth_min"] <= t["depth_max"]


def test_metadata_matches_the_camera_used(dataset, small_cfg):
    import dofjax

    out, _ = dataset
    for r in read_manifest(out):
        i = r["index"]
        _, _, meta = dofjax.read_exr(os.path.join(out, r["files"]["target"]))
        sharp_meta = dofjax.read_exr_metadata(os.path.join(out, r["files"]["sharp"]))
        s = data_gen.build_sample(small_cfg, SEED, i)  # rebuild in memory: the camera used
        cam = s["camera"]
        for m in (meta, sharp_meta):
            assert m["focus_distance"] == float(cam.focus_distance)
            assert m["aperture_radius"] == float(cam.aperture_radius)
            assert m["fov"] == float(cam.fov)
            assert m["seed"] == SEED and m["index"] == i
            assert m["kind"] == r["kind"] and m["identifiable"] == r["identifiable"]
            assert m["method"] == "defocus"
            assert m["noise"] == r["noise"] and m["noise_model"] == r["noise"]["model"]
        assert r["truth"]["focus_distance"] == float(cam.focus_distance)
        assert r["truth"]["aperture_radius"] == float(cam.aperture_radius)
        # The stored target is the in-memory one (noise included), bit for bit.
        rgb, _, _ = dofjax.read_exr(os.path.join(out, r["files"]["target"]))
        np.testing.assert_array_equal(rgb, s["target"])


def test_photographic_camera_metadata(tmp_path, small_cfg):
    import dofjax

    cfg = load_config({**SMALL, "kinds": {"single_plane": 1.0},
                       "camera": {"model": "photographic", "max_coc_px": 3.0}})
    out = str(tmp_path / "photo")
    run(out, 2, SEED, cfg, progress=False)
    for r in read_manifest(out):
        t = r["truth"]
        meta = dofjax.read_exr_metadata(os.path.join(out, r["files"]["target"]))
        assert meta["camera_model"] == "photographic"
        assert 0.024 <= t["focal_length"] <= 0.085 and t["sensor_width"] == 0.036
        assert 1.4 * (1 - 1e-6) <= t["f_number"]
        # A = f / (2N) and fov = 2 atan(S / 2f) (Camera.from_photographic), to float32 rounding.
        assert t["aperture_radius"] == pytest.approx(t["focal_length"] / (2 * t["f_number"]),
                                                     rel=1e-6)
        fov = np.degrees(2 * np.arctan(t["sensor_width"] / (2 * t["focal_length"])))
        assert t["fov"] == pytest.approx(fov, rel=1e-6)
        assert meta["f_number"] == t["f_number"] and meta["focal_length"] == t["focal_length"]


def test_reference_target(tmp_path):
    import jax

    import dofjax

    if not hasattr(dofjax, "render_reference"):
        pytest.skip("dofjax.render_reference has not landed yet")
    cfg = load_config({**SMALL, "kinds": {"single_plane": 1.0}, "noise": [{"model": "none"}],
                       "target": {"method": "reference", "reference_spp": 4}})
    out = str(tmp_path / "ref")
    run(out, 1, SEED, cfg, progress=False)
    (r,) = read_manifest(out)
    assert r["method"] == "reference"
    rgb, _, meta = dofjax.read_exr(os.path.join(out, r["files"]["target"]))
    assert meta["method"] == "reference" and meta["spp"] == 4
    # The target is the lens-sampling reference of the saved scene and camera with the recorded key.
    scene = dofjax.load_scene(os.path.join(out, r["files"]["scene"]))
    cam = dofjax.load_camera(os.path.join(out, r["files"]["scene"]))
    again = dofjax.render_reference(scene, cam, spp=4,
                                    key=jax.random.key(r["truth"]["reference_key"]))
    np.testing.assert_array_equal(np.asarray(again, np.float32), rgb)
    # the sharp file carries the configured peeled layers for a reference target too (what a
    # fit of it needs to model the hidden surfaces)
    sharp, _ = dofjax.read_rgbd(os.path.join(out, r["files"]["sharp"]))
    assert sharp.layers is not None and sharp.layers.depth.shape[0] == cfg["target"]["layers"]


def test_scene_json_rerenders_to_the_sharp_image(dataset, small_cfg):
    import dofjax

    out, _ = dataset
    for r in read_manifest(out):
        scene = dofjax.load_scene(os.path.join(out, r["files"]["scene"]))
        rgbd, meta = dofjax.read_rgbd(os.path.join(out, r["files"]["sharp"]))
        cam = dofjax.load_camera(os.path.join(out, r["files"]["scene"]))
        assert (cam.width, cam.height) == (meta["width"], meta["height"])
        for name in ("fov", "focus_distance", "aperture_radius"):
            assert float(getattr(cam, name)) == meta[name]
        for name in ("eye", "target", "up"):
            assert np.asarray(getattr(cam, name)).tolist() == meta[name]
        again = dofjax.render(scene, cam, spp=small_cfg["target"]["sharp_spp"],
                              layers=small_cfg["target"]["layers"])
        np.testing.assert_array_equal(np.asarray(again.rgb, np.float32), np.asarray(rgbd.rgb))
        np.testing.assert_array_equal(np.asarray(again.depth, np.float32),
                                      np.asarray(rgbd.depth))


def test_noise_recorded_and_applied(dataset):
    import dofjax

    out, _ = dataset
    for r in read_manifest(out):
        layers = dofjax.read_exr_layers(os.path.join(out, r["files"]["target"]))
        if r["noise"]["model"] == "none":
            assert "clean" not in layers
        else:
            # The noise-free target travels along as layer "clean"; re-applying the recorded model
            # with the sample's noise stream reproduces the stored noisy target exactly.
            again = apply_noise(layers["clean"], r["noise"],
                                sample_rng(SEED, r["index"], "noise_pixels"))
            np.testing.assert_array_equal(again, layers["rgb"])


def test_same_seed_same_bytes(dataset, small_cfg, tmp_path):
    out, _ = dataset
    other = str(tmp_path / "b")
    run(other, COUNT, SEED, small_cfg, progress=False)
    assert _digest(other) == _digest(out)
    # A different seed gives different data.
    third = str(tmp_path / "c")
    run(third, 1, SEED + 1, small_cfg, progress=False)
    a = _digest(out)[sample_files(0)["target"]]
    assert _digest(third)[sample_files(0)["target"]] != a


def test_resume_after_interrupted_run(dataset, small_cfg, tmp_path):
    out, _ = dataset
    want = _digest(out)
    work = str(tmp_path / "resume")
    shutil.copytree(out, work)
    files = sample_files(1)
    # Interrupt sample 1 mid-write: truncated target, no record; sample 2 lost its sharp file;
    # the manifest lost a line; a temporary file is left behind.
    with open(os.path.join(work, files["target"]), "r+b") as f:
        f.truncate(100)
    os.remove(os.path.join(work, files["record"]))
    os.remove(os.path.join(work, sample_files(2)["sharp"]))
    with open(os.path.join(work, "manifest.jsonl")) as f:
        lines = f.readlines()
    with open(os.path.join(work, "manifest.jsonl"), "w") as f:
        f.writelines(lines[:-1])
    with open(os.path.join(work, sample_files(3)["target"] + ".tmp123.exr"), "w") as f:
        f.write("junk")
    # sample 0's sharp file has one byte flipped (same size): its sha256 tells
    sharp0 = os.path.join(work, sample_files(0)["sharp"])
    with open(sharp0, "r+b") as f:
        f.seek(os.path.getsize(sharp0) // 2)
        byte = f.read(1)
        f.seek(-1, os.SEEK_CUR)
        f.write(bytes([byte[0] ^ 0xFF]))
    assert finished_record(work, 1) is None and finished_record(work, 2) is None
    assert finished_record(work, 0) is None
    assert finished_record(work, 3) is not None
    summary = run(work, COUNT, SEED, small_cfg, progress=False)
    assert summary.skipped == COUNT - 3 and summary.generated == 3
    assert _digest(work) == want


def test_extending_a_data_set_keeps_its_samples(dataset, small_cfg, tmp_path):
    out, _ = dataset
    work = str(tmp_path / "more")
    shutil.copytree(out, work)
    before = _digest(out)
    summary = run(work, COUNT + 1, SEED, small_cfg, progress=False)
    assert summary.skipped == COUNT and summary.generated == 1
    after = _digest(work)
    assert {k: v for k, v in after.items() if k in before and k != "manifest.jsonl"} == {
        k: v for k, v in before.items() if k != "manifest.jsonl"}
    lines = _lines(os.path.join(work, "manifest.jsonl"))
    assert len(lines) == COUNT + 1
    assert lines[:COUNT] == _lines(os.path.join(out, "manifest.jsonl"))


def test_collect_for_other_executors(dataset, tmp_path):
    out, _ = dataset
    work = str(tmp_path / "ext")
    shutil.copytree(out, work)
    os.remove(os.path.join(work, "manifest.jsonl"))
    records = data_gen.collect(work, COUNT)
    assert records == read_manifest(out) == read_manifest(work)
    os.remove(os.path.join(work, sample_files(2)["record"]))
    with pytest.raises(ValueError, match="1 sample.s. missing or incomplete: 2"):
        data_gen.collect(work, COUNT)


def test_resume_refuses_a_different_config(dataset, small_cfg, tmp_path):
    out, _ = dataset
    work = str(tmp_path / "other")
    shutil.copytree(out, work)
    with pytest.raises(ValueError, match=f"different seed or config .seed: {SEED} in the file, "
                       f"{SEED + 1} now"):
        run(work, COUNT, SEED + 1, small_cfg, progress=False)


def test_resume_names_the_config_keys_that_differ(tmp_path):
    """A data set from an older data_gen (a config key it did not have) is refused with the
    key named, not only "different config"."""
    from data_gen._run import _check_generator_file
    cfg = {"target": {"kind": "reference", "margin": "auto"}, "noise": {"sigma": 0.01}}
    out = str(tmp_path)
    _check_generator_file(out, 3, cfg)
    _check_generator_file(out, 3, cfg)  # the same: accepted
    old = {"target": {"kind": "reference"}, "noise": {"sigma": 0.02}}
    with pytest.raises(ValueError) as err:
        _check_generator_file(out, 3, old)
    assert "config.noise.sigma: 0.01 in the file, 0.02 now" in str(err.value)
    assert "config.target.margin: 'auto' in the file, 'absent' now" in str(err.value)


@pytest.mark.slow  # two spawned processes, each imports JAX and compiles its own renderer
def test_workers_give_the_same_bytes(small_cfg, tmp_path, dataset):
    # Two spawned processes, only the cheapest kind (each process compiles its own renderer).
    cfg = json.loads(json.dumps(small_cfg))
    cfg["kinds"] = {"single_plane": 1.0}
    one, two = str(tmp_path / "w1"), str(tmp_path / "w2")
    run(one, 2, SEED, cfg, workers=1, progress=False)
    run(two, 2, SEED, cfg, workers=2, progress=False)
    assert _digest(one) == _digest(two)
