"""Engine parity measured by a real client: the exported GLB rendered by three.js in Chromium.

:class:`ThreeClient` serves a tiny page (three.js from ``node_modules``, no CDN) to headless
Chromium (Playwright, Debian's ``/usr/bin/chromium`` with the flags of
:mod:`torchmetal.viewer.browser`), loads a GLB with three.js's own ``GLTFLoader`` (so the material
is the ``MeshPhysicalMaterial`` the loader builds from the glTF: base colour, roughness,
``KHR_materials_specular``/``ior``, normal map, clear coat) and renders it under torchmetal's light
and camera into a float render target, read back as linear radiance (no tone mapping, no sRGB
encoding: render targets get neither).

Light units. torchmetal's point light (x, y, z, 1) with radiant intensity I gives irradiance
E = I/d² at distance d and a Lambertian radiance d·E·(n·l) for texture d (docs/design.md §2.2). three.js
(r155+, physically based units always) gives a ``PointLight`` of ``color·intensity`` = J (candela,
``decay`` 2, ``distance`` 0 = no cut-off) the incident radiance term J/d²·(n·l) and a Lambertian
BRDF albedo/π, so its radiance is albedo/π·J/d²·(n·l). The export's convention is that the base
colour is d (engine irradiance = π × torchmetal's, :mod:`torchmetal.formats.engine`), hence
J = π·I. The same holds for a directional light (w = 0): ``DirectionalLight`` intensity = π·E.
three.js clamps d² below 0.01 (scene units²): shots here keep every point of the sample farther
than 0.1 from a point light.

Where the pixels are. torchmetal renders in texture space: pixel (i, j) is the texel at
x = ((j + ½)/W − ½)·w, y = (½ − (i + ½)/H)·h on the plane z = 0, seen from the camera position
(w = 1) or direction (w = 0). Two placements, both shading with three.js's unmodified fragment
shader:

- ``"camera"``: three.js's own projection. Only for a camera straight above the centre
  ((0, 0, z, 1) perspective, or (0, 0, 1, 0) orthographic): the plane is then parallel to the
  image plane, so with the field of view that frames the sample exactly, pixel centres land on
  texel centres (an affine map; nothing to resample).
- ``"texture"`` (any camera): the vertex shader's clip position is replaced by the texel position
  (``gl_Position = (2u − 1, 1 − 2v, 0, 1)``), after three.js has computed the view-space position
  it shades with, so every pixel is its texel seen from the real camera. :func:`parity` checks on
  an overhead shot that both placements give the same image.

What three.js does differently from the glTF BRDF as torchmetal evaluates it (measured by
``psnr_client``): its Schlick Fresnel is the spherical-Gaussian approximation
2^((−5.55473·v·h − 6.98316)·v·h) of (1 − v·h)^5 (+9 % at v·h = 0.5; its effect on a grazing shot:
docs/measurements.md); it adds multiple-scattering energy compensation (1 + F0·(1/E_ss − 1), small for
dielectric F0); it mixes the diffuse with (1 − F) per channel (torchmetal: 1 − max_c F); its clear
coat's Fresnel uses n·v, not v·h; roughness is clamped to ≥ 0.045; textures are 8-bit PNGs (sRGB
base colour, linear roughness/normal/specular maps).

:func:`parity` reports PSNR (torchmetal.metrics.psnr: linear, clipped to [0, 1], peak 1) of
three.js against torchmetal's renderer, split into what the glTF model loses (torchmetal's own
evaluation of the exported BRDF, :func:`~torchmetal.formats.engine.engine_render`, against the
renderer) and what the client does differently (three.js against that evaluation).
"""

from __future__ import annotations

import base64
import json
import math
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchmetal.flakes.model import FlakeModel
from torchmetal.formats.engine import engine_material, engine_render, reference_render
from torchmetal.formats.gltf import write_engine
from torchmetal.io.images import atomic_write_bytes, encode_image, linear_to_srgb
from torchmetal.material import Material
from torchmetal.metrics import psnr
from torchmetal.normals import estimate_normals
from torchmetal.synth import synth_capture
from torchmetal.viewer.browser import CHROMIUM, launch_chromium, serve_folder
from torchmetal.viewer.three import IMPORT_MAP, copy_three

PAGE_HTML = """<!doctype html>
<html><head><meta charset="utf-8"><title>torchmetal parity</title><link rel="icon" href="data:,">
<script type="importmap">{importmap}</script>
<script type="module" src="parity.js"></script></head><body></body></html>
"""

