// torchmetal viewer page: one code path for both modes; only the backend differs.
//   served: POST render → the Python server runs the material's ONNX file with onnxruntime
//   static: onnxruntime-web (wasm, single-threaded by default; WebGPU with ?ep=webgpu) in the page
// Both return the renderer's output (3, H, W) float32 linear radiance; the page does exposure and
// sRGB encoding (display.js). Test hooks: window.tmviewer (ready, idle(), frames, lastInputs, …).
import { readHash, writeHash, inputsFromState, stateFromShot, clampState, direction } from "./state.js";
import { encodeInto, decodeRGBA, linearToSrgb, srgbToLinear } from "./display.js";

const $ = (id) => document.getElementById(id);
const api = (window.tmviewer = { frames: 0, lastInputs: null, lastFlakes: null, error: null, state: null, config: null });

// ------------------------------------------------------------------------------ backends

class ServedBackend {
  constructor(cfg) { this.cfg = cfg; this.label = "served · onnxruntime (Python)"; }
  async render(inputs, flakes) {
    const r = await fetch("render", {
      method: "POST", headers: { "content-type": "application/json" },
      body: JSON.stringify({ ...inputs, flakes }),
    });
    if (!r.ok) throw new Error((await r.text()).split("\n")[0]);
    return new Float32Array(await r.arrayBuffer());
  }
}

class StaticBackend {
  static async create(cfg, ep) {
    let useGpu = false, note = "";
    if (ep === "webgpu") {
      const adapter = cfg.ort.webgpu && navigator.gpu ? await navigator.gpu.requestAdapter().catch(() => null) : null;
      useGpu = !!adapter;
      if (!useGpu) note = cfg.ort.webgpu ? " — no WebGPU adapter, using wasm" : " — this site has no WebGPU build (export --webgpu), using wasm";
    }
    const ort = await import(new URL(useGpu ? cfg.ort.webgpu : cfg.ort.wasm, location.href).href);
    ort.env.wasm.wasmPaths = new URL("ort/", location.href).href; // ORT's .wasm/.mjs from this site only
    ort.env.wasm.numThreads = cfg.threads || 1;
    ort.env.wasm.proxy = false;
    const opts = { executionProviders: useGpu ? ["webgpu", "wasm"] : ["wasm"], graphOptimizationLevel: "all" };
    const b = new StaticBackend();
    b.ort = ort;
    b.sessions = {};
    for (const [key, file] of Object.entries(cfg.graphs)) {
      b.sessions[key] = await ort.InferenceSession.create(new URL(file, location.href).href, opts);
    }
    b.label = `static · onnxruntime-web ${ort.env.versions?.web ?? ""} (${useGpu ? "WebGPU" : "wasm"}, ${ort.env.wasm.numThreads} thread${ort.env.wasm.numThreads > 1 ? "s" : ""})${note}`;
    return b;
  }
  async render(inputs, flakes) {
    const s = flakes && this.sessions.flakes ? this.sessions.flakes : this.sessions.plain;
    const T = this.ort.Tensor;
    const out = await s.run({
      light: new T("float32", Float32Array.from(inputs.light), [1, 4]),
      light_intensity: new T("float32", Float32Array.from(inputs.light_intensity), [1, 3]),
      camera: new T("float32", Float32Array.from(inputs.camera), [1, 4]),
    });
    return out.image.data;
  }
}

// ------------------------------------------------------------------------------ page state

let cfg, backend, extent, W, H;
let state = readHash(location.hash);
let linear = null; // last render (3, H, W)
let photo = null; // linear photo of the selected shot (3, H, W)
let busy = false, pending = false, waiters = [];
let photoTask = Promise.resolve();
let preview = null, previewPaused = false; // the 3D preview (preview.js), when config.json offers one
const times = [];

function setStatus(text) { $("status").textContent = text || ""; }

