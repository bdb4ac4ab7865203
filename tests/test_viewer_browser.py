"""dofjax view in a real headless Chromium: drag the focus slider, click to focus, run a
reference and a fit, read the numbers the page shows. Saves a screenshot as a test artifact
(and to $DOFJAX_VIEWER_SCREENSHOT when set).

Needs Debian's Chromium (`apt-get install chromium`, at /usr/bin/chromium) and the `playwright`
Python package (the test extra); no browser is downloaded. Same scene, size and fit options as
tests/test_viewer.py, so the two share compiled programs through the persistent cache.
"""

import os
import shutil
import threading
import time

import numpy as np
import pytest

import dofjax
from dofjax._viewer import Engine, _engine, bind, create_app, load_source

CHROMIUM = "/usr/bin/chromium"
QUADS = os.path.join(os.path.dirname(__file__), "..", "examples", "quads.json")
W, H = 64, 48

if not os.path.exists(CHROMIUM):
    pytest.skip(f"no Chromium at {CHROMIUM}: apt-get install chromium", allow_module_level=True)
sync_api = pytest.importorskip(
    "playwright.sync_api", reason="the playwright package: pip install -e '.[test]'")


def _fit_options():
    from test_viewer import FIT_OPTIONS  # the same fit program as the server tests

    return FIT_OPTIONS


@pytest.fixture(scope="module")
def server():
    import uvicorn

    engine = Engine(load_source(QUADS, width=W, height=H), fit_options=_fit_options())
    engine.warm_up()
    sock = bind("127.0.0.1", 0)
    uv = uvicorn.Server(uvicorn.Config(create_app(engine), log_level="warning",
                                       lifespan="off"))
    thread = threading.Thread(target=uv.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not uv.started:
        assert time.monotonic() < deadline and thread.is_alive(), "the server did not start"
        time.sleep(0.02)
    host, port = sock.getsockname()[:2]
    yield engine, f"http://{host}:{port}/"
    uv.should_exit = True
    thread.join(10)
    sock.close()


@pytest.fixture(scope="module")
def page(server):
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, headless=True,
                                    args=["--no-sandbox"])
        pg = browser.new_page(viewport={"width": 1280, "height": 900})
        pg.errors = []
        pg.on("pageerror", lambda e: pg.errors.append(str(e)))
        pg.goto(server[1])
        pg.wait_for_function("window.dofjaxView && window.dofjaxView.painted.length > 0",
                             timeout=30_000)
        yield pg
        browser.close()


def _painted(pg) -> int:
    return pg.evaluate("window.dofjaxView.painted.length")


def _value(pg, selector: str) -> float:
    return float(pg.get_attribute(selector, "data-value"))


def test_drag_the_focus_slider(page):
    before = page.locator("#frame").screenshot()
    n0 = _painted(page)
    box = page.locator("#focus").bounding_box()
    y = box["y"] + box["height"] / 2
    page.mouse.move(box["x"] + 0.6 * box["width"], y)
    page.mouse.down()
    for k in range(1, 6):  # the image follows while the button is still down
        page.mouse.move(box["x"] + (0.6 - 0.1 * k) * box["width"], y, steps=2)
        page.wait_for_timeout(60)
    page.wait_for_function(f"window.dofjaxView.painted.length > {n0}")
    during = _painted(page)
    page.mouse.up()
    assert during > n0
    # at rest the live frame is refined with the exact (final) method
    page.wait_for_function("window.dofjaxView.painted.at(-1).exact && !window.dofjaxView.busy()",
                           timeout=60_000)
    final = page.evaluate("window.dofjaxView.painted.at(-1)")
    assert final["quality"] == ("live" if _engine.LIVE_METHOD == _engine.FINAL_METHOD
                                else "final")
    assert page.locator("#frame").screenshot() != before
    assert _value(page, "#focus-readout") < 3.0  # dragged towards the near end


def test_click_to_focus_reads_the_depth(page, server):
    engine = server[0]
    depth = engine.source.depth
    near = np.argwhere(depth == depth.min())  # the nearest quad
    y, x = near[len(near) // 2]
    box = page.locator("#frame").bounding_box()
    page.mouse.click(box["x"] + (x + 0.5) * box["width"] / W,
                     box["y"] + (y + 0.5) * box["height"] / H)
    page.wait_for_function("document.getElementById('pick-readout').dataset.depth")
    assert float(page.get_attribute("#pick-readout", "data-depth")) == float(depth[y, x])
    assert _value(page, "#focus-readout") == float(depth[y, x])
    assert page.text_content("#focus-readout") == f"{float(depth[y, x]):#.4g}"  # 4 digits
    assert "z-depth" in page.text_content("#pick-readout")


def test_reference_shows_the_rmse(page, server):
    engine = server[0]
    page.select_option("#spp", "16")
    page.click("#reference-run")
    page.wait_for_selector("#reference-rmse", timeout=120_000)
    shown = float(page.text_content("#reference-rmse"))
    result = engine.reference.status()["result"]
    assert result["spp"] == 16 and result["focus"] == _value(page, "#focus-readout")
    assert shown == pytest.approx(result["rmse"], rel=1e-3)
    assert page.is_visible("#ref-difference")


def test_fit_a_target_and_apply(page, server, tmp_path):
    from test_viewer import cheap_model

    engine = server[0]
    truth = dict(focus_distance=2.5, aperture_radius=0.7 * engine.aperture_max)
    target = np.asarray(cheap_model(engine.source.rgb, engine.source.depth,
                                    engine.camera.replace(**truth)), np.float32)
    path = tmp_path / "target.exr"
    dofjax.write_exr(str(path), target)
    page.set_input_files("#target-file", str(path))
    page.wait_for_function("document.getElementById('target-name').textContent === 'target.exr'")
    page.click("#fit-run")
    page.wait_for_selector("#fit-table", state="visible", timeout=240_000)
    assert _value(page, "#fit-focus") == pytest.approx(truth["focus_distance"], rel=1e-4)
    assert _value(page, "#fit-aperture") == pytest.approx(truth["aperture_radius"], rel=1e-4)
    assert page.text_content("#fit-identifiable") == "yes"
    assert page.text_content("#fit-message") == "ok"
    assert " ± " in page.text_content("#fit-focus")
    page.click("#fit-apply")
    assert _value(page, "#focus-readout") == pytest.approx(truth["focus_distance"], rel=1e-4)


def test_overlay_and_screenshot(page, tmp_path):
    n0 = _painted(page)
    page.keyboard.press("3")  # the signed CoC overlay
    page.wait_for_function(f"window.dofjaxView.painted.length > {n0}")
    assert page.is_visible("#legend") and "px" in page.text_content("#legend-hi")
    page.keyboard.press("1")
    page.wait_for_function(f"window.dofjaxView.painted.length > {n0 + 1}")
    assert page.errors == []
    shot = tmp_path / "viewer.png"
    page.screenshot(path=str(shot), full_page=True)
    assert shot.stat().st_size > 10_000
    print(f"screenshot: {shot}")
    if os.environ.get("DOFJAX_VIEWER_SCREENSHOT"):
        shutil.copy(shot, os.environ["DOFJAX_VIEWER_SCREENSHOT"])