# The page's API: window.parity.load(url) -> true; window.parity.render(spec) -> base64 float32
# RGBA rows bottom-up (WebGL order). spec: {width, height, size: [w, h], light: [4],
# intensity: [3], camera: [4], placement: "texture" | "camera"}.
PAGE_JS = r"""
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";

const renderer = new THREE.WebGLRenderer({ antialias: false });
renderer.outputColorSpace = THREE.LinearSRGBColorSpace;  // (render targets are linear anyway)
renderer.toneMapping = THREE.NoToneMapping;
let sample = null;  // the loaded glTF scene
const TEXTURE_SPACE = "#include <project_vertex>\n\tgl_Position = vec4( 2.0 * uv.x - 1.0, 1.0 - 2.0 * uv.y, 0.0, 1.0 );";

function placeInTextureSpace(root, on) {
  root.traverse((o) => {
    if (!o.isMesh) return;
    const m = o.material;
    m.onBeforeCompile = on ? (shader) => { shader.vertexShader = shader.vertexShader.replace("#include <project_vertex>", TEXTURE_SPACE); } : () => {};
    m.customProgramCacheKey = () => (on ? "torchmetal-texture-space" : "");
    m.needsUpdate = true;
  });
}

function makeLight(spec) {
  const [x, y, z, w] = spec.light;
  const top = Math.max(...spec.intensity, 1e-30);
  const color = new THREE.Color().setRGB(...spec.intensity.map((v) => v / top), THREE.LinearSRGBColorSpace);
  // torchmetal intensity I -> three.js pi*I (see torchmetal/formats/parity.py: base colour = d)
  const light = w > 0.5 ? new THREE.PointLight(color, Math.PI * top, 0, 2) : new THREE.DirectionalLight(color, Math.PI * top);
  light.position.set(x, y, z);
  return light;
}

function makeCamera(spec) {
  const [x, y, z, w] = spec.camera;
  const [sw, sh] = spec.size;
  const far = 100 * Math.max(sw, sh, Math.hypot(x, y, z));
  let cam;
  if (w > 0.5) {
    const fov = (2 * Math.atan(sh / 2 / z) * 180) / Math.PI;  // frames the sample exactly from (0, 0, z)
    cam = new THREE.PerspectiveCamera(fov, sw / sh, 1e-4 * Math.max(sw, sh), far);
    cam.position.set(x, y, z);
  } else {
    const d = 10 * Math.max(sw, sh);
    cam = new THREE.OrthographicCamera(-sw / 2, sw / 2, sh / 2, -sh / 2, 1e-3 * d, 3 * d);
    cam.position.set(x * d, y * d, z * d);
  }
  cam.up.set(0, 1, 0);
  if (Math.hypot(x, y) > 1e-9 * Math.hypot(x, y, z)) cam.up.set(0, 0, 1);
  cam.lookAt(0, 0, 0);
  cam.updateMatrixWorld(true);
  return cam;
}

function b64(bytes) {
  let s = "";
  for (let i = 0; i < bytes.length; i += 8192) s += String.fromCharCode(...bytes.subarray(i, i + 8192));
  return btoa(s);
}

window.parity = {
  revision: THREE.REVISION,
  async load(url) {
    const gltf = await new GLTFLoader().loadAsync(url);
    sample = gltf.scene;
    return true;
  },
  material() {
    let m = null;
    sample.traverse((o) => { if (o.isMesh) m = o.material; });
    return { type: m.type, roughness: m.roughness, ior: m.ior, specularIntensity: m.specularIntensity,
             specularColor: m.specularColor.toArray(), clearcoat: m.clearcoat, hasNormalMap: !!m.normalMap };
  },
  render(spec) {
    placeInTextureSpace(sample, spec.placement === "texture");
    const scene = new THREE.Scene();
    scene.add(sample);
    const light = makeLight(spec);
    scene.add(light);
    if (light.isDirectionalLight) scene.add(light.target);  // target at the origin
    const cam = makeCamera(spec);
    const rt = new THREE.WebGLRenderTarget(spec.width, spec.height, {
      type: THREE.FloatType, format: THREE.RGBAFormat, minFilter: THREE.NearestFilter, magFilter: THREE.NearestFilter,
      depthBuffer: true, samples: 0 });
    renderer.setRenderTarget(rt);
    renderer.setClearColor(0x000000, 0);
    renderer.clear();
    renderer.render(scene, cam);
    const out = new Float32Array(spec.width * spec.height * 4);
    renderer.readRenderTargetPixels(rt, 0, 0, spec.width, spec.height, out);
    renderer.setRenderTarget(null);
    rt.dispose();
    return b64(new Uint8Array(out.buffer));
  },
};
window.parityReady = true;
"""