// The URL follows the state at most every 200 ms (browsers throttle history updates during fast
// drags) and at once whenever the page goes idle.
let hashTimer = null;
function flushHash() {
  clearTimeout(hashTimer);
  hashTimer = null;
  const h = writeHash(state);
  if (location.hash !== h) history.replaceState(null, "", location.pathname + location.search + h);
}

function setState(patch, { render = true } = {}) {
  state = clampState({ ...state, ...patch });
  api.state = state;
  if (hashTimer === null) hashTimer = setTimeout(flushHash, 200);
  syncControls();
  if (render) requestRender(); else redraw();
}

async function requestRender() {
  if (busy) { pending = true; return; }
  busy = true;
  try {
    do {
      pending = false;
      const inputs = inputsFromState(state, extent);
      const flakes = !!(state.fl && cfg.graphs.flakes);
      const t0 = performance.now();
      const out = await backend.render(inputs, flakes);
      api.lastRenderMs = performance.now() - t0;
      if (out.length !== 3 * W * H) throw new Error(`render: expected ${3 * W * H} values, found ${out.length}`);
      linear = out;
      api.lastInputs = inputs;
      api.lastFlakes = flakes;
      redraw();
      times.push(performance.now() - t0);
      if (times.length > 20) times.shift();
      api.frames++;
      api.error = null;
      showFps();
      setStatus("");
    } while (pending);
  } catch (e) {
    api.error = String(e.message || e);
    setStatus(api.error);
  } finally {
    busy = false;
    const w = waiters; waiters = [];
    w.forEach((f) => f());
  }
}

/** Resolves once no render is running or queued and the selected shot's photo is drawn. */
api.idle = async () => {
  await photoTask;
  if (busy) await new Promise((r) => waiters.push(r));
  flushHash();
};
api.setState = async (patch) => { setState(patch); await api.idle(); };
/** Render n frames back to back (light azimuth sweeping); returns {fps, ms_median, ms_mean, frames}. */
api.bench = async (n = 30) => {
  await api.idle();
  const ms = [], render = [];
  const base = state.laz;
  previewPaused = true; // the frame rate is the texture view's: the 3D preview waits
  for (let k = 0; k < n; k++) {
    const t0 = performance.now();
    setState({ laz: base + (360 * (k + 1)) / n });
    await api.idle();
    ms.push(performance.now() - t0);
    render.push(api.lastRenderMs);
  }
  previewPaused = false;
  updatePreview();
  const median = (a) => [...a].sort((x, y) => x - y)[a.length >> 1];
  const mean = ms.reduce((a, b) => a + b, 0) / n;
  // ms_render: the backend alone (ORT run, or the HTTP round trip); the rest is sRGB encode + draw
  return { frames: n, ms_median: median(ms), ms_mean: mean, ms_render_median: median(render), fps: 1000 / mean };
};

function showFps() {
  const mean = times.reduce((a, b) => a + b, 0) / times.length;
  $("fps").textContent = `${(1000 / mean).toFixed(1)} fps (${mean.toFixed(1)} ms/frame)`;
}

// ------------------------------------------------------------------------------ drawing

const images = {}; // one reused ImageData per canvas
function imageFor(ctx, id) {
  if (!images[id] || images[id].width !== W || images[id].height !== H) images[id] = ctx.createImageData(W, H);
  return images[id];
}

