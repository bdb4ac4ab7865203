"""The viewer's HTTP API and page: a Starlette app over an `Engine`.

Every endpoint takes numbers (camera, bokeh, pixel) or an uploaded body, never a path: the only
files read are the ones named on the command line. Bad requests get 400 with `{"error": ...}`;
an upload over the size limit 413; a job already running 409.
"""

from __future__ import annotations

import asyncio
import math
import os
import tempfile
from importlib import resources

import numpy as np
from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

import dofjax

from . import _engine
from ._engine import Bokeh, Engine, encode

STATIC = str(resources.files("dofjax._viewer") / "static")
MAX_UPLOAD = 64 * 2**20
_IMAGE_SUFFIXES = (".exr", ".png", ".jpg", ".jpeg", ".tif", ".tiff", ".hdr")


class BadRequest(ValueError):
    """A request the API refuses (400)."""


def _number(q, name: str, *, default=None) -> float:
    raw = q.get(name)
    if raw is None:
        if default is None:
            raise BadRequest(f"missing parameter {name!r}")
        return default
    try:
        value = float(raw)
    except ValueError:
        raise BadRequest(f"parameter {name!r}: not a number: {raw!r}") from None
    if not math.isfinite(value):
        raise BadRequest(f"parameter {name!r}: must be finite, got {raw!r}")
    return value


def _integer(q, name: str, *, default=None) -> int:
    value = _number(q, name, default=default)
    if value != int(value):
        raise BadRequest(f"parameter {name!r}: must be an integer, got {q.get(name)!r}")
    return int(value)


def _bokeh(q) -> Bokeh:
    blades = _integer(q, "blades", default=0)
    if blades == 0:
        return Bokeh()
    if not 3 <= blades <= 16:
        raise BadRequest(f"parameter 'blades': 0 (disc) or 3..16, got {blades}")
    rotation = _number(q, "rotation", default=0.0) % 360.0
    return Bokeh(blades=blades, rotation=round(rotation, 1))


class FrameGate:
    """At most one frame renders at a time; a request waiting for its turn is answered at once
    (204) when a newer one from the same page arrives: the latest value wins, nothing queues.
    The app has one gate per lane (live, final), so a slow exact render never holds up the
    live frames."""

    def __init__(self):
        self._loop = None

    def _ensure(self):
        loop = asyncio.get_running_loop()
        if self._loop is not loop:  # one per event loop (a test client starts its own)
            self._loop, self._lock, self._waiting, self._latest = loop, asyncio.Lock(), {}, {}

    async def enter(self, client: str, seq: int) -> bool:
        self._ensure()
        if seq < self._latest.get(client, -1):
            return False
        self._latest[client] = seq
        old = self._waiting.get(client)
        if old is not None and not old.done():
            old.set_result(False)
        superseded = self._loop.create_future()
        self._waiting[client] = superseded
        acquire = asyncio.ensure_future(self._lock.acquire())
        try:
            await asyncio.wait({acquire, superseded}, return_when=asyncio.FIRST_COMPLETED)
        except asyncio.CancelledError:  # the request went away: never keep the lock
            self._drop(acquire)
            raise
        if superseded.done():
            self._drop(acquire)
            return False
        if self._waiting.get(client) is superseded:
            del self._waiting[client]
        return True

    def leave(self) -> None:
        self._lock.release()

    def _drop(self, acquire) -> None:
        if acquire.done() and not acquire.cancelled():
            self._lock.release()
        else:
            acquire.cancel()


