"""The viewer's work: frames for a (focus, aperture, bokeh), the reference and the fit jobs.

Everything here calls the library (`defocus_fn`, `coc_radius`, `render_reference`,
`fit_focus`); this module only chooses programs, caches them and turns arrays into pictures.
"""

from __future__ import annotations

import functools
import io
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import jax
import numpy as np
from PIL import Image

import dofjax

from .._io import srgb_encode
from ._source import Source, check_target

# The defocus methods, in one place: LIVE while a slider moves (the fastest the library offers),
# FINAL when it rests (the exact kernel; None: the library's default). Equal: no refinement.
LIVE_METHOD: str | None = "sliced"
FINAL_METHOD: str | None = "exact"

# Difference and residual pictures span +-max|difference|, at least +-1 % of white: a match to
# rounding is shown white, not as amplified noise.
_MIN_SCALE = 0.01

# Compiled defocus programs kept (one per method and bokeh): a new bokeh compiles once.
_PROGRAMS = 6


@dataclass(frozen=True)
class Bokeh:
    """The aperture's shape: a disc, or a polygon with `blades` blades rotated `rotation` deg."""

    blades: int | None = None
    rotation: float = 0.0

    def options(self) -> dict:
        if self.blades is None:
            return {"shape": "disc"}
        return {"shape": "polygon", "blades": self.blades,
                "rotation": math.radians(self.rotation)}

    def describe(self) -> str:
        return "disc" if self.blades is None else f"{self.blades} blades, {self.rotation:g} deg"


def _method_kw(method: str | None) -> dict:
    return {} if method is None else {"method": method}


_LUT_MAX = 65535


@functools.cache
def _srgb8_table() -> np.ndarray:
    return np.round(srgb_encode(np.linspace(0.0, 1.0, _LUT_MAX + 1)) * 255.0).astype(np.uint8)


def encode(rgb_or_srgb8: np.ndarray, fmt: str, *, linear: bool = True, exposure: float = 0.0,
           quality: int = 90) -> bytes:
    """PNG or JPEG bytes of a linear image (sRGB-encoded here) or of 8-bit sRGB."""
    if linear:
        # the sRGB OETF through a 16-bit table of it: a few ms at 512x512 instead of ~30 for
        # the power function per value (at most one 8-bit level apart, at rounding boundaries)
        x = np.asarray(rgb_or_srgb8, np.float32) * np.float32(_LUT_MAX * 2.0 ** exposure)
        pixels = _srgb8_table()[np.clip(x + 0.5, 0, _LUT_MAX).astype(np.uint16)]
    else:
        pixels = np.asarray(rgb_or_srgb8, np.uint8)
    out = io.BytesIO()
    if fmt == "jpeg":
        Image.fromarray(pixels).save(out, format="JPEG", quality=quality, subsampling=0)
    else:
        Image.fromarray(pixels).save(out, format="PNG", compress_level=1)
    return out.getvalue()