function redraw() {
  const view = $("view");
  const ctx = view.getContext("2d");
  const img = imageFor(ctx, "view");
  const split = state.ab === "split" && photo;
  if (linear) encodeInto(linear, W, H, state.ex, img.data, split ? Math.round(state.sp * W) : 0, W);
  if (split) encodeInto(photo, W, H, state.ex, img.data, 0, Math.round(state.sp * W));
  ctx.putImageData(img, 0, 0);
  if (split) {
    ctx.fillStyle = "rgba(255,255,255,0.8)";
    ctx.fillRect(Math.round(state.sp * W), 0, Math.max(1, Math.round(W / 256)), H);
  }
  const side = state.ab === "side" && photo;
  $("photo-box").hidden = !side;
  if (side) {
    const pimg = imageFor($("photo").getContext("2d"), "photo");
    encodeInto(photo, W, H, state.ex, pimg.data);
    $("photo").getContext("2d").putImageData(pimg, 0, 0);
  }
  const shot = state.shot >= 0 ? cfg.shots[state.shot] : null;
  $("photo-caption").textContent = shot ? `photo: shot ${shot.name}` : "photo";
  $("view-caption").textContent = split ? `photo (left) | render (right) — shot ${shot.name}` : "render";
  drawHemisphere();
  updatePreview();
  const i = api.lastInputs || inputsFromState(state, extent);
  const f = (v) => v.map((x) => Number(x.toPrecision(4))).join(", ");
  $("inputs").textContent = `light [${f(i.light)}]\nintensity [${f(i.light_intensity)}]\ncamera [${f(i.camera)}]`;
}

function updatePreview() {
  if (preview && !previewPaused) preview.update(inputsFromState(state, extent), state.ex);
}

/** The 3D preview: three.js and the glTF export from this site (see preview.js); optional. */
async function startPreview() {
  if (!cfg.preview) {
    api.preview = { error: cfg.preview_note || "no 3D preview" };
    return;
  }
  $("preview-box").hidden = false;
  try {
    const { createPreview } = await import("./preview.js");
    preview = api.preview = await createPreview($("preview"), cfg);
    updatePreview();
  } catch (e) {
    $("preview-box").hidden = true;
    api.preview = { error: `3D preview: ${e.message || e}` };
    setStatus(api.preview.error);
  }
}

function drawHemisphere() {
  const c = $("hemi"), ctx = c.getContext("2d");
  const R = c.width / 2 - 6, cx = c.width / 2, cy = c.height / 2;
  ctx.clearRect(0, 0, c.width, c.height);
  ctx.fillStyle = "#222"; ctx.beginPath(); ctx.arc(cx, cy, R, 0, 2 * Math.PI); ctx.fill();
  ctx.strokeStyle = "#444";
  for (const el of [30, 60]) { ctx.beginPath(); ctx.arc(cx, cy, R * Math.cos((el * Math.PI) / 180), 0, 2 * Math.PI); ctx.stroke(); }
  ctx.beginPath(); ctx.moveTo(cx - R, cy); ctx.lineTo(cx + R, cy); ctx.moveTo(cx, cy - R); ctx.lineTo(cx, cy + R); ctx.stroke();
  ctx.fillStyle = "#888"; ctx.font = "10px sans-serif"; ctx.fillText("+x", cx + R - 14, cy - 3); ctx.fillText("+y", cx + 3, cy - R + 10);
  const dot = (az, el, color, r) => {
    const d = direction(az, el);
    ctx.fillStyle = color; ctx.beginPath(); ctx.arc(cx + d[0] * R, cy - d[1] * R, r, 0, 2 * Math.PI); ctx.fill();
  };
  dot(state.caz, state.cel, "#6af", 4);
  dot(state.laz, state.lel, "#f2c14e", 7);
}

// ------------------------------------------------------------------------------ controls

const log10 = Math.log10, log2 = Math.log2;
const hex = (lc) => "#" + lc.map((v) => Math.round(255 * linearToSrgb(Math.min(1, v))).toString(16).padStart(2, "0")).join("");

function syncControls() {
  $("light-type").value = state.lt;
  $("light-dist").value = log10(state.ld); $("light-dist-out").value = state.ld.toPrecision(3);
  $("light-dist").disabled = state.lt !== "point";
  $("intensity").value = state.li > 0 ? log2(state.li) : -5; $("intensity-out").value = state.li.toPrecision(3);
  $("light-color").value = hex(state.lc);
  $("exposure").value = state.ex > 0 ? log2(state.ex) : -8; $("exposure-out").value = state.ex.toPrecision(3);
  $("flakes").checked = !!state.fl && !!cfg.graphs.flakes;
  $("camera-type").value = state.ct;
  $("cam-az").value = state.caz; $("cam-az-out").value = state.caz.toFixed(1);
  $("cam-el").value = state.cel; $("cam-el-out").value = state.cel.toFixed(1);
  $("cam-dist").value = log10(state.cd); $("cam-dist-out").value = state.cd.toPrecision(3);
  $("cam-dist").disabled = state.ct !== "point";
  $("shot").value = String(state.shot);
  $("compare").value = state.ab;
  $("split").value = state.sp;
}

