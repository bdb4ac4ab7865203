"""`python -m fit.recover`: the CLI over fit_focus, end to end on a small render."""

import json
import os
import re

import numpy as np
import pytest

import dofjax
from fit import recover

SCENE = os.path.join(os.path.dirname(__file__), "..", "examples", "quads.json")


def _camera(width, height, focus, aperture):
    base = dofjax.load_camera(SCENE)
    return dofjax.Camera(width=width, height=height, fov=base.fov, focus_distance=focus,
                         aperture_radius=aperture, eye=base.eye, target=base.target, up=base.up)


def _fails(capsys, main, argv, pattern):
    """`main(argv)` ends with exit status 2 (bad input) and a stderr line matching `pattern`;
    returns what it printed on stdout."""
    with pytest.raises(SystemExit) as info:
        main(argv)
    out, err = capsys.readouterr()
    assert info.value.code == 2, err
    assert re.search(pattern, err, re.MULTILINE), err
    return out


@pytest.mark.slow
def test_recover_from_a_supersampled_layered_scene(tmp_path, capsys):
    # the target is the supersampled, layered sliced model itself: recovered exactly
    true = _camera(32, 24, 4.0, 0.08)
    sharp = dofjax.render(dofjax.load_scene(SCENE), true.scaled(2), layers=2)
    target = np.asarray(dofjax.defocus(sharp, true, method="sliced"))
    path = str(tmp_path / "target.exr")
    dofjax.write_exr(path, target, metadata={"focus_distance": 4.0, "aperture_radius": 0.08})
    prefix = str(tmp_path / "fit")
    recover.main([path, "--scene", SCENE, "--layers", "2", "--supersample", "2", "--focus", "7",
                  "--aperture", "0.05", "--focus-bounds", "1", "50", "--aperture-bounds", "0.01",
                  "0.3", "--starts", "4", "--clipped-at", "0.55", "--out", prefix])
    out = capsys.readouterr().out
    assert "focus_distance" in out and "message: ok" in out
    clipped = int(np.any(target >= 0.55, axis=-1).sum())
    assert 0 < clipped < target.shape[0] * target.shape[1] // 2  # (the fit survives them)
    assert f"left out {clipped} of {24 * 32} target pixels clipped at 0.55" in out
    with open(prefix + ".json") as f:
        result = json.load(f)["result"]
    assert result["focus_distance"] == pytest.approx(4.0, rel=1e-3)
    assert result["aperture_radius"] == pytest.approx(0.08, rel=1e-3)
    assert os.path.exists(prefix + ".png")


def test_recover_rejects_options_that_do_not_apply(tmp_path, capsys):
    path = str(tmp_path / "t.exr")
    dofjax.write_exr(path, np.zeros((4, 4, 3), np.float32))
    for argv, msg in ((["--samples", "64"], "--samples is for --method lens only"),
                      (["--method", "lens", "--subapertures", "4"],
                       "--subapertures is for --method sliced only"),
                      (["--sharp", path, "--supersample", "2"], "are for --scene"),
                      (["--supersample", "0"], "--supersample must be >= 1"),
                      (["--layers", "0"], "--layers must be >= 1"),
                      (["--margin", "-1"], "--margin must be >= 0, got -1")):
        if "--sharp" not in argv:
            argv = ["--scene", SCENE] + argv
        with pytest.raises(SystemExit):
            recover.main([path] + argv)
        assert msg in capsys.readouterr().err
    # a value only the library can judge: its named error, not a silent default
    _fails(capsys, recover.main, [path, "--scene", SCENE, "--method", "lens", "--samples", "0"],
           "samples must be a positive int, got 0")
    _fails(capsys, recover.main, [path, "--scene", SCENE, "--subapertures", "0"],
           r"subapertures must be an int in \[1, 16\], got 0")


def test_recover_names_a_target_clipped_everywhere(tmp_path, capsys):
    # (not fit_focus's "mask: selects no pixels", which names an argument the user did not pass)
    sharp = dofjax.render(dofjax.load_scene(SCENE), _camera(8, 6, 4.0, 0.05))
    dofjax.write_rgbd(str(tmp_path / "sharp.exr"), sharp)
    target = str(tmp_path / "target.exr")
    dofjax.write_exr(target, np.full((6, 8, 3), 0.7, np.float32))
    argv = [target, "--sharp", str(tmp_path / "sharp.exr"), "--clipped-at", "0.5"]
    # a sharp file without the field of view in its metadata: the flag to pass, named
    _fails(capsys, recover.main, argv, r"^recover: error: .*sharp\.exr: no fov in the file's "
           r"metadata; pass --fov$")
    _fails(capsys, recover.main, argv + ["--fov", "40"], r"^recover: error: .*target.exr: every "
           r"pixel has a channel clipped at 0.5: nothing to fit")


