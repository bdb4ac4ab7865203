// dofjax view: the page. Plain JS, no build step, no network beyond this server.
"use strict";

const $ = (id) => document.getElementById(id);
const SLIDER = 1000;  // slider positions
const view = {
  info: null,
  focus: 1, aperture: 0, exposure: 0, blades: 0, rotation: 0, mode: "image",
  client: Math.random().toString(36).slice(2, 10),
  seq: 0, version: 0, paintedSeq: 0, lastChange: 0, refineTimer: null, refineDelay: 150,
  lanes: {live: {inFlight: false, pending: false}, final: {inFlight: false, pending: false}},
  busy: () => busy(),
  shownExact: true,
  painted: [],   // {seq, quality, latency (ms from the input event to the paint), serverMs}
};
window.dofjaxView = view;

function fmt(x, digits = 4) {
  if (x === null || x === undefined || !isFinite(x)) return String(x);
  return Number(x).toPrecision(digits);
}

function setStatus(text, isError = false) {
  const s = $("status");
  s.textContent = text;
  s.classList.toggle("error", isError);
}

// ---------------------------------------------------------------- sliders <-> camera
function focusToSlider(d) {
  const [lo, hi] = view.info.focus_range;
  return Math.round(SLIDER * Math.log(d / lo) / Math.log(hi / lo));
}
function sliderToFocus(v) {
  const [lo, hi] = view.info.focus_range;
  return lo * Math.exp((v / SLIDER) * Math.log(hi / lo));
}
function apertureToSlider(a) { return Math.round(SLIDER * a / view.info.aperture_max); }
function sliderToAperture(v) { return (v / SLIDER) * view.info.aperture_max; }

function showCamera() {
  $("focus-readout").textContent = fmt(view.focus);
  $("focus-readout").dataset.value = String(view.focus);
  $("aperture-readout").textContent = fmt(view.aperture);
  $("aperture-readout").dataset.value = String(view.aperture);
  const p = view.info.photographic;
  if (p) {
    const n = view.aperture > 0 ? p.focal_length / (2 * view.aperture) : Infinity;
    $("photo-readout").hidden = false;
    $("photo-readout").textContent =
      `f/${isFinite(n) ? n.toFixed(n < 10 ? 1 : 0) : "inf"}, focal length ${fmt(p.focal_length, 3)}, ` +
      `sensor width ${fmt(p.sensor_width, 3)}`;
  }
  $("exposure-readout").textContent = `${view.exposure > 0 ? "+" : ""}${view.exposure} EV`;
  const q = cameraQuery();
  $("download-exr").href = `/api/download.exr?${q}`;
  $("download-png").href = `/api/download.png?${q}&exposure=${view.exposure}`;
  showLegend();
}

function cameraQuery() {
  const p = new URLSearchParams({focus: view.focus, aperture: view.aperture, blades: view.blades,
                                 rotation: view.rotation});
  return p.toString();
}

function showLegend() {
  const legend = $("legend");
  if (view.mode === "coc") {
    const w = view.info.window;
    legend.hidden = false;
    $("legend-bar").style.background =
      "linear-gradient(to right, #053061, #4393c3, #f7f7f7, #d6604d, #67001f)";
    $("legend-lo").textContent = `-${w} px`;
    $("legend-mid").textContent = "0";
    $("legend-hi").textContent = `+${w} px`;
    $("legend-caption").textContent = "signed CoC radius: behind the focal plane (blue), in front (red)";
  } else if (view.mode === "depth") {
    const [lo, hi] = view.info.focus_range;
    legend.hidden = false;
    $("legend-bar").style.background =
      "linear-gradient(to right, #000004, #57106e, #bc3754, #f98e09, #fcffa4)";
    $("legend-lo").textContent = fmt(hi, 3);
    $("legend-mid").textContent = "z-depth (1/z scale)";
    $("legend-hi").textContent = fmt(lo, 3);
    $("legend-caption").textContent = "far (dark) to near (bright); background black";
  } else {
    legend.hidden = true;
  }
}

// ---------------------------------------------------------------- frames: the latest value wins
// Two lanes: "live" frames (fast method) while a control moves, and a "final" frame (the exact
// method) once it rests. Each lane has at most one request in flight and keeps only the newest
// state to send next; a slow final render never holds up the live frames, and a final frame
// whose state has changed since it was asked for is not shown.
function changed(quality = "live") {
  view.version += 1;
  view.lastChange = performance.now();
  showCamera();
  requestFrame(quality);
}

