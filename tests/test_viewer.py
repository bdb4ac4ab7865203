"""dofjax view's server: every endpoint through Starlette's test client, bad requests, the
stale-frame gate, the inputs it loads and the command's start-up errors.

One small scene (quads at 64x48) and one engine for the module: a render, one defocus program,
one reference program. Fits use `cheap_model`, a forward model that depends on |CoC| as the
defocus does but compiles in seconds (the real fit is `fit_focus`'s tests' business).
"""

import asyncio
import io
import os
import socket
import threading

import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image
from starlette.testclient import TestClient

import dofjax
from dofjax import _cli
from dofjax._viewer import Bokeh, Engine, _engine, create_app, load_source
from dofjax._viewer._app import FrameGate
from dofjax._viewer._engine import encode

QUADS = os.path.join(os.path.dirname(__file__), "..", "examples", "quads.json")
W, H = 64, 48


def cheap_model(rgb, depth, camera):
    """A per-pixel blend of the sharp image and a 5x5 box blur, weighted by |c| (smooth in c)."""
    c = dofjax.coc_radius(depth, camera)
    w = (1.0 - jnp.exp(-0.5 * c * c))[..., None]
    p = jnp.pad(rgb, ((2, 2), (2, 2), (0, 0)), mode="edge")
    box = sum(p[i:i + rgb.shape[0], j:j + rgb.shape[1]] for i in range(5) for j in range(5)) / 25
    return (1 - w) * rgb + w * box


FIT_OPTIONS = dict(model=cheap_model, starts=2, coarse_size=None, scan_points=0, screen_steps=0,
                   robust_rounds=0)


@pytest.fixture(scope="module")
def engine():
    eng = Engine(load_source(QUADS, width=W, height=H), fit_options=FIT_OPTIONS)
    eng.warm_up()
    return eng


@pytest.fixture(scope="module")
def client(engine):
    with TestClient(create_app(engine, max_upload=200_000)) as c:
        yield c


def _png_bytes(rgb8):
    out = io.BytesIO()
    Image.fromarray(rgb8).save(out, format="PNG")
    return out.getvalue()


def _decode(body):
    return np.asarray(Image.open(io.BytesIO(body)).convert("RGB"), np.float64)


def _exr_bytes(tmp_path, rgb, name="t.exr"):
    path = tmp_path / name
    dofjax.write_exr(str(path), np.asarray(rgb, np.float32))
    return path.read_bytes()


# ------------------------------------------------------------------------------ page and info


def test_page_static_files_and_no_paths(client):
    page = client.get("/")
    assert page.status_code == 200 and "/static/app.js" in page.text
    for name in ("app.js", "style.css", "index.html"):
        assert client.get(f"/static/{name}").status_code == 200
    assert "http" not in client.get("/static/app.js").text.replace("HTTP", "")  # offline page
    assert client.get("/static/../_app.py").status_code == 404
    assert client.get("/static/%2e%2e/_app.py").status_code == 404
    assert client.get("/api/nothing").status_code == 404


def test_info_ranges(client, engine):
    info = client.get("/api/info").json()
    assert (info["width"], info["height"]) == (W, H)
    lo, hi = info["focus_range"]
    zmin, zmax = info["depth_range"]
    assert lo < zmin <= zmax < hi
    assert info["has_scene"] and info["target"] is None
    # the aperture slider ends where the largest |CoC| over the focus range reaches the window
    ends = [np.abs(np.asarray(dofjax.coc_radius(engine.source.depth, engine.camera.replace(
        focus_distance=d, aperture_radius=info["aperture_max"])))).max() for d in (lo, hi)]
    assert max(ends) == pytest.approx(info["window"], rel=1e-6)


# ------------------------------------------------------------------------------ frames


