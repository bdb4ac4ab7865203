"""`python -m fit.recover`: the CLI over fit_focus, end to end on a small render."""

import json
import os

import numpy as np
import pytest

import dofjax
from fit import recover

SCENE = os.path.join(os.path.dirname(__file__), "..", "examples", "quads.json")


def _camera(width, height, focus, aperture):
    base = dofjax.load_camera(SCENE)
    return dofjax.Camera(width=width, height=height, fov=base.fov, focus_distance=focus,
                         aperture_radius=aperture, eye=base.eye, target=base.target, up=base.up)


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
    with pytest.raises(SystemExit, match="samples must be a positive int, got 0"):
        recover.main([path, "--scene", SCENE, "--method", "lens", "--samples", "0"])
    with pytest.raises(SystemExit, match=r"subapertures must be an int in \[1, 16\], got 0"):
        recover.main([path, "--scene", SCENE, "--subapertures", "0"])


def test_recover_names_a_target_clipped_everywhere(tmp_path):
    # (not fit_focus's "mask: selects no pixels", which names an argument the user did not pass)
    sharp = dofjax.render(dofjax.load_scene(SCENE), _camera(8, 6, 4.0, 0.05))
    dofjax.write_rgbd(str(tmp_path / "sharp.exr"), sharp, metadata={"fov": 40.0})
    target = str(tmp_path / "target.exr")
    dofjax.write_exr(target, np.full((6, 8, 3), 0.7, np.float32))
    argv = [target, "--sharp", str(tmp_path / "sharp.exr"), "--clipped-at", "0.5"]
    # and a sharp file without a camera guess in its metadata: the flag to pass, named
    with pytest.raises(SystemExit, match=r"^recover: no initial focus distance \(the sharp "
                                         r"file's metadata has none\); pass --focus$"):
        recover.main(argv)
    with pytest.raises(SystemExit, match=r"^recover: no initial aperture radius .*--aperture$"):
        recover.main(argv + ["--focus", "3"])
    with pytest.raises(SystemExit, match=r"^recover: error: .*target.exr: every pixel has a "
                                         r"channel clipped at 0.5: nothing to fit"):
        recover.main(argv + ["--focus", "3", "--aperture", "0.05"])


def test_scripts_name_a_missing_or_unreadable_file(tmp_path):
    # one line naming the file (SystemExit's message), not a traceback from the reader
    from fit import sweep

    target = str(tmp_path / "t.exr")
    dofjax.write_exr(target, np.zeros((4, 4, 3), np.float32))
    missing = str(tmp_path / "missing.exr")
    with pytest.raises(SystemExit, match=r"^recover: error: .*missing\.exr: no such file"):
        recover.main([missing, "--sharp", target])
    with pytest.raises(SystemExit, match=r"^recover: error: .*missing\.exr: no such file"):
        recover.main([target, "--sharp", missing])
    with pytest.raises(SystemExit, match=r"^recover: error: .*nope\.json: cannot read scene"):
        recover.main([target, "--scene", str(tmp_path / "nope.json")])
    text = tmp_path / "notes.txt"
    text.write_text("not an image\n")
    with pytest.raises(SystemExit, match=r"^recover: error: .*notes\.txt: not a readable image"):
        recover.main([str(text), "--sharp", target])
    with pytest.raises(SystemExit, match=r"^sweep: error: .*No such file"):
        sweep.main([str(tmp_path / "manifest.jsonl")])
    with pytest.raises(SystemExit, match=r"notes\.txt, line 1: not a data_gen manifest line"):
        sweep.main([str(text), "--out", str(tmp_path)])
    record = tmp_path / "record.jsonl"
    record.write_text('{"files": {}}\n')
    with pytest.raises(SystemExit, match=r"line 1: not a data_gen manifest record \(no index, "
                       r"truth, kind, noise\)"):
        sweep.main([str(record), "--out", str(tmp_path)])
    # a sample whose files are gone: named with its index, the rest of the sweep not run
    gone = tmp_path / "gone.jsonl"
    gone.write_text(json.dumps({"index": 7, "kind": "planes", "noise": {"model": "none"},
                                "truth": {"fov": 40.0},
                                "files": {"sharp": "x.sharp.exr", "target": "x.target.exr"}})
                    + "\n")
    with pytest.raises(SystemExit, match=r"^sweep: error: sample 7 \(planes; 0 of 1 fitted, "
                                         r"in .*sweep\.jsonl\): .*x\.sharp\.exr: no such file"):
        sweep.main([str(gone), "--out", str(tmp_path)])
    empty = tmp_path / "empty.jsonl"
    empty.write_text("\n")
    with pytest.raises(SystemExit, match="empty manifest"):
        sweep.main([str(empty), "--out", str(tmp_path)])


def test_demo_and_data_gen_name_bad_paths(tmp_path, capsys):
    from data_gen.__main__ import main as data_gen_main
    from fit import demo

    with pytest.raises(SystemExit, match=r"^demo: error: .*nope\.json: cannot read scene file"):
        demo.main(["--scene", str(tmp_path / "nope.json")])
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    assert data_gen_main(["--out", str(a_file), "--count", "1", "--seed", "0",
                          "--no-progress"]) != 0
    assert "a_file is a file, not a directory" in capsys.readouterr().err
