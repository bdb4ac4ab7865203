"""dofjax view's latency in a real browser: slider change to new image painted, and start-up.

    python benchmarks/viewer_latency.py [--sizes 256 512 1024] [--changes 40] [--warmup 5]
        [--screenshot docs/viewer.png]

For each size N, starts `dofjax view examples/quads.json --width N --height N` twice with one
fresh persistent compilation cache (the first run compiles and fills it, the second loads from
it) and times the command to its "ready" line (the live method compiled) and to the exact
method's (compiled after "ready"; measuring starts once it is). On the second server it drives
Debian's headless Chromium (Playwright, /usr/bin/chromium): each change moves the focus or the
aperture slider (alternately, to seeded random positions) and dispatches the slider's `input`
event, as a drag does; the page reports the time from that event to the frame painted with the
new value (`window.dofjaxView.painted`: after the image's decode and the next animation frame).
Medians over `--changes` changes after `--warmup`. `--screenshot` saves the page at the scene's own
size (512x384) after a reference run and a click to focus. Writes
benchmarks/results/viewer_latency.md and .png.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SCENE = os.path.join(ROOT, "examples", "quads.json")
CHROMIUM = "/usr/bin/chromium"


class Viewer:
    """A `dofjax view` subprocess; `ready_seconds` from the start of the command to "ready"."""

    def __init__(self, args: list[str], cache: str | None = None):
        start = time.perf_counter()
        first = [] if cache is None else ["--jax-cache", cache]
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "dofjax._cli", *first, "view", SCENE, *args],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT)
        self.url = None
        lines = []
        for line in self.proc.stdout:
            lines.append(line)
            m = re.search(r"ready at (\S+)", line)
            if m:
                self.url = m.group(1)
                break
        if self.url is None:
            raise SystemExit("viewer_latency: dofjax view did not start:\n" + "".join(lines))
        self.ready_seconds = time.perf_counter() - start
        self.exact_seconds = None
        for line in self.proc.stdout:  # the exact method compiles after "ready"
            if "exact method is compiled" in line:
                self.exact_seconds = time.perf_counter() - start
                break
        if self.exact_seconds is None:
            raise SystemExit("viewer_latency: dofjax view stopped before the exact method "
                             "compiled")

    def close(self):
        self.proc.terminate()
        self.proc.wait(30)


MEASURE = """async ([id, value]) => {
  const v = window.dofjaxView, slider = document.getElementById(id);
  v.refineDelay = 1e9;  // live frames only: no exact refinement between changes
  while (v.busy()) await new Promise((r) => setTimeout(r, 2));
  const n = v.painted.length;
  slider.value = value;
  slider.dispatchEvent(new Event("input", {bubbles: true}));
  while (v.painted.length === n || v.busy()) await new Promise((r) => setTimeout(r, 2));
  return v.painted[v.painted.length - 1];
}"""


def measure(page, url: str, changes: int, warmup: int, seed: int = 0) -> dict:
    import random

    rng = random.Random(seed)
    page.goto(url)
    page.wait_for_function("window.dofjaxView && window.dofjaxView.painted.length > 0",
                           timeout=120_000)
    latencies, server = [], []
    for i in range(warmup + changes):
        slider = "focus" if i % 2 == 0 else "aperture"
        painted = page.evaluate(MEASURE, [slider, str(rng.randrange(0, 1001))])
        page.wait_for_timeout(50)
        if i >= warmup:
            latencies.append(painted["latency"])
            server.append(painted["serverMs"])
    latencies.sort()
    return {"median": statistics.median(latencies),
            "p90": latencies[int(0.9 * (len(latencies) - 1))],
            "server": statistics.median(server), "n": len(latencies)}


def screenshot(page, url: str, path: str) -> None:
    page.goto(url)
    page.wait_for_function("window.dofjaxView && window.dofjaxView.painted.length > 0",
                           timeout=120_000)
    box = page.locator("#frame").bounding_box()
    n = page.evaluate("window.dofjaxView.painted.length")
    # the coffee cup quad (depth 3): focus on it
    page.mouse.click(box["x"] + 0.56 * box["width"], box["y"] + 0.30 * box["height"])
    page.wait_for_function(f"window.dofjaxView.painted.length > {n}")
    page.select_option("#spp", "64")
    page.click("#reference-run")
    page.wait_for_selector("#reference-rmse", timeout=600_000)
    page.wait_for_timeout(500)
    page.screenshot(path=path, full_page=True)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024])
    p.add_argument("--changes", type=int, default=40)
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--screenshot", help="also save a screenshot of the page here (PNG)")
    p.add_argument("--out", default=os.path.join(HERE, "results", "viewer_latency"))
    a = p.parse_args(argv)
    from playwright.sync_api import sync_playwright

    if not os.path.exists(CHROMIUM):
        raise SystemExit(f"viewer_latency: no Chromium at {CHROMIUM}: apt-get install chromium")
    rows = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True,
                                     args=["--no-sandbox"])
        page = browser.new_page(viewport={"width": 1400, "height": 1000})
        for n in a.sizes:
            with tempfile.TemporaryDirectory(prefix="viewer-latency-cache-") as cache:
                size = ["--width", str(n), "--height", str(n)]
                cold = Viewer(size, cache)
                cold.close()
                warm = Viewer(size, cache)
                try:
                    m = measure(page, warm.url, a.changes, a.warmup)
                finally:
                    warm.close()
            load = os.getloadavg()[0]
            rows.append(dict(size=n, cold=cold.ready_seconds, warm=warm.ready_seconds,
                             cold_exact=cold.exact_seconds, warm_exact=warm.exact_seconds,
                             load=load, **m))
            print(f"{n}x{n}: ready {cold.ready_seconds:.1f} s (compiling), "
                  f"{warm.ready_seconds:.1f} s (cache), exact method {cold.exact_seconds:.1f} / "
                  f"{warm.exact_seconds:.1f} s; slider to paint median "
                  f"{m['median']:.0f} ms, p90 {m['p90']:.0f} ms (render {m['server']:.0f} ms), "
                  f"load {load:.1f}", flush=True)
        if a.screenshot:
            viewer = Viewer([])
            try:
                screenshot(page, viewer.url, a.screenshot)
            finally:
                viewer.close()
            print(f"wrote {a.screenshot}")
        version = browser.version
        browser.close()
    write(rows, a, version)


def write(rows, a, browser_version) -> None:
    import jax

    cpus = os.cpu_count()
    head = ("| size | slider to paint, median ms | p90 ms | server render + encode, median ms"
            " | ready, compiling s | ready, from the cache s | exact method compiled, compiling"
            " / from the cache s | load average |")
    lines = [
        "# dofjax view: latency in a real browser",
        "",
        f"`python benchmarks/viewer_latency.py --sizes {' '.join(map(str, a.sizes))} "
        f"--changes {a.changes} --warmup {a.warmup}`; examples/quads.json at N x N, "
        f"headless Chromium {browser_version}, JAX {jax.__version__}, {cpus} CPU cores "
        "(the load average, 1 min, is the machine's at the end of the size's run: other "
        "processes share the cores). Slider to paint: from the slider's input event to the "
        "next animation frame after the new image is decoded, "
        f"median over {a.changes} changes after {a.warmup}. Ready: from the command to its "
        "'ready' line (the live method compiled), with a fresh persistent compilation cache "
        "(compiling) and again with it filled; the exact method compiles after 'ready', beside "
        "the running server.",
        "",
        head,
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['size']}x{r['size']} | {r['median']:.0f} | {r['p90']:.0f} | "
                     f"{r['server']:.0f} | {r['cold']:.1f} | {r['warm']:.1f} | "
                     f"{r['cold_exact']:.1f} / {r['warm_exact']:.1f} | {r['load']:.1f} |")
    os.makedirs(os.path.dirname(a.out), exist_ok=True)
    with open(a.out + ".md", "w") as f:
        f.write("\n".join(lines) + "\n")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("(no matplotlib: no plot; pip install -e '.[bench]')")
    else:
        fig, ax = plt.subplots(figsize=(5, 3.2))
        sizes = [r["size"] for r in rows]
        ax.plot(sizes, [r["median"] for r in rows], "o-", label="slider to paint (median)")
        ax.plot(sizes, [r["server"] for r in rows], "s--", label="server render + encode")
        ax.axhline(100, color="grey", lw=0.8, ls=":", label="100 ms")
        ax.set_xscale("log", base=2)
        ax.set_xticks(sizes, [f"{s}" for s in sizes])
        ax.set_xlabel("image size N (N x N px)")
        ax.set_ylabel("ms")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(a.out + ".png", dpi=120)
    print(f"wrote {a.out}.md")


if __name__ == "__main__":
    main()