def test_frame_is_the_library_defocus(client, engine):
    d, a = 2.0, 0.6 * engine.aperture_max
    r = client.get("/api/frame", params=dict(focus=d, aperture=a, seq=1, client="t1"))
    assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg"
    assert r.headers["x-dofjax-exact"] == "1" and r.headers["x-dofjax-seq"] == "1"
    final = {} if _engine.FINAL_METHOD is None else {"method": _engine.FINAL_METHOD}
    expected = dofjax.defocus(engine.source.rgbd, engine.camera.replace(
        focus_distance=d, aperture_radius=a), window=engine.window, **final)
    got = _decode(r.content)
    assert got.shape == (H, W, 3)
    # the sRGB JPEG of the library's image (same encoder; float rounding may move a level)
    assert np.abs(got - _decode(encode(np.asarray(expected), "jpeg"))).max() <= 2
    srgb = np.round(dofjax._io.srgb_encode(np.asarray(expected, np.float64)) * 255)
    other = _decode(client.get("/api/frame", params=dict(focus=9.0, aperture=a)).content)
    assert np.abs(got - srgb).mean() < 0.5 * np.abs(other - srgb).mean()  # JPEG's error small
    brighter = _decode(client.get("/api/frame", params=dict(focus=d, aperture=a,
                                                            exposure=1)).content)
    assert brighter.mean() > got.mean() + 5
    # while a slider moves: the live method (exact only if it is the final one), close to it
    live = client.get("/api/frame", params=dict(focus=d, aperture=a, quality="live"))
    exact = _engine.LIVE_METHOD == _engine.FINAL_METHOD
    assert live.headers["x-dofjax-exact"] == ("1" if exact else "0")
    assert np.abs(_decode(live.content) - got).mean() < 0.5 * np.abs(other - srgb).mean()


def test_overlays(client, engine):
    z = client.get("/api/frame", params=dict(focus=3, aperture=0.0, view="depth"))
    assert z.status_code == 200
    coc0 = _decode(client.get("/api/frame", params=dict(focus=3, aperture=0.0,
                                                        view="coc")).content)
    assert np.abs(coc0 - 247).max() < 12  # zero CoC everywhere: the ramp's white middle
    coc = _decode(client.get("/api/frame", params=dict(
        focus=3, aperture=engine.aperture_max, view="coc")).content)
    near = engine.source.depth < 2.5  # in front of the focal plane: red
    far = engine.source.depth > 5.0  # behind: blue
    assert coc[near][:, 0].mean() > coc[near][:, 2].mean() + 60
    assert coc[far][:, 2].mean() > coc[far][:, 0].mean() + 60


@pytest.mark.parametrize("params, needle", [
    (dict(aperture=0.01), "missing parameter 'focus'"),
    (dict(focus="x", aperture=0.01), "not a number"),
    (dict(focus="nan", aperture=0.01), "must be finite"),
    (dict(focus=1e6, aperture=0.01), "outside the viewer's range"),
    (dict(focus=3, aperture=-1), "outside the viewer's range"),
    (dict(focus=3, aperture=0.01, view="normals"), "parameter 'view'"),
    (dict(focus=3, aperture=0.01, quality="best"), "parameter 'quality'"),
    (dict(focus=3, aperture=0.01, blades=2), "parameter 'blades'"),
    (dict(focus=3, aperture=0.01, seq=1.5), "must be an integer"),
    (dict(focus=3, aperture=0.01, exposure=99), "parameter 'exposure'"),
])
def test_frame_bad_requests(client, params, needle):
    r = client.get("/api/frame", params=params)
    assert r.status_code == 400 and needle in r.json()["error"]