class ThreeClient:
    """three.js in headless Chromium, rendering GLB files under torchmetal's lights and cameras.

    ```python
    with ThreeClient() as client:
        client.load("material.glb")
        image = client.render(light, intensity, camera, height=H, width=W, size=(w, h))  # (3, H, W)
    ```
    Raises RuntimeError (one line) when three.js (``npm ci``) or Chromium is missing. ``browser``: a
    running Playwright browser to open the page in (kept open); default: a Chromium of its own.
    """

    def __init__(self, three_dir=None, browser=None) -> None:
        self.three_dir = three_dir
        self._own = browser is None
        self._given = browser
        self._root: Path | None = None
        self._pw = self._browser = self._page = self._httpd = None
        self.errors: list[str] = []
        self._n = 0

    def __enter__(self) -> "ThreeClient":
        from playwright.sync_api import sync_playwright

        if not Path(CHROMIUM).exists():
            raise RuntimeError(f"three.js parity: expected Chromium at {CHROMIUM}, found none (apt-get install chromium)")
        self._root = Path(tempfile.mkdtemp(prefix="torchmetal-parity-"))
        try:
            self.version = copy_three(self._root, self.three_dir)
            if self.version is None:
                raise RuntimeError("three.js parity: expected three.js 0.187 in node_modules, found none (run `npm ci`)")
            (self._root / "index.html").write_text(PAGE_HTML.replace("{importmap}", json.dumps(IMPORT_MAP)))
            (self._root / "parity.js").write_text(PAGE_JS)
            self._httpd, self.url = serve_folder(self._root)
            if self._own:
                self._pw = sync_playwright().start()
                self._browser = launch_chromium(self._pw)
                self._page = self._browser.new_page()
            else:
                self._page = self._given.new_page()
            self._page.on("pageerror", lambda e: self.errors.append(str(e)))
            self._page.on("console", lambda m: self.errors.append(m.text) if m.type == "error" else None)
            self._page.goto(self.url)
            self._page.wait_for_function("window.parityReady === true || false", timeout=60_000)
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        for f in (lambda: self._page.close(), lambda: self._browser.close(), lambda: self._pw.stop(),
                  lambda: (self._httpd.shutdown(), self._httpd.server_close())):
            try:
                f()
            except Exception:
                pass
        self._browser = self._pw = self._httpd = self._page = None
        if self._root is not None:
            shutil.rmtree(self._root, ignore_errors=True)
            self._root = None

    def load(self, glb: str | Path | bytes) -> dict:
        """Load a GLB (path or bytes) with GLTFLoader; returns a summary of the built material."""
        self._n += 1
        name = f"sample-{self._n}.glb"
        data = glb if isinstance(glb, (bytes, bytearray)) else Path(glb).read_bytes()
        (self._root / name).write_bytes(data)
        self._page.evaluate("url => window.parity.load(url)", name)
        return self._page.evaluate("window.parity.material()")

    def render(self, light, intensity, camera, *, height: int, width: int, size: tuple[float, float],
               placement: str = "texture") -> np.ndarray:
        """three.js's linear radiance (3, H, W) float32 of the loaded GLB for one shot."""
        if placement == "camera":
            c = [float(v) for v in camera]
            if abs(c[0]) > 1e-9 or abs(c[1]) > 1e-9 or c[2] <= 0:
                raise ValueError(f"placement 'camera': expected a camera straight above the sample, found {c}")
        spec = {"width": int(width), "height": int(height), "size": [float(size[0]), float(size[1])],
                "light": [float(v) for v in light], "intensity": [float(v) for v in intensity],
                "camera": [float(v) for v in camera], "placement": placement}
        data = base64.b64decode(self._page.evaluate("spec => window.parity.render(spec)", spec))
        rgba = np.frombuffer(data, np.float32).reshape(height, width, 4)[::-1]  # WebGL rows are bottom-up
        if self.errors:
            raise RuntimeError(f"three.js parity: the page reported {self.errors[0]}")
        return np.ascontiguousarray(rgba[..., :3].transpose(2, 0, 1))