def test_recover_never_starts_from_the_files_focus_and_aperture(tmp_path, capsys):
    # a data_gen sharp file records the true camera: the guess must not come from it
    true = _camera(16, 12, 4.0, 0.05)
    sharp = dofjax.render(dofjax.load_scene(SCENE), true)
    meta = {"fov": float(true.fov), "focus_distance": 4.0, "aperture_radius": 0.05}
    dofjax.write_rgbd(str(tmp_path / "sharp.exr"), sharp, metadata=meta)
    target = str(tmp_path / "target.exr")
    dofjax.write_exr(target, np.zeros((12, 16, 3), np.float32), metadata=meta)
    argv = [target, "--sharp", str(tmp_path / "sharp.exr"), "--clipped-at", "-1"]
    z = np.asarray(sharp.depth)
    z = z[np.isfinite(z)]
    d_lo, d_hi = 0.5 * z.min(), 4.0 * z.max()
    d_mid = 2.0 / (1.0 / d_lo + 1.0 / d_hi)
    # (every pixel "clipped" at -1 ends the run after the guess is printed, before any fit)
    out = _fails(capsys, recover.main, argv, "nothing to fit")
    assert re.search(rf"^initial guess: d {d_mid:.4g}, A \S+ from global search \(8 starts",
                     out, re.MULTILINE), out
    out = _fails(capsys, recover.main, argv + ["--focus", "9", "--aperture", "0.02"],
                 "nothing to fit")
    assert "initial guess: d 9, A 0.02 from --focus 9 --aperture 0.02" in out


def test_scripts_name_a_missing_or_unreadable_file(tmp_path, capsys):
    # one line naming the file on stderr, not a traceback from the reader
    from fit import sweep

    target = str(tmp_path / "t.exr")
    dofjax.write_exr(target, np.zeros((4, 4, 3), np.float32))
    missing = str(tmp_path / "missing.exr")
    _fails(capsys, recover.main, [missing, "--sharp", target],
           r"^recover: error: .*missing\.exr: no such file")
    _fails(capsys, recover.main, [target, "--sharp", missing],
           r"^recover: error: .*missing\.exr: no such file")
    _fails(capsys, recover.main, [target, "--scene", str(tmp_path / "nope.json")],
           r"^recover: error: .*nope\.json: cannot read scene")
    text = tmp_path / "notes.txt"
    text.write_text("not an image\n")
    _fails(capsys, recover.main, [str(text), "--sharp", target],
           r"^recover: error: .*notes\.txt: not a readable image")
    _fails(capsys, sweep.main, [str(tmp_path / "manifest.jsonl")],
           r"^sweep: error: .*No such file")
    _fails(capsys, sweep.main, [str(text), "--out", str(tmp_path)],
           r"notes\.txt, line 1: not a data_gen manifest line")
    record = tmp_path / "record.jsonl"
    record.write_text('{"files": {}}\n')
    _fails(capsys, sweep.main, [str(record), "--out", str(tmp_path)],
           r"line 1: not a data_gen manifest record \(no index, truth, kind, noise\)")
    # a sample whose files are gone: named with its index, the rest of the sweep not run
    gone = tmp_path / "gone.jsonl"
    gone.write_text(json.dumps({"index": 7, "kind": "planes", "noise": {"model": "none"},
                                "truth": {"fov": 40.0},
                                "files": {"sharp": "x.sharp.exr", "target": "x.target.exr"}})
                    + "\n")
    _fails(capsys, sweep.main, [str(gone), "--out", str(tmp_path)],
           r"^sweep: error: sample 7 \(planes; 0 of 1 fitted, in .*sweep\.jsonl\): "
           r".*x\.sharp\.exr: no such file")
    empty = tmp_path / "empty.jsonl"
    empty.write_text("\n")
    _fails(capsys, sweep.main, [str(empty), "--out", str(tmp_path)],
           "empty manifest")


def test_demo_and_data_gen_name_bad_paths(tmp_path, capsys):
    from data_gen.__main__ import main as data_gen_main
    from fit import demo

    _fails(capsys, demo.main, ["--scene", str(tmp_path / "nope.json")],
           r"^demo: error: .*nope\.json: cannot read scene file")
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    assert data_gen_main(["--out", str(a_file), "--count", "1", "--seed", "0",
                          "--no-progress"]) != 0
    assert "a_file is a file, not a directory" in capsys.readouterr().err