def test_stale_frames_are_dropped_not_queued():
    """While one frame renders, a waiting request is answered at once when a newer one from the
    same page arrives; an older sequence number than one already seen is refused outright."""

    async def scenario():
        gate = FrameGate()
        assert await gate.enter("page", 1)  # rendering
        second = asyncio.ensure_future(gate.enter("page", 2))
        other_page = asyncio.ensure_future(gate.enter("other", 1))
        await asyncio.sleep(0.01)
        assert not second.done()
        third = asyncio.ensure_future(gate.enter("page", 3))
        await asyncio.sleep(0.01)
        assert second.done() and second.result() is False  # dropped while the first renders
        assert not await gate.enter("page", 2)  # older than one already seen
        gate.leave()  # the lock goes to the waiters in order of arrival: the other page first
        assert await asyncio.wait_for(other_page, 1) is True
        assert not third.done()
        gone = asyncio.ensure_future(gate.enter("closed tab", 1))
        await asyncio.sleep(0.01)
        gone.cancel()  # a request that went away while waiting does not keep the lock
        gate.leave()
        assert await asyncio.wait_for(third, 1) is True
        gate.leave()
        assert await asyncio.wait_for(gate.enter("later", 1), 1) is True
        gate.leave()

    asyncio.run(scenario())


# ------------------------------------------------------------------------------ click to focus


def test_depth_under_the_cursor(client, engine):
    y, x = np.argwhere(engine.source.depth == engine.source.depth.min())[0]
    body = client.get("/api/depth", params=dict(x=int(x), y=int(y))).json()
    assert body["depth"] == float(engine.source.depth[y, x]) == body["focus"]
    assert not body["background"]
    for params in (dict(x=W, y=0), dict(x=0, y=-1), dict(x="a", y=0), dict(x=0)):
        assert client.get("/api/depth", params=params).status_code == 400


# ------------------------------------------------------------------------------ reference


def test_reference_job(client, engine):
    import jax

    d, a = 3.0, 0.5 * engine.aperture_max
    r = client.post("/api/reference", params=dict(focus=d, aperture=a, spp=16, seed=3))
    assert r.status_code == 202
    engine.reference.wait(120)
    status = client.get("/api/reference").json()
    assert status["state"] == "done" and status["done"] == status["total"] == 16
    result = status["result"]
    cam = engine.camera.replace(focus_distance=d, aperture_radius=a)
    ref = np.asarray(dofjax.render_reference(engine.source.scene, cam, spp=16,
                                             key=jax.random.key(3)), np.float64)
    final = {} if _engine.FINAL_METHOD is None else {"method": _engine.FINAL_METHOD}
    post = np.asarray(dofjax.defocus(engine.source.rgbd, cam, window=engine.window, **final),
                      np.float64)
    assert result["rmse"] == pytest.approx(np.sqrt(np.mean((post - ref) ** 2)), rel=1e-4)
    for which in ("reference", "postprocess", "difference"):
        img = client.get(f"/api/reference/{which}.png")
        assert img.status_code == 200 and _decode(img.content).shape == (H, W, 3)
    assert client.get("/api/reference/scene.png").status_code == 400
    bad = client.post("/api/reference", params=dict(focus=d, aperture=a, spp=0))
    assert bad.status_code == 400 and "spp" in bad.json()["error"]


def test_a_running_job_refuses_a_second(client, engine):
    release = threading.Event()
    engine.fit.start(lambda job: release.wait(30) and {"images": {}})
    try:
        r = client.post("/api/fit", params=dict(focus=3, aperture=0.01))
        assert r.status_code == 409 and "already running" in r.json()["error"]
        assert client.get("/api/fit").json()["state"] == "running"
    finally:
        release.set()
        engine.fit.wait(30)


# ------------------------------------------------------------------------------ target and fit