def _ramp(t: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """Piecewise-linear colour ramp: t in [0, 1] -> 8-bit sRGB through `stops` (n, 3)."""
    t = np.clip(np.nan_to_num(t, nan=0.0), 0.0, 1.0) * (len(stops) - 1)
    i = np.minimum(t.astype(int), len(stops) - 2)
    f = (t - i)[..., None]
    return np.round(stops[i] * (1 - f) + stops[i + 1] * f).astype(np.uint8)


# ColorBrewer RdBu (reversed): blue behind the focal plane (c < 0), white on it, red in front.
DIVERGING = np.array([[5, 48, 97], [67, 147, 195], [247, 247, 247], [214, 96, 77],
                      [103, 0, 31]], np.float64)
# Near is bright: 1/z mapped from the scene's far end (dark) to its near end (light).
SEQUENTIAL = np.array([[0, 0, 4], [87, 16, 110], [188, 55, 84], [249, 142, 9],
                       [252, 255, 164]], np.float64)  # inferno


class Engine:
    """Renders frames and runs the reference and fit jobs for one `Source`.

    Args:
        source: the loaded input.
        window: the defocus window, px (largest |CoC|); None: twice the input camera's largest
            |CoC| over the focus range, between 8 and 32 px. The aperture slider stops where
            the CoC reaches it.
        fit_options: extra keyword arguments for `dofjax.fit_focus`.
    """

    def __init__(self, source: Source, *, window: float | None = None,
                 fit_options: dict | None = None):
        self.source = source
        self.camera = source.camera
        depth = source.depth
        finite = depth[np.isfinite(depth)]
        if finite.size == 0:
            raise ValueError(f"{source.name}: every pixel is background (no finite depth): "
                             "there is nothing to focus on")
        self.depth_min, self.depth_max = float(finite.min()), float(finite.max())
        self.focus_min = 0.8 * self.depth_min
        self.focus_max = 1.25 * self.depth_max
        if source.photographic:
            self.focus_min = max(self.focus_min, 1.01 * source.photographic["focal_length"])
        # |CoC| per unit aperture at the two ends of the focus range (the largest over it)
        per_unit = max(self._max_coc(d, 1.0) for d in (self.focus_min, self.focus_max))
        a0 = float(self.camera.aperture_radius)
        if window is None:
            window = float(min(32.0, max(8.0, 2.0 * a0 * per_unit)))
        self.window = float(window)
        self.aperture_max = self.window / per_unit
        self.fit_options = dict(fit_options or {})
        self._programs: OrderedDict = OrderedDict()
        self._programs_lock = threading.Lock()
        self._warming: dict = {}
        self.final_ready = threading.Event()
        self.reference = Job("reference")
        self.fit = Job("fit")
        self.target = source.target
        self.target_name = source.target_name

    # --------------------------------------------------------------------- camera and programs

    def camera_at(self, focus: float, aperture: float) -> dofjax.Camera:
        return self.camera.replace(focus_distance=focus, aperture_radius=aperture)

    def _max_coc(self, focus: float, aperture: float) -> float:
        c = dofjax.coc_radius(self.source.depth, self.camera_at(focus, aperture))
        return float(np.max(np.abs(np.asarray(c))))

    def check_camera(self, focus: float, aperture: float) -> None:
        if not (math.isfinite(focus) and self.focus_min * 0.999 <= focus
                <= self.focus_max * 1.001):
            raise ValueError(f"focus {focus!r} is outside the viewer's range "
                             f"[{self.focus_min:.6g}, {self.focus_max:.6g}]")
        if not (math.isfinite(aperture) and 0.0 <= aperture <= self.aperture_max * 1.001):
            raise ValueError(f"aperture {aperture!r} is outside the viewer's range "
                             f"[0, {self.aperture_max:.6g}]")

    def program(self, method: str | None, bokeh: Bokeh) -> Callable:
        """The jitted `f(focus, aperture) -> image` for a method and bokeh (compiled once)."""
        key = (method, bokeh)
        with self._programs_lock:
            if key in self._programs:
                self._programs.move_to_end(key)
                return self._programs[key]
            f = jax.jit(dofjax.defocus_fn(
                self.source.rgbd, self.camera, window=self.window, margin=self.source.margin,
                **_method_kw(method), **bokeh.options()))
            self._programs[key] = f
            while len(self._programs) > _PROGRAMS:
                self._programs.popitem(last=False)
            return f

    def warm_up(self, bokeh: Bokeh = Bokeh(), *, background: bool = False) -> None:
        """Compile (or load from the persistent cache) the live and final programs, side by
        side (XLA compiles a program on one core).

        background: return once the live program is ready; the final one goes on compiling
        (`final_ready` is set when it is), and a final frame asked for meanwhile waits for it.
        """
        errors = []

        def run(method):
            try:
                self.image(self.camera_focus(), self.camera_aperture(), bokeh, method)
            except Exception as exc:  # re-raised in the caller's thread, or at the first frame
                errors.append(exc)
            if method == FINAL_METHOD:
                self.final_ready.set()

        methods = [LIVE_METHOD] + ([FINAL_METHOD] if FINAL_METHOD != LIVE_METHOD else [])
        threads = [threading.Thread(target=run, args=(m,), daemon=True) for m in methods]
        for m, t in zip(methods, threads):
            self._warming[(m, bokeh)] = t
            t.start()
        for t in threads[:1] if background else threads:
            t.join()
        if errors:
            raise errors[0]

    def camera_focus(self) -> float:
        return float(np.clip(float(self.camera.focus_distance), self.focus_min, self.focus_max))

    def camera_aperture(self) -> float:
        return float(min(float(self.camera.aperture_radius), self.aperture_max))

    # --------------------------------------------------------------------- frames

    def image(self, focus: float, aperture: float, bokeh: Bokeh,
              method: str | None = FINAL_METHOD) -> np.ndarray:
        warming = self._warming.get((method, bokeh))
        if warming is not None and warming is not threading.current_thread():
            warming.join()  # one compilation, not a second one beside it
        f = self.program(method, bokeh)
        dtype = np.asarray(self.camera.focus_distance).dtype
        return np.asarray(f(np.asarray(focus, dtype), np.asarray(aperture, dtype)))

    def coc(self, focus: float, aperture: float) -> np.ndarray:
        return np.asarray(dofjax.coc_radius(self.source.depth, self.camera_at(focus, aperture)))

    def coc_picture(self, focus: float, aperture: float) -> np.ndarray:
        """Signed CoC as 8-bit colour, -window (blue) .. 0 (white) .. +window px (red)."""
        c = self.coc(focus, aperture)
        return _ramp(0.5 + 0.5 * c / self.window, DIVERGING)

    def depth_picture(self) -> np.ndarray:
        """Inverse depth as 8-bit colour: the far end of the range dark, the near end bright,
        the background (+inf) black."""
        inv = 1.0 / self.source.depth  # 0 at +inf
        lo, hi = 1.0 / self.focus_max, 1.0 / self.focus_min
        pic = _ramp((inv - lo) / (hi - lo), SEQUENTIAL)
        pic[~np.isfinite(self.source.depth)] = 0
        return pic

    def depth_at(self, x: int, y: int) -> float:
        h, w = self.source.depth.shape
        if not (0 <= x < w and 0 <= y < h):
            raise ValueError(f"pixel ({x}, {y}) is outside the {w}x{h} image")
        return float(self.source.depth[y, x])

    # --------------------------------------------------------------------- jobs

    def start_reference(self, focus: float, aperture: float, bokeh: Bokeh, spp: int,
                        seed: int = 0) -> None:
        self.reference.check_idle()
        if self.source.scene is None:
            raise ValueError("no scene: the reference ray traces the scene, and this input is an "
                             "RGB-D image (start the viewer with a scene file or data_gen sample)")
        if not (isinstance(spp, int) and 1 <= spp <= 65536):
            raise ValueError(f"spp must be an integer in [1, 65536], got {spp!r}")
        self.check_camera(focus, aperture)
        camera = self.camera_at(focus, aperture)

        def run(job: Job) -> dict:
            start = time.perf_counter()
            ref = dofjax.render_reference(
                self.source.scene, camera, spp=spp, key=jax.random.key(seed),
                progress=lambda done, total: job.progress(done, total), **bokeh.options())
            ref = np.asarray(ref, np.float32)
            ref_seconds = time.perf_counter() - start
            self.image(focus, aperture, bokeh)  # compiled before timing the post-process
            start = time.perf_counter()
            post = self.image(focus, aperture, bokeh)
            post_seconds = time.perf_counter() - start
            diff = post - ref
            rmse = float(np.sqrt(np.mean(diff.astype(np.float64) ** 2)))
            scale = max(float(np.max(np.abs(diff))), _MIN_SCALE)
            return {
                "focus": focus, "aperture": aperture, "spp": spp, "bokeh": bokeh.describe(),
                "rmse": rmse, "reference_seconds": ref_seconds,
                "postprocess_seconds": post_seconds, "difference_scale": scale,
                "images": {"reference": encode(ref, "png"), "postprocess": encode(post, "png"),
                           "difference": encode(_ramp(0.5 + 0.5 * diff.mean(-1) / scale,
                                                      DIVERGING), "png", linear=False)},
            }

        self.reference.start(run)

    def set_target(self, target: np.ndarray, name: str) -> None:
        bad = ~np.isfinite(np.asarray(target))
        if bad.any():
            raise ValueError(f"{name}: the target has {int(bad.sum())} NaN/inf value(s)")
        self.target = check_target(self.source, target, name)
        self.target_name = name

    def start_fit(self, focus: float, aperture: float, bokeh: Bokeh) -> None:
        self.fit.check_idle()
        if self.target is None:
            raise ValueError("no target image: load one (the file button, or --target FILE)")
        self.check_camera(focus, aperture)
        guess = self.camera_at(focus, max(aperture, 0.05 * self.aperture_max))
        target = self.target
        options = {"bounds": {"focus_distance": (self.focus_min, self.focus_max),
                              "aperture_radius": (0.0, self.aperture_max)},
                   "window": self.window, "margin": self.source.margin,
                   "defocus_options": {**_method_kw(FINAL_METHOD), **bokeh.options()},
                   **self.fit_options}

        def run(job: Job) -> dict:
            start = time.perf_counter()
            r = dofjax.fit_focus(target, self.source.rgbd, guess, **options)
            seconds = time.perf_counter() - start
            d, a = float(r.focus_distance), float(r.aperture_radius)
            model = options.get("model")
            if model is None:
                d_show = float(np.clip(d, self.focus_min, self.focus_max))
                a_show = float(np.clip(a, 0.0, self.aperture_max))
                predicted = self.image(d_show, a_show, bokeh)
            else:
                predicted = np.asarray(model(self.source.rgb, self.source.depth,
                                             self.camera_at(d, a)))
            residual = np.asarray(target, np.float64) - predicted
            scale = max(float(np.max(np.abs(residual))), _MIN_SCALE)
            return {
                "focus": d, "aperture": a,
                "focus_se": float(r.focus_distance_se), "aperture_se": float(r.aperture_radius_se),
                "focus_se_tiles": float(r.focus_distance_se_tiles),
                "aperture_se_tiles": float(r.aperture_radius_se_tiles),
                "identifiable": bool(r.identifiable), "converged": bool(r.converged),
                "ambiguous": bool(r.ambiguous), "message": str(r.message),
                "steps": int(r.steps), "rmse": float(np.sqrt(np.mean(residual ** 2))),
                "seconds": seconds, "residual_scale": scale, "target": self.target_name,
                "images": {"residual": encode(_ramp(0.5 + 0.5 * residual.mean(-1) / scale,
                                                    DIVERGING), "png", linear=False),
                           "target": encode(target, "png")},
            }

        self.fit.start(run)


class Job:
    """One background computation at a time, with progress and a result or an error."""

    def __init__(self, name: str):
        self.name = name
        self._lock = threading.Lock()
        self.state = "idle"
        self.done = self.total = 0
        self.started = self.finished = 0.0
        self.result: dict | None = None
        self.error: str | None = None

    def progress(self, done: int, total: int) -> None:
        self.done, self.total = int(done), int(total)

    def check_idle(self) -> None:
        if self.state == "running":
            raise RuntimeError(f"a {self.name} is already running")

    def start(self, work: Callable[[Job], dict]) -> None:
        with self._lock:
            if self.state == "running":
                raise RuntimeError(f"a {self.name} is already running")
            self.state, self.done, self.total = "running", 0, 0
            self.result, self.error = None, None
            self.started = time.perf_counter()
        threading.Thread(target=self._run, args=(work,), daemon=True,
                         name=f"dofjax-view-{self.name}").start()

    def _run(self, work) -> None:
        try:
            result = work(self)
        except Exception as exc:  # reported on the page; the server goes on
            with self._lock:
                self.error = f"{type(exc).__name__}: {exc}"
                self.state, self.finished = "error", time.perf_counter()
            return
        with self._lock:
            self.result, self.state, self.finished = result, "done", time.perf_counter()

    def wait(self, timeout: float | None = None) -> None:
        """Block until the job is not running (tests, scripts)."""
        end = None if timeout is None else time.perf_counter() + timeout
        while self.state == "running":
            if end is not None and time.perf_counter() > end:
                raise TimeoutError(f"{self.name} still running after {timeout} s")
            time.sleep(0.02)

    def status(self) -> dict:
        with self._lock:
            now = self.finished if self.state in ("done", "error") else time.perf_counter()
            out = {"state": self.state, "done": self.done, "total": self.total,
                   "elapsed": (now - self.started) if self.started else 0.0,
                   "error": self.error}
            if self.result is not None:
                out["result"] = {k: v for k, v in self.result.items() if k != "images"}
            return out

    def image(self, which: str) -> bytes | None:
        with self._lock:
            if self.result is None:
                return None
            return self.result["images"].get(which)