function hemiToState(ev) {
  const c = $("hemi"), r = c.getBoundingClientRect();
  const R = (c.width / 2 - 6) * (r.width / c.width);
  const x = (ev.clientX - r.left - r.width / 2) / R, y = -(ev.clientY - r.top - r.height / 2) / R;
  const rho = Math.min(1, Math.hypot(x, y));
  return { laz: (Math.atan2(y, x) * 180) / Math.PI, lel: (Math.acos(rho) * 180) / Math.PI };
}

function bindControls() {
  const hemi = $("hemi");
  hemi.addEventListener("pointerdown", (e) => { hemi.setPointerCapture(e.pointerId); setState(hemiToState(e)); });
  hemi.addEventListener("pointermove", (e) => { if (hemi.hasPointerCapture(e.pointerId)) setState(hemiToState(e)); });
  hemi.addEventListener("keydown", (e) => {
    const step = { ArrowLeft: [5, 0], ArrowRight: [-5, 0], ArrowUp: [0, 5], ArrowDown: [0, -5] }[e.key];
    if (step) { e.preventDefault(); setState({ laz: state.laz + step[0], lel: state.lel + step[1] }); }
  });
  const view = $("view");
  let drag = null;
  view.addEventListener("pointerdown", (e) => { view.setPointerCapture(e.pointerId); drag = { x: e.clientX, y: e.clientY, caz: state.caz, cel: state.cel }; moveView(e); });
  view.addEventListener("pointermove", (e) => { if (drag && view.hasPointerCapture(e.pointerId)) moveView(e); });
  view.addEventListener("pointerup", () => { drag = null; });
  function moveView(e) {
    if (state.ab === "split" && photo) {
      const r = view.getBoundingClientRect();
      setState({ sp: (e.clientX - r.left) / r.width }, { render: false });
    } else {
      setState({ caz: drag.caz - (e.clientX - drag.x) * 0.5, cel: drag.cel + (e.clientY - drag.y) * 0.5 });
    }
  }
  const on = (id, ev, f) => $(id).addEventListener(ev, (e) => f(e.target));
  on("light-type", "change", (t) => setState({ lt: t.value }));
  on("light-dist", "input", (t) => setState({ ld: 10 ** Number(t.value) }));
  on("intensity", "input", (t) => setState({ li: 2 ** Number(t.value) }));
  on("light-color", "input", (t) => {
    const v = [1, 3, 5].map((i) => srgbToLinear(parseInt(t.value.slice(i, i + 2), 16) / 255));
    const top = Math.max(...v);
    setState({ lc: top > 0 ? v.map((x) => x / top) : [1, 1, 1] });
  });
  on("exposure", "input", (t) => setState({ ex: 2 ** Number(t.value) }, { render: false }));
  on("flakes", "change", (t) => setState({ fl: t.checked ? 1 : 0 }));
  on("camera-type", "change", (t) => setState({ ct: t.value }));
  on("cam-az", "input", (t) => setState({ caz: Number(t.value) }));
  on("cam-el", "input", (t) => setState({ cel: Number(t.value) }));
  on("cam-dist", "input", (t) => setState({ cd: 10 ** Number(t.value) }));
  on("shot", "change", (t) => selectShot(Number(t.value)));
  on("compare", "change", (t) => setState({ ab: t.value }, { render: false }));
  on("split", "input", (t) => setState({ sp: Number(t.value) }, { render: false }));
  on("snapshot", "click", snapshot);
  on("ep", "change", (t) => {
    const q = new URLSearchParams(location.search); q.set("ep", t.value);
    location.search = q.toString();
  });
  window.addEventListener("hashchange", () => {
    const next = readHash(location.hash);
    if (writeHash(next) !== writeHash(state)) {
      const shotChanged = next.shot !== state.shot;
      state = next; api.state = state; syncControls(); requestRender();
      if (shotChanged) loadPhoto(state.shot);
    }
  });
}