def test_target_upload_errors(client, engine, tmp_path):
    def post(name, body):
        return client.post("/api/target", params=dict(name=name), content=body)

    r = post("t.png", _png_bytes(np.zeros((10, 12, 3), np.uint8)))
    assert r.status_code == 400 and "12x10" in r.json()["error"] and f"{W}x{H}" in r.json()[
        "error"]
    r = post("t.exr", b"not an image at all")
    assert r.status_code == 400 and "not a readable image" in r.json()["error"]
    assert str(tmp_path) not in r.json()["error"]  # no server paths in messages
    r = post("notes.txt", b"hello")
    assert r.status_code == 400 and "unsupported file type" in r.json()["error"]
    assert post("t.png", b"").status_code == 400
    r = post("big.exr", b"\0" * 200_001)
    assert r.status_code == 413 and "upload limit" in r.json()["error"]
    r = post("../../etc/passwd.png", _png_bytes(np.zeros((10, 12, 3), np.uint8)))
    assert r.status_code == 400 and "passwd.png" in r.json()["error"]
    assert engine.target is None  # nothing kept from the failures
    r = client.post("/api/fit", params=dict(focus=3, aperture=0.01))
    assert r.status_code == 400 and "no target image" in r.json()["error"]


def test_fit_job(client, engine, tmp_path):
    truth = engine.camera.replace(focus_distance=2.5, aperture_radius=0.7 * engine.aperture_max)
    target = np.asarray(cheap_model(engine.source.rgb, engine.source.depth, truth))
    r = client.post("/api/target", params=dict(name="target.exr"),
                    content=_exr_bytes(tmp_path, target))
    assert r.status_code == 200 and r.json()["target"] == "target.exr"
    assert client.get("/api/info").json()["target"] == "target.exr"
    assert client.get("/api/target.png").status_code == 200
    r = client.post("/api/fit", params=dict(focus=6.0, aperture=0.3 * engine.aperture_max))
    assert r.status_code == 202
    engine.fit.wait(300)
    status = client.get("/api/fit").json()
    assert status["state"] == "done", status
    f = status["result"]
    assert f["focus"] == pytest.approx(2.5, rel=1e-4)
    assert f["aperture"] == pytest.approx(0.7 * engine.aperture_max, rel=1e-4)
    assert f["identifiable"] and f["converged"] and f["message"] == "ok"
    assert f["focus_se"] >= 0 and f["aperture_se"] >= 0 and f["rmse"] < 1e-4
    assert _decode(client.get("/api/fit/residual.png").content).shape == (H, W, 3)


def test_fit_that_cannot_succeed_reports_and_the_server_goes_on(client, engine, tmp_path):
    flat = np.full((H, W, 3), 0.5, np.float32)  # no texture: nothing to see the blur in
    assert client.post("/api/target", params=dict(name="flat.exr"),
                       content=_exr_bytes(tmp_path, flat)).status_code == 200
    client.post("/api/fit", params=dict(focus=3.0, aperture=0.01))
    engine.fit.wait(300)
    status = client.get("/api/fit").json()
    if status["state"] == "done":
        f = status["result"]
        assert not f["identifiable"] and f["message"] != "ok"
    else:
        assert status["state"] == "error" and status["error"]
    frame = client.get("/api/frame", params=dict(focus=3.0, aperture=0.01))
    assert frame.status_code == 200


def test_nan_target_refused(client, engine, tmp_path):
    before = engine.target_name
    bad = np.full((H, W, 3), 0.5, np.float32)
    path = tmp_path / "nan.exr"
    dofjax.write_exr(str(path), bad)
    with pytest.raises(ValueError, match="NaN/inf"):
        engine.set_target(np.where(bad > 0, np.nan, bad), "nan.exr")
    assert engine.target_name == before


# ------------------------------------------------------------------------------ download


def test_download_exr_and_png(client, engine, tmp_path):
    d, a = 4.0, 0.4 * engine.aperture_max
    r = client.get("/api/download.exr", params=dict(focus=d, aperture=a, blades=0))
    assert r.status_code == 200 and "attachment" in r.headers["content-disposition"]
    path = tmp_path / "down.exr"
    path.write_bytes(r.content)
    rgb, depth, meta = dofjax.read_exr(str(path))
    np.testing.assert_array_equal(rgb, np.asarray(engine.image(d, a, Bokeh()), np.float32))
    np.testing.assert_array_equal(depth, engine.source.depth.astype(np.float32))
    assert meta["focus_distance"] == d and meta["aperture_radius"] == a
    assert meta["fov"] == pytest.approx(40.0) and meta["generator"] == "dofjax view"
    png = client.get("/api/download.png", params=dict(focus=d, aperture=a))
    assert png.status_code == 200 and _decode(png.content).shape == (H, W, 3)
    assert client.get("/api/download.tif", params=dict(focus=d, aperture=a)).status_code == 400