function requestFrame(quality) {
  clearTimeout(view.refineTimer);
  const lane = view.lanes[quality];
  if (lane.inFlight) { lane.pending = true; return; }
  sendFrame(quality);
}

function busy() {
  return view.lanes.live.inFlight || view.lanes.live.pending ||
         view.lanes.final.inFlight || view.lanes.final.pending;
}

async function sendFrame(quality) {
  const lane = view.lanes[quality];
  lane.inFlight = true;
  const seq = ++view.seq;
  const version = view.version;
  const changeTime = view.lastChange;
  const q = `${cameraQuery()}&view=${view.mode}&quality=${quality}&exposure=${view.exposure}` +
            `&client=${view.client}&seq=${seq}`;
  let exact = true;
  try {
    const r = await fetch(`/api/frame?${q}`, {cache: "no-store"});
    const stale = seq < view.paintedSeq || (quality === "final" && version !== view.version);
    if (r.status === 200 && !stale) {
      const blob = await r.blob();
      exact = r.headers.get("X-Dofjax-Exact") === "1";
      const serverMs = parseFloat(r.headers.get("X-Dofjax-Render-Ms"));
      const url = URL.createObjectURL(blob);
      const img = $("frame");
      const old = img.src;
      img.src = url;
      await img.decode();
      await new Promise((res) => requestAnimationFrame(() => res()));
      const latency = performance.now() - changeTime;
      view.paintedSeq = seq;
      view.painted.push({seq, quality, latency, serverMs, exact, version});
      if (view.painted.length > 1000) view.painted.shift();
      if (old.startsWith("blob:")) URL.revokeObjectURL(old);
      view.shownExact = exact;
      setStatus(`${exact ? "exact" : "preview"} ${serverMs.toFixed(0)} ms render, ` +
                `${latency.toFixed(0)} ms to screen`);
    } else if (r.status !== 200 && r.status !== 204) {
      const body = await r.json().catch(() => ({error: r.statusText}));
      setStatus(body.error || `error ${r.status}`, true);
    }
  } catch (err) {
    setStatus(`the viewer server is not answering (${err.message})`, true);
  } finally {
    lane.inFlight = false;
  }
  if (lane.pending) {
    lane.pending = false;
    sendFrame(quality);
  } else if (quality === "live" && !exact && !view.lanes.live.inFlight) {
    view.refineTimer = setTimeout(() => requestFrame("final"), view.refineDelay);
  }
}

// ---------------------------------------------------------------- controls
function bindControls() {
  $("focus").addEventListener("input", (e) => { view.focus = sliderToFocus(+e.target.value); changed(); });
  $("aperture").addEventListener("input", (e) => { view.aperture = sliderToAperture(+e.target.value); changed(); });
  $("exposure").addEventListener("input", (e) => { view.exposure = +e.target.value; changed(); });
  for (const r of document.querySelectorAll("input[name=view]")) {
    r.addEventListener("change", (e) => setMode(e.target.value));
  }
  const bokeh = () => {
    const polygon = $("shape").value === "polygon";
    $("blades").disabled = $("rotation").disabled = !polygon;
    const blades = Math.round(+$("blades").value);
    view.blades = polygon ? Math.min(16, Math.max(3, blades || 6)) : 0;
    view.rotation = ((+$("rotation").value % 360) + 360) % 360;
    setStatus(polygon ? "new bokeh: compiling it once..." : "rendering...");
    changed();
  };
  $("shape").addEventListener("change", bokeh);
  $("blades").addEventListener("change", bokeh);
  $("rotation").addEventListener("change", bokeh);

  const img = $("frame");
  img.addEventListener("click", (e) => pickFocus(e));
  img.addEventListener("wheel", (e) => {
    e.preventDefault();
    nudgeFocus(e.deltaY > 0 ? 10 : -10);
  }, {passive: false});
  document.addEventListener("keydown", (e) => {
    if (e.target.tagName === "INPUT" && e.target.type !== "range" && e.target.type !== "radio") return;
    if (e.target.tagName === "SELECT") return;
    const keys = {"1": () => setMode("image"), "2": () => setMode("depth"), "3": () => setMode("coc"),
                  ",": () => nudgeFocus(-10), ".": () => nudgeFocus(10),
                  "[": () => nudgeAperture(-20), "]": () => nudgeAperture(20)};
    if (keys[e.key]) { keys[e.key](); e.preventDefault(); }
  });

  $("reference-run").addEventListener("click", runReference);
  $("target-file").addEventListener("change", uploadTarget);
  $("fit-run").addEventListener("click", runFit);
  $("fit-apply").addEventListener("click", applyFit);
}