def create_app(engine: Engine, *, max_upload: int = MAX_UPLOAD) -> Starlette:
    """The Starlette app serving the page and the API for `engine`."""
    gates = {"live": FrameGate(), "final": FrameGate()}
    source = engine.source

    def info(request: Request) -> JSONResponse:
        cam = engine.camera
        h, w = source.depth.shape
        return JSONResponse({
            "name": source.name, "width": w, "height": h,
            "focus": engine.camera_focus(), "aperture": engine.camera_aperture(),
            "focus_range": [engine.focus_min, engine.focus_max],
            "aperture_max": engine.aperture_max, "depth_range": [engine.depth_min,
                                                                 engine.depth_max],
            "window": engine.window, "fov": float(cam.fov),
            "photographic": source.photographic, "has_scene": source.scene is not None,
            "target": engine.target_name, "max_upload": max_upload,
            "live_exact": _engine.LIVE_METHOD == _engine.FINAL_METHOD,
            "methods": {"live": _engine.LIVE_METHOD or "default",
                        "final": _engine.FINAL_METHOD or "default"},
            "version": dofjax.__version__,
        })

    async def frame(request: Request) -> Response:
        q = request.query_params
        focus, aperture = _number(q, "focus"), _number(q, "aperture")
        bokeh = _bokeh(q)
        view = q.get("view", "image")
        if view not in ("image", "depth", "coc"):
            raise BadRequest(f"parameter 'view': image, depth or coc, got {view!r}")
        quality = q.get("quality", "final")
        if quality not in ("live", "final"):
            raise BadRequest(f"parameter 'quality': live or final, got {quality!r}")
        exposure = _number(q, "exposure", default=0.0)
        if abs(exposure) > 20:
            raise BadRequest(f"parameter 'exposure': within +-20 stops, got {exposure}")
        client, seq = q.get("client", ""), _integer(q, "seq", default=0)
        if len(client) > 64:
            raise BadRequest("parameter 'client': at most 64 characters")
        try:
            engine.check_camera(focus, aperture)
        except ValueError as exc:
            raise BadRequest(str(exc)) from None
        gate = gates[quality]
        if not await gate.enter(client, seq):
            return Response(status_code=204, headers={"X-Dofjax-Dropped": "superseded"})
        try:
            method = _engine.LIVE_METHOD if quality == "live" else _engine.FINAL_METHOD
            start = asyncio.get_running_loop().time()

            def work() -> bytes:
                if view == "depth":
                    return encode(engine.depth_picture(), "jpeg", linear=False)
                if view == "coc":
                    return encode(engine.coc_picture(focus, aperture), "jpeg", linear=False)
                return encode(engine.image(focus, aperture, bokeh, method), "jpeg",
                              exposure=exposure)

            body = await run_in_threadpool(work)
            ms = (asyncio.get_running_loop().time() - start) * 1e3
        finally:
            gate.leave()
        exact = method == _engine.FINAL_METHOD or view != "image"  # overlays: no method
        return Response(body, media_type="image/jpeg", headers={
            "X-Dofjax-Seq": str(seq), "X-Dofjax-Exact": "1" if exact else "0",
            "X-Dofjax-Render-Ms": f"{ms:.1f}", "Cache-Control": "no-store"})

    async def depth(request: Request) -> JSONResponse:
        q = request.query_params
        x, y = _integer(q, "x"), _integer(q, "y")
        try:
            z = engine.depth_at(x, y)
        except ValueError as exc:
            raise BadRequest(str(exc)) from None
        background = not math.isfinite(z)
        focus = engine.focus_max if background else float(
            np.clip(z, engine.focus_min, engine.focus_max))
        return JSONResponse({"x": x, "y": y, "depth": None if background else z,
                             "background": background, "focus": focus})

    def _camera_query(q):
        focus, aperture = _number(q, "focus"), _number(q, "aperture")
        try:
            engine.check_camera(focus, aperture)
        except ValueError as exc:
            raise BadRequest(str(exc)) from None
        return focus, aperture, _bokeh(q)

    async def reference_start(request: Request) -> JSONResponse:
        q = request.query_params
        focus, aperture, bokeh = _camera_query(q)
        spp = _integer(q, "spp", default=64)
        seed = _integer(q, "seed", default=0)
        try:
            engine.start_reference(focus, aperture, bokeh, spp, seed)
        except RuntimeError as exc:
            return JSONResponse({"error": str(exc)}, status_code=409)
        except ValueError as exc:
            raise BadRequest(str(exc)) from None
        return JSONResponse(engine.reference.status(), status_code=202)

    async def fit_start(request: Request) -> JSONResponse:
        focus, aperture, bokeh = _camera_query(request.query_params)
        try:
            engine.start_fit(focus, aperture, bokeh)
        except RuntimeError as exc:
            return JSONResponse({"error": str(exc)}, status_code=409)
        except ValueError as exc:
            raise BadRequest(str(exc)) from None
        return JSONResponse(engine.fit.status(), status_code=202)

    def job_status(job):
        async def status(request: Request) -> JSONResponse:
            return JSONResponse(job.status())
        return status

    def job_image(job, names):
        async def image(request: Request) -> Response:
            which = request.path_params["which"]
            if which not in names:
                raise BadRequest(f"unknown image {which!r}: one of {', '.join(names)}")
            body = job.image(which)
            if body is None:
                return JSONResponse({"error": f"no {job.name} result yet"}, status_code=404)
            return Response(body, media_type="image/png", headers={"Cache-Control": "no-store"})
        return image

    async def target_upload(request: Request) -> JSONResponse:
        name = os.path.basename(request.query_params.get("name", "upload.exr"))
        suffix = os.path.splitext(name)[1].lower()
        if suffix not in _IMAGE_SUFFIXES:
            raise BadRequest(f"{name}: unsupported file type; upload one of "
                             f"{', '.join(_IMAGE_SUFFIXES)}")
        declared = request.headers.get("content-length")
        if declared is not None and declared.isdigit() and int(declared) > max_upload:
            return JSONResponse({"error": f"{name}: {int(declared)} bytes is over the upload "
                                          f"limit of {max_upload} bytes"}, status_code=413)
        chunks, size = [], 0
        async for chunk in request.stream():
            size += len(chunk)
            if size > max_upload:
                return JSONResponse({"error": f"{name}: over the upload limit of {max_upload} "
                                              "bytes"}, status_code=413)
            chunks.append(chunk)
        if size == 0:
            raise BadRequest(f"{name}: empty upload")

        def load():
            with tempfile.TemporaryDirectory(prefix="dofjax-view-") as tmp:
                path = os.path.join(tmp, "target" + suffix)
                with open(path, "wb") as f:
                    f.write(b"".join(chunks))
                try:
                    rgb = dofjax.read_image(path)
                except (ValueError, OSError) as exc:
                    raise BadRequest(f"{name}: not a readable image "
                                     f"({str(exc).replace(path, name)})") from None
            engine.set_target(rgb, name)

        try:
            await run_in_threadpool(load)
        except ValueError as exc:
            raise BadRequest(str(exc)) from None
        h, w = source.depth.shape
        return JSONResponse({"target": name, "width": w, "height": h})

    async def target_image(request: Request) -> Response:
        if engine.target is None:
            return JSONResponse({"error": "no target image loaded"}, status_code=404)
        body = await run_in_threadpool(encode, engine.target, "png")
        return Response(body, media_type="image/png", headers={"Cache-Control": "no-store"})

    async def download(request: Request) -> Response:
        fmt = request.path_params["fmt"]
        if fmt not in ("exr", "png"):
            raise BadRequest(f"download format exr or png, got {fmt!r}")
        q = request.query_params
        focus, aperture, bokeh = _camera_query(q)
        exposure = _number(q, "exposure", default=0.0)
        camera = engine.camera_at(focus, aperture)

        def make() -> bytes:
            img = engine.image(focus, aperture, bokeh)
            if fmt == "png":
                return encode(img, "png", exposure=exposure)
            meta = {"focus_distance": focus, "aperture_radius": aperture,
                    "fov": float(camera.fov), "width": camera.width, "height": camera.height,
                    "eye": np.asarray(camera.eye, float).tolist(),
                    "target": np.asarray(camera.target, float).tolist(),
                    "up": np.asarray(camera.up, float).tolist(),
                    "pixel_scale": float(camera.pixel_scale), "bokeh": bokeh.describe(),
                    "defocus_method": _engine.FINAL_METHOD or "default",
                    "source": source.name, "generator": "dofjax view",
                    "version": dofjax.__version__}
            if source.photographic:
                meta.update(source.photographic)
                meta["f_number"] = source.photographic["focal_length"] / (2.0 * aperture) \
                    if aperture > 0 else None
                if meta["f_number"] is None:
                    del meta["f_number"]
            with tempfile.TemporaryDirectory(prefix="dofjax-view-") as tmp:
                path = os.path.join(tmp, "view.exr")
                dofjax.write_exr(path, img, source.depth, meta)
                with open(path, "rb") as f:
                    return f.read()

        body = await run_in_threadpool(make)
        media = "image/x-exr" if fmt == "exr" else "image/png"
        return Response(body, media_type=media, headers={
            "Content-Disposition": f'attachment; filename="dofjax-view.{fmt}"',
            "Cache-Control": "no-store"})

    async def index(request: Request) -> FileResponse:
        return FileResponse(os.path.join(STATIC, "index.html"),
                            headers={"Cache-Control": "no-store"})

    async def bad_request(request: Request, exc: BadRequest) -> JSONResponse:
        return JSONResponse({"error": str(exc)}, status_code=400)

    routes = [
        Route("/", index),
        Route("/favicon.ico", lambda request: Response(status_code=204)),
        Route("/api/info", info),
        Route("/api/frame", frame),
        Route("/api/depth", depth),
        Route("/api/reference", reference_start, methods=["POST"]),
        Route("/api/reference", job_status(engine.reference)),
        Route("/api/reference/{which}.png",
              job_image(engine.reference, ("reference", "postprocess", "difference"))),
        Route("/api/fit", fit_start, methods=["POST"]),
        Route("/api/fit", job_status(engine.fit)),
        Route("/api/fit/{which}.png", job_image(engine.fit, ("residual", "target"))),
        Route("/api/target", target_upload, methods=["POST"]),
        Route("/api/target.png", target_image),
        Route("/api/download.{fmt}", download),
        Mount("/static", StaticFiles(directory=STATIC), name="static"),
    ]
    app = Starlette(routes=routes, exception_handlers={BadRequest: bad_request})
    app.state.engine = engine
    return app