def default_shots(size: tuple[float, float]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[str]]:
    """Three shots with the highlight on the sample: light, intensity (irradiance 1 at the centre), camera, names.

    - ``overhead``: point light 35° off the normal, point camera straight above (the shot both
      placements can render);
    - ``mirror``: point light 30° off, point camera at its mirror direction (highlight at the centre);
    - ``grazing``: directional light 60° off the normal, orthographic camera at its mirror direction.
    """
    e = max(size)
    def d(theta, phi):
        t, p = math.radians(theta), math.radians(phi)
        return [math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)]
    rl, rc = 1.8 * e, 2.2 * e
    lights = [[*(rl * x for x in d(35, 30)), 1.0], [*(rl * x for x in d(30, 150)), 1.0], [*d(60, -60), 0.0]]
    cams = [[0.0, 0.0, rc, 1.0], [*(rc * x for x in d(30, -30)), 1.0], [*d(60, 120), 0.0]]
    inten = [[rl * rl] * 3, [rl * rl * 1.0, rl * rl * 0.9, rl * rl * 0.8], [1.0, 1.0, 1.0]]
    return (torch.tensor(lights), torch.tensor(inten), torch.tensor(cams), ["overhead", "mirror", "grazing"])


@dataclass
class ParityResult:
    """PSNRs (dB) per shot and overall; images (B, 3, H, W) numpy: torchmetal, engine model, three.js."""

    names: list[str]
    psnr: list[float]  # three.js vs torchmetal
    psnr_model: list[float]  # torchmetal's evaluation of the glTF BRDF vs torchmetal (what the format loses)
    psnr_client: list[float]  # three.js vs that evaluation (what the client does differently)
    psnr_placement: float | None  # texture-space vs three.js's own projection on the overhead shot
    reference: np.ndarray
    model: np.ndarray
    three: np.ndarray
    material: dict
    extras: dict

    @property
    def psnr_all(self) -> float:
        return psnr(self.three, self.reference)

    def row(self) -> dict:
        return {"psnr": round(self.psnr_all, 2), "psnr_model": round(psnr(self.model, self.reference), 2),
                "psnr_client": round(psnr(self.three, self.model), 2),
                "psnr_placement": None if self.psnr_placement is None else round(self.psnr_placement, 2),
                "per_shot": {n: round(p, 2) for n, p in zip(self.names, self.psnr)}}


def parity(material: Material, client: ThreeClient, *, shots=None, views=None, flakes: str = "auto") -> ParityResult:
    """Export ``material`` as GLB, render it with three.js (``client``) and compare with torchmetal.

    Args:
        shots: (light (B, 4), intensity (B, 3), camera (B, 4), names); default :func:`default_shots`.
        views, flakes: passed to :func:`~torchmetal.formats.engine.engine_material`.
    """
    light, inten, cam, names = shots if shots is not None else default_shots(material.size)
    em = engine_material(material, views=views, flakes=flakes)
    with tempfile.TemporaryDirectory(prefix="torchmetal-parity-") as tmp:
        glb = write_engine(em, Path(tmp) / "sample.glb")
        summary = client.load(glb)
    ref = reference_render(material, light, inten, cam).numpy()
    with torch.inference_mode():
        model = engine_render(em, light, inten, cam)
    if model.shape[-1] != ref.shape[-1]:  # flakes baked at a finer texel density
        model = torch.nn.functional.avg_pool2d(model, model.shape[-1] // ref.shape[-1])
    model = model.numpy()
    h, w = em.height, em.width
    three = np.stack([client.render(light[k].tolist(), inten[k].tolist(), cam[k].tolist(), height=h, width=w,
                                    size=material.size) for k in range(light.shape[0])])
    if three.shape[-1] != ref.shape[-1]:
        f = three.shape[-1] // ref.shape[-1]
        three = three.reshape(*three.shape[:2], ref.shape[-2], f, ref.shape[-1], f).mean(axis=(3, 5))
    placement = None
    over = [k for k in range(cam.shape[0]) if float(cam[k, 0]) == 0.0 and float(cam[k, 1]) == 0.0]
    if over:
        k = over[0]
        own = client.render(light[k].tolist(), inten[k].tolist(), cam[k].tolist(), height=h, width=w,
                            size=material.size, placement="camera")
        ts = client.render(light[k].tolist(), inten[k].tolist(), cam[k].tolist(), height=h, width=w, size=material.size)
        placement = psnr(own, ts)
    return ParityResult(
        names=list(names),
        psnr=[psnr(three[k], ref[k]) for k in range(len(names))],
        psnr_model=[psnr(model[k], ref[k]) for k in range(len(names))],
        psnr_client=[psnr(three[k], model[k]) for k in range(len(names))],
        psnr_placement=placement, reference=ref, model=model, three=three, material=summary,
        extras={k: em.extras.get(k) for k in ("lobe", "lobe_fit", "flakes", "bake") if k in em.extras})


def side_by_side(reference: np.ndarray, three: np.ndarray, path: str | Path, *, scale: int = 4, gain: float = 4.0) -> Path:
    """One PNG per call: rows = shots, columns = torchmetal | three.js | |difference|×gain (sRGB, nearest ×scale)."""
    ref = np.asarray(reference, np.float32).reshape(-1, *reference.shape[-3:])
    got = np.asarray(three, np.float32).reshape(-1, *three.shape[-3:])
    b, _, h, w = ref.shape
    gap = 2
    canvas = np.full((b * h + (b - 1) * gap, 3 * w + 2 * gap, 3), 0.2, np.float32)
    for k in range(b):
        y = k * (h + gap)
        for c, img in enumerate((ref[k], got[k], np.abs(got[k] - ref[k]) * gain)):
            srgb = linear_to_srgb(torch.from_numpy(img).clamp(0, 1)).permute(1, 2, 0).numpy()
            canvas[y:y + h, c * (w + gap):c * (w + gap) + w] = srgb
    big = canvas.repeat(scale, 0).repeat(scale, 1)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, encode_image(big, ".png", bits=8))
    return path