# ------------------------------------------------------------------------------ inputs


def test_exr_and_data_gen_inputs(engine, tmp_path):
    """A sharp EXR (camera from its metadata) has no scene, so no reference; a data_gen record
    brings its scene, its target and its guard band (cropped from the frame)."""
    m = 2
    rgb = np.pad(engine.source.rgb, ((m, m), (m, m), (0, 0)), mode="edge")
    depth = np.pad(engine.source.depth, m, mode="edge")
    cam = engine.camera
    meta = dict(fov=float(cam.fov), focus_distance=4.0, aperture_radius=0.02, margin=m,
                eye=[0.0, 0.0, 0.0], target=[0.0, 0.0, 1.0], up=[0.0, 1.0, 0.0])
    dofjax.write_exr(str(tmp_path / "sharp.exr"), rgb, depth, meta)
    source = load_source(str(tmp_path / "sharp.exr"))
    np.testing.assert_array_equal(source.depth, engine.source.depth.astype(np.float32))
    assert source.margin == m and source.scene is None and source.camera.width == W
    with pytest.raises(ValueError, match="no scene"):
        Engine(source).start_reference(4.0, 0.01, Bokeh(), 16)

    samples = tmp_path / "samples" / "0000"
    samples.mkdir(parents=True)
    dofjax.write_exr(str(samples / "000000.target.exr"), engine.source.rgb)
    os.replace(tmp_path / "sharp.exr", samples / "000000.sharp.exr")
    import shutil

    shutil.copy(QUADS, samples / "000000.scene.json")
    record = {"index": 0, "kind": "quads", "truth": {"focal_length": 0.05, "f_number": 2.0,
                                                     "sensor_width": 0.036},
              "files": {k: f"samples/0000/000000.{k}.{'json' if k == 'scene' else 'exr'}"
                        for k in ("scene", "sharp", "target")}}
    (samples / "000000.json").write_text(__import__("json").dumps(record))
    (tmp_path / "manifest.jsonl").write_text(__import__("json").dumps(record) + "\n")
    for path, kw in ((samples / "000000.json", {}), (tmp_path, {}), (tmp_path, {"sample": 0})):
        s = load_source(str(path), **kw)
        assert s.scene is not None and s.margin == m and s.target.shape == (H, W, 3)
        assert s.photographic["focal_length"] == 0.05
    with pytest.raises(ValueError, match="no sample with index 5"):
        load_source(str(tmp_path), sample=5)
    with pytest.raises(ValueError, match="no fov"):
        dofjax.write_exr(str(tmp_path / "bare.exr"), rgb, depth)
        load_source(str(tmp_path / "bare.exr"))


# ------------------------------------------------------------------------------ the command


def test_command_errors(capsys, tmp_path):
    assert _cli.main(["view", str(tmp_path / "missing.json")]) == 2
    assert "missing.json: no such file" in capsys.readouterr().err
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        assert _cli.main(["view", QUADS, "--port", str(port)]) == 2
    err = capsys.readouterr().err
    assert f"port {port} on 127.0.0.1 is in use" in err and "--port" in err
    assert _cli.main(["view", QUADS, "--port", "70000"]) == 2
    assert "--port" in capsys.readouterr().err
    (tmp_path / "notes.txt").write_text("x")
    assert _cli.main(["view", str(tmp_path / "notes.txt")]) == 2
    assert "expected a scene file" in capsys.readouterr().err