function setMode(mode) {
  view.mode = mode;
  for (const r of document.querySelectorAll("input[name=view]")) r.checked = r.value === mode;
  changed();
}

function nudgeFocus(steps) {
  const v = Math.min(SLIDER, Math.max(0, focusToSlider(view.focus) + steps));
  $("focus").value = v;
  view.focus = sliderToFocus(v);
  changed();
}

function nudgeAperture(steps) {
  const v = Math.min(SLIDER, Math.max(0, apertureToSlider(view.aperture) + steps));
  $("aperture").value = v;
  view.aperture = sliderToAperture(v);
  changed();
}

function setCamera(focus, aperture) {
  const [lo, hi] = view.info.focus_range;
  view.focus = Math.min(hi, Math.max(lo, focus));
  view.aperture = Math.min(view.info.aperture_max, Math.max(0, aperture));
  $("focus").value = focusToSlider(view.focus);
  $("aperture").value = apertureToSlider(view.aperture);
}

async function pickFocus(e) {
  const img = $("frame");
  const box = img.getBoundingClientRect();
  const x = Math.floor((e.clientX - box.left) * img.naturalWidth / box.width);
  const y = Math.floor((e.clientY - box.top) * img.naturalHeight / box.height);
  const r = await fetch(`/api/depth?x=${x}&y=${y}`);
  const body = await r.json();
  if (!r.ok) { setStatus(body.error, true); return; }
  setCamera(body.focus, view.aperture);
  const readout = $("pick-readout");
  readout.dataset.depth = body.depth === null ? "inf" : String(body.depth);
  readout.textContent = body.background
    ? `pixel (${x}, ${y}): background (infinitely far); focus set to the far end, ${fmt(body.focus)}`
    : `pixel (${x}, ${y}): z-depth ${fmt(body.depth)}; focus set there`;
  changed();
}

// ---------------------------------------------------------------- reference
async function runReference() {
  const spp = $("spp").value;
  const r = await fetch(`/api/reference?${cameraQuery()}&spp=${spp}`, {method: "POST"});
  const body = await r.json();
  if (!r.ok) { $("reference-status").textContent = body.error; $("reference-status").classList.add("error"); return; }
  $("reference-status").classList.remove("error");
  $("reference-run").disabled = true;
  $("reference-progress").hidden = false;
  pollReference();
}

async function pollReference() {
  const s = await (await fetch("/api/reference")).json();
  const bar = $("reference-progress");
  if (s.total) { bar.max = s.total; bar.value = s.done; }
  $("reference-status").textContent = `${s.state}: ${s.done}/${s.total || "?"} spp, ${s.elapsed.toFixed(1)} s`;
  if (s.state === "running") { setTimeout(pollReference, 200); return; }
  $("reference-run").disabled = false;
  bar.hidden = true;
  if (s.state === "error") {
    $("reference-status").textContent = s.error;
    $("reference-status").classList.add("error");
    return;
  }
  const res = s.result;
  $("reference-status").innerHTML = "";
  $("reference-status").append(
    `RMSE `, Object.assign(document.createElement("span"), {id: "reference-rmse", textContent: res.rmse.toPrecision(4)}),
    ` at ${res.spp} spp: reference ${res.reference_seconds.toFixed(2)} s, post-process ` +
    `${(res.postprocess_seconds * 1e3).toFixed(1)} ms`);
  const stamp = Date.now();
  for (const which of ["reference", "postprocess", "difference"]) {
    $(`ref-${which}`).src = `/api/reference/${which}.png?t=${stamp}`;
  }
  $("ref-caption-reference").textContent = `reference, ${res.spp} spp, ${res.reference_seconds.toFixed(2)} s`;
  $("ref-caption-postprocess").textContent = `post-process, ${(res.postprocess_seconds * 1e3).toFixed(1)} ms`;
  $("ref-caption-difference").textContent =
    `post-process - reference (blue < 0 < red, +-${res.difference_scale.toPrecision(3)}), RMSE ${res.rmse.toPrecision(4)}`;
  $("compare").hidden = false;
}