KIND_NOTES = {
    "phong": "global Phong lobe (the paper's model), flat",
    "blinn": "global Blinn-Phong lobe, flat",
    "ggx": "global GGX lobe (torchmetal's own GGX), flat",
    "clustered": "two specular clusters (Phong, alpha 15 and 80-120), flat",
    "gloss": "per-pixel gloss maps (Phong, alpha 40-300, s 0.1-0.3), flat",
    "normals": "normal map estimated from 12 synthetic shots (normals.estimate_normals), Phong lobe",
    "normals-ggx": "the same estimated normal map, GGX lobe",
    "flakes": "Phong + flake model (baked into the glTF maps)",
    "flakes-ggx": "GGX + flake model (baked into the glTF maps)",
}
FLAKE_FREE_GGX = ("ggx", "normals-ggx")  # kinds the glTF model can carry: the >= 30 dB goal applies to every shot


def parity_kinds(height: int = 64, width: int = 80, kinds=None) -> dict:
    """{kind: Material} of :data:`KIND_NOTES`, built deterministically on one procedural texture.

    The normal map of ``normals*`` is estimated from a synthetic bumpy capture of the same texture
    (:func:`torchmetal.normals.estimate_normals`, 12 shots), as ``fit --normals estimate`` does.
    """
    kinds = list(KIND_NOTES) if kinds is None else list(kinds)
    size = (0.12, 0.1)
    truth = synth_capture(size=(height, width), shots=12, seed=2, texture="procedural", bumpy=True)
    tex = truth.material().texture.float()
    s, a = torch.tensor([0.1, 0.15, 0.2]), torch.tensor([40.0, 50.0, 60.0])
    ggx_s, ggx_a = torch.full((3,), 0.2), torch.full((3,), 80.0)
    flakes = FlakeModel(0.02, area_log_mean=1.5, color_mean=(0.9, 0.8, 0.6), tilt_sigma=0.12, glint_sigma=0.05, seed=3)
    out = {}
    for kind in kinds:
        if kind == "phong":
            out[kind] = Material(tex, s, a, size)
        elif kind == "blinn":
            out[kind] = Material(tex, s, a, size, lobe="blinn")
        elif kind == "ggx":
            out[kind] = Material(tex, ggx_s, ggx_a, size, lobe="ggx")
        elif kind == "clustered":
            labels = (torch.arange(width).view(1, width).expand(height, width) >= width // 2).long()
            out[kind] = Material(tex, s, a, size, spec_labels=labels,
                                 cluster_s=torch.tensor([[0.08, 0.1, 0.12], [0.3, 0.25, 0.2]]),
                                 cluster_alpha=torch.tensor([[15.0, 15.0, 15.0], [120.0, 100.0, 80.0]]))
        elif kind == "gloss":
            yy, xx = torch.meshgrid(torch.linspace(0, 1, height), torch.linspace(0, 1, width), indexing="ij")
            ga = torch.exp(math.log(40.0) + (math.log(300.0) - math.log(40.0)) * xx).expand(3, height, width).clone()
            gs = (0.1 + 0.2 * yy).expand(3, height, width).clone()
            out[kind] = Material(tex, gs.mean((1, 2)), ga.mean((1, 2)), size, gloss_s=gs, gloss_alpha=ga)
        elif kind in ("normals", "normals-ggx"):
            if "_normals" not in out:
                out["_normals"] = estimate_normals(truth.capture).normals.float()
            n = out["_normals"]
            out[kind] = (Material(tex, s, a, size, normals=n) if kind == "normals"
                         else Material(tex, ggx_s, ggx_a, size, normals=n, lobe="ggx"))
        elif kind == "flakes":
            out[kind] = Material(tex, s, a, size, flakes=flakes)
        elif kind == "flakes-ggx":
            out[kind] = Material(tex, ggx_s, ggx_a, size, flakes=flakes, lobe="ggx")
        else:
            raise ValueError(f"kind: expected one of {list(KIND_NOTES)}, found {kind!r}")
    out.pop("_normals", None)
    return out



def table(out: str | Path, kinds=None) -> dict:
    """Run :func:`parity` on :func:`parity_kinds`; writes ``parity_<kind>.png`` and ``parity.json`` in
    ``out``; returns {"three": version, "kinds": {kind: row}}. RuntimeError without Chromium or three.js."""
    out = Path(out)
    rows = {}
    with ThreeClient() as client:
        for kind, m in parity_kinds(kinds=kinds).items():
            r = parity(m, client)
            side_by_side(r.reference, r.three, out / f"parity_{kind}.png")
            rows[kind] = {**r.row(), "note": KIND_NOTES[kind],
                          "client_per_shot": {n: round(p, 2) for n, p in zip(r.names, r.psnr_client)}}
        version = client.version
    res = {"three": version, "kinds": rows}
    out.mkdir(parents=True, exist_ok=True)
    (out / "parity.json").write_text(json.dumps(res, indent=1) + "\n")
    return res


def markdown(res: dict) -> str:
    """The parity table of :func:`table` as markdown."""
    if "skipped" in res:
        return f"skipped: {res['skipped']}"
    nan = float("nan")
    lines = [f"three.js {res['three']} (GLTFLoader → MeshPhysicalMaterial) against torchmetal's renderer, PSNR dB "
             "(linear, clipped, peak 1). Shots: overhead camera; camera at the light's mirror direction (30°); "
             "directional light and orthographic camera at 60° mirror. *glTF model*: torchmetal's evaluation of the "
             "exported BRDF vs its renderer (what the format loses); *client*: three.js vs that evaluation; "
             "*placement*: texture-space vs three.js's own projection (overhead shot).", "",
             "| kind | all shots | overhead | mirror | grazing | glTF model | client | placement | what it is |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for kind, r in res["kinds"].items():
        ps = r["per_shot"]
        pl = "—" if r["psnr_placement"] is None else f"{r['psnr_placement']:.0f}"
        lines.append(f"| {kind} | {r['psnr']:.1f} | {ps.get('overhead', nan):.1f} | {ps.get('mirror', nan):.1f} | "
                     f"{ps.get('grazing', nan):.1f} | {r['psnr_model']:.1f} | {r['psnr_client']:.1f} | {pl} | {r['note']} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    """``python -m torchmetal.formats.parity [--out DIR] [--kinds a,b]``: the parity table (markdown),
    ``parity.json`` and one side-by-side PNG per kind (torchmetal | three.js | |diff|×4; rows: overhead,
    mirror, grazing) in ``--out`` (default ``bench-results/parity``)."""
    import argparse

    p = argparse.ArgumentParser(prog="python -m torchmetal.formats.parity", description=main.__doc__)
    p.add_argument("--out", default="bench-results/parity")
    p.add_argument("--kinds", default=",".join(KIND_NOTES))
    args = p.parse_args(argv)
    res = table(args.out, [k for k in args.kinds.split(",") if k])
    print(markdown(res))
    print(f"\nside by side: {args.out}/parity_<kind>.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