function loadPhoto(k) {
  photoTask = decodePhoto(k).catch((e) => {
    api.error = `photo ${k}: ${e.message || e}`;
    setStatus(api.error);
  });
  return photoTask;
}

async function decodePhoto(k) {
  photo = null;
  if (k < 0 || k >= cfg.shots.length) { redraw(); return; }
  const img = new Image();
  img.src = cfg.shots[k].photo;
  await img.decode();
  const c = document.createElement("canvas");
  c.width = W; c.height = H;
  const ctx = c.getContext("2d");
  ctx.imageSmoothingEnabled = img.naturalWidth !== W || img.naturalHeight !== H;
  ctx.drawImage(img, 0, 0, W, H);
  photo = decodeRGBA(ctx.getImageData(0, 0, W, H).data, W, H);
  redraw();
}

async function selectShot(k) {
  if (k >= 0 && k < cfg.shots.length) {
    setState({ ...stateFromShot(state, cfg.shots[k], extent), shot: k, ab: state.ab === "render" ? "split" : state.ab });
  } else {
    setState({ shot: -1 }, { render: false });
  }
  await loadPhoto(state.shot);
}

function snapshot() {
  const name = state.shot >= 0 ? `shot-${cfg.shots[state.shot].name}` : `light-${state.laz.toFixed(0)}-${state.lel.toFixed(0)}`;
  $("view").toBlob((blob) => {
    const a = document.createElement("a");
    a.href = URL.createObjectURL(blob);
    a.download = `torchmetal-${name}.png`;
    document.body.appendChild(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(a.href), 10000);
  }, "image/png");
}

// ------------------------------------------------------------------------------ start

async function start() {
  if (location.protocol === "file:") {
    throw new Error("open this page over http: run `python3 -m http.server` in its folder (browsers block wasm and fetch from file://)");
  }
  const r = await fetch("config.json");
  if (!r.ok) throw new Error(`config.json: expected the viewer's config, found HTTP ${r.status}`);
  cfg = api.config = await r.json();
  if (cfg.format !== "torchmetal-viewer") throw new Error(`config.json: expected format torchmetal-viewer, found ${cfg.format}`);
  W = cfg.width; H = cfg.height;
  extent = Math.max(cfg.surface[0], cfg.surface[1]);
  for (const id of ["view", "photo"]) { $(id).width = W; $(id).height = H; }
  document.title = $("title").textContent = cfg.title;
  const ep = new URLSearchParams(location.search).get("ep") || "wasm";
  backend = cfg.mode === "static" ? await StaticBackend.create(cfg, ep) : new ServedBackend(cfg);
  $("mode").textContent = `${backend.label} · ${W}×${H}`;
  if (cfg.mode === "static" && cfg.ort.webgpu) { $("ep-box").hidden = false; $("ep").value = ep; }
  if (!cfg.graphs.flakes) { $("flakes").disabled = true; $("flakes").parentElement.title = "this material has no flakes"; }
  const sel = $("shot");
  cfg.shots.forEach((s, k) => sel.add(new Option(s.name, String(k))));
  if (state.shot >= cfg.shots.length) state = { ...state, shot: -1 };
  api.state = state;
  bindControls();
  syncControls();
  flushHash();
  if (state.shot >= 0) await loadPhoto(state.shot);
  await requestRender();
  if (api.error) throw new Error(api.error);
  api.previewReady = startPreview();
}

api.ready = start().catch((e) => {
  api.error = String(e.message || e);
  setStatus(api.error);
  throw e;
});