// ---------------------------------------------------------------- target and fit
async function uploadTarget(e) {
  const file = e.target.files[0];
  if (!file) return;
  const status = $("fit-status");
  if (file.size > view.info.max_upload) {
    status.textContent = `${file.name}: ${file.size} bytes is over the upload limit of ${view.info.max_upload}`;
    status.classList.add("error");
    return;
  }
  status.textContent = `uploading ${file.name}...`;
  const r = await fetch(`/api/target?name=${encodeURIComponent(file.name)}`, {method: "POST", body: file});
  const body = await r.json();
  if (!r.ok) { status.textContent = body.error; status.classList.add("error"); return; }
  status.classList.remove("error");
  status.textContent = "";
  showTarget(body.target);
}

function showTarget(name) {
  $("target-name").textContent = name || "none";
  $("fit-run").disabled = !name;
}

async function runFit() {
  const status = $("fit-status");
  const r = await fetch(`/api/fit?${cameraQuery()}`, {method: "POST"});
  const body = await r.json();
  if (!r.ok) { status.textContent = body.error; status.classList.add("error"); return; }
  status.classList.remove("error");
  $("fit-run").disabled = true;
  $("fit-progress").hidden = false;
  $("fit-table").hidden = true;
  $("fit-apply").hidden = true;
  pollFit();
}

async function pollFit() {
  const s = await (await fetch("/api/fit")).json();
  const status = $("fit-status");
  status.textContent = `fitting (multi-start, then polish): ${s.elapsed.toFixed(1)} s`;
  if (s.state === "running") { setTimeout(pollFit, 250); return; }
  $("fit-run").disabled = false;
  $("fit-progress").hidden = true;
  if (s.state === "error") { status.textContent = s.error; status.classList.add("error"); return; }
  const f = s.result;
  status.textContent = `done in ${f.seconds.toFixed(1)} s, ${f.steps} steps`;
  $("fit-focus").textContent = `${fmt(f.focus, 5)} ± ${fmt(f.focus_se, 2)} (tiles ± ${fmt(f.focus_se_tiles, 2)})`;
  $("fit-focus").dataset.value = String(f.focus);
  $("fit-aperture").textContent = `${fmt(f.aperture, 5)} ± ${fmt(f.aperture_se, 2)} (tiles ± ${fmt(f.aperture_se_tiles, 2)})`;
  $("fit-aperture").dataset.value = String(f.aperture);
  $("fit-identifiable").textContent = `${f.identifiable ? "yes" : "NO"}${f.converged ? "" : " (did not converge)"}`;
  $("fit-identifiable").classList.toggle("bad", !f.identifiable || !f.converged);
  $("fit-rmse").textContent = f.rmse.toPrecision(4);
  $("fit-message").textContent = f.message;
  $("fit-message").classList.toggle("bad", f.message !== "ok");
  $("fit-table").hidden = false;
  $("fit-apply").hidden = false;
  view.fitted = f;
  const stamp = Date.now();
  $("fit-target").src = `/api/fit/target.png?t=${stamp}`;
  $("fit-residual").src = `/api/fit/residual.png?t=${stamp}`;
  $("fit-residual-caption").textContent =
    `target - model at the fit (blue < 0 < red, +-${f.residual_scale.toPrecision(3)}), RMSE ${f.rmse.toPrecision(4)}`;
  $("fit-images").hidden = false;
}

function applyFit() {
  if (!view.fitted) return;
  setCamera(view.fitted.focus, view.fitted.aperture);
  changed();
}

// ---------------------------------------------------------------- start
async function start() {
  try {
    view.info = await (await fetch("/api/info")).json();
  } catch (err) {
    setStatus(`cannot reach the viewer server (${err.message})`, true);
    return;
  }
  const i = view.info;
  $("source").textContent = `${i.name}, ${i.width}x${i.height}`;
  if (!i.has_scene) {
    $("reference-run").disabled = true;
    $("reference-status").textContent = "needs a scene (this input is an RGB-D image)";
  }
  showTarget(i.target);
  setCamera(i.focus, i.aperture);
  bindControls();
  document.body.dataset.ready = "1";
  changed();
}

start();
