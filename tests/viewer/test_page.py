"""The viewer page in real Chromium, both modes: served (Python onnxruntime) and static (onnxruntime-web).

Every frame check compares the canvas with the onnxruntime (Python) render of the same inputs,
encoded with the library's sRGB curve: within one 8-bit level on ≥ 99 % of pixels.
"""

from __future__ import annotations

import base64
import io
import json
import re

import numpy as np
import pytest

from tests.viewer.conftest import SIZE, ort_render, parse_hash, srgb8, state_inputs

MODES = ("served", "static")
CHOSEN = [
    # point light, orthographic camera, exposure ≠ 1
    "#lt=point&laz=40&lel=35&ld=1.2&li=1.5&lc=1,0.8,0.6&ex=1.5&ct=ortho&caz=0&cel=90&cd=2&fl=1&shot=-1&ab=render",
    # directional light, perspective camera off-axis
    "#lt=dir&laz=-120&lel=60&ld=1&li=0.8&lc=1,1,1&ex=1&ct=point&caz=45&cel=70&cd=1.5&fl=1&shot=-1&ab=render",
]


@pytest.fixture(scope="module", params=MODES)
def mode_url(request, scene, served, static_url):
    return request.param, (served.url if request.param == "served" else static_url)


@pytest.fixture(scope="module")
def page(browser, mode_url):
    from torchmetal.viewer.browser import open_viewer

    p = open_viewer(browser, mode_url[1])
    yield p
    p.close()


def canvas(page, cid: str = "view") -> np.ndarray:
    """(H, W, 3) uint8 pixels of a canvas (its own resolution, not the CSS size)."""
    w, h, data = page.evaluate("""id => { const c = document.getElementById(id);
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let s = ''; for (let i = 0; i < d.length; i += 8192) s += String.fromCharCode(...d.subarray(i, i + 8192));
        return [c.width, c.height, btoa(s)]; }""", cid)
    return np.frombuffer(base64.b64decode(data), np.uint8).reshape(h, w, 4)[..., :3]


def page_state(page) -> dict:
    return parse_hash(page.evaluate("location.hash"))


def graph(scene, flakes: bool):
    return scene.site / ("renderer.onnx" if flakes else "renderer-noflakes.onnx")


def expected(scene, state: dict, flakes: bool | None = None) -> np.ndarray:
    extent = max(scene.material.size)
    light, intensity, camera = state_inputs(state, extent)
    fl = bool(state["fl"]) if flakes is None else flakes
    return srgb8(ort_render(graph(scene, fl), light, intensity, camera), state["ex"])


def assert_matches(got: np.ndarray, want: np.ndarray, what: str) -> None:
    assert got.shape == want.shape, f"{what}: shape {got.shape} vs {want.shape}"
    diff = np.abs(got.astype(int) - want.astype(int)).max(axis=2)
    within = float((diff <= 1).mean())
    assert within >= 0.99, f"{what}: {within:.4f} of pixels within one 8-bit level (max diff {diff.max()})"


def save(page, artefacts, name: str) -> None:
    page.screenshot(path=str(artefacts / f"{name}.png"))


class TestPage:
    def test_first_frame(self, page, mode_url, artefacts):
        mode = mode_url[0]
        assert page.evaluate("window.tmviewer.frames") >= 1
        assert page.evaluate("window.tmviewer.error") is None
        assert page.locator("#mode").inner_text().startswith(mode)
        px = canvas(page)
        assert px.shape == (SIZE, SIZE, 3) and px.std() > 5, "first frame is blank"
        assert re.fullmatch(r"\d+(\.\d+)? fps \(\d+(\.\d+)? ms/frame\)", page.locator("#fps").inner_text())
        assert not page.locator("#ep-box").is_visible()  # no WebGPU build in this site / served mode
        save(page, artefacts, f"{mode}-first-frame")

    def test_light_drag_changes_frame(self, page, mode_url, scene, artefacts):
        page.evaluate("window.tmviewer.setState({laz: 0, lel: 60, lt: 'point', ex: 1, fl: 1, shot: -1, ab: 'render', ct: 'ortho', cel: 90})")
        before, s0 = canvas(page), page_state(page)
        box = page.locator("#hemi").bounding_box()
        cx, cy, r = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2, box["width"] / 2 - 6
        frames = page.evaluate("window.tmviewer.frames")
        page.mouse.move(cx + 0.5 * r, cy)
        page.mouse.down()
        page.mouse.move(cx - 0.3 * r, cy - 0.6 * r, steps=6)
        page.mouse.up()
        page.evaluate("window.tmviewer.idle()")
        s1 = page_state(page)
        assert page.evaluate("window.tmviewer.frames") > frames
        assert abs(s1["laz"] - s0["laz"]) > 30 and abs(s1["lel"] - s0["lel"]) > 5, (s0, s1)
        after = canvas(page)
        assert np.abs(after.astype(int) - before.astype(int)).mean() > 1.0, "the drag did not change the frame"
        assert_matches(after, expected(scene, s1), f"{mode_url[0]} after drag")
        save(page, artefacts, f"{mode_url[0]}-after-drag")

    @pytest.mark.parametrize("k", range(len(CHOSEN)))
    def test_chosen_light_matches_python(self, browser, mode_url, scene, artefacts, k):
        """A fresh page opened at a URL state renders exactly that state's inputs."""
        from torchmetal.viewer.browser import open_viewer

        urls: list[str] = []
        p = open_viewer(browser, mode_url[1] + CHOSEN[k], requests=urls)
        try:
            # everything (page, ORT's .mjs/.wasm, graphs, three.js, the glb) comes from this site / server
            # only; blob: URLs of this origin are the glb's embedded textures (GLTFLoader)
            assert urls and all(u.startswith((mode_url[1], "data:", "blob:" + mode_url[1])) for u in urls), urls
            if mode_url[0] == "static":
                assert any(u.endswith("ort/ort-wasm-simd-threaded.wasm") for u in urls), urls
            p.evaluate("window.tmviewer.idle()")
            state = page_state(p)
            want_state = parse_hash(CHOSEN[k])
            for key, v in want_state.items():
                assert state[key] == pytest.approx(v), key
            light, intensity, camera = state_inputs(want_state, max(scene.material.size))
            got = p.evaluate("window.tmviewer.lastInputs")
            np.testing.assert_allclose(got["light"], light, rtol=1e-6, atol=1e-7)
            np.testing.assert_allclose(got["light_intensity"], intensity, rtol=1e-6)
            np.testing.assert_allclose(got["camera"], camera, rtol=1e-6, atol=1e-7)
            assert_matches(canvas(p), expected(scene, want_state), f"{mode_url[0]} {CHOSEN[k]}")
            save(p, artefacts, f"{mode_url[0]}-chosen-{k}")
        finally:
            p.close()

    def test_flakes_toggle(self, page, mode_url, scene, artefacts):
        state = flake_state(scene)
        page.evaluate("s => window.tmviewer.setState(s)", state)
        full = canvas(page)
        assert_matches(full, expected(scene, page_state(page), flakes=True), "flakes on")
        page.locator("#flakes").click()
        page.evaluate("window.tmviewer.idle()")
        s = page_state(page)
        assert s["fl"] == 0 and page.evaluate("window.tmviewer.lastFlakes") is False
        plain = canvas(page)
        assert_matches(plain, expected(scene, s, flakes=False), "flakes off")
        assert (np.abs(full.astype(int) - plain.astype(int)).max(axis=2) > 2).sum() >= 5, "flakes toggle did not change the frame"
        save(page, artefacts, f"{mode_url[0]}-flakes-off")
        page.locator("#flakes").click()
        page.evaluate("window.tmviewer.idle()")
        assert page_state(page)["fl"] == 1
        assert_matches(canvas(page), full, "flakes back on")

    def test_snapshot_written(self, page, mode_url, artefacts):
        from PIL import Image

        page.evaluate("window.tmviewer.setState({laz: 100, lel: 40, ab: 'render', shot: -1})")
        with page.expect_download() as dl:
            page.locator("#snapshot").click()
        target = artefacts / f"{mode_url[0]}-snapshot.png"
        dl.value.save_as(str(target))
        assert dl.value.suggested_filename.startswith("torchmetal-") and dl.value.suggested_filename.endswith(".png")
        img = np.asarray(Image.open(target).convert("RGB"))
        assert np.array_equal(img, canvas(page)), "snapshot PNG differs from the displayed frame"

    def test_photo_render_ab(self, page, mode_url, scene, artefacts):
        from PIL import Image

        from torchmetal.viewer.site import photo_png

        k = 1
        shot = {"light": scene.capture.lights[k].tolist(), "light_intensity": scene.capture.intensities[k].tolist(),
                "camera": scene.capture.cameras[k].tolist()}
        page.evaluate("window.tmviewer.setState({ex: 1, fl: 1, ab: 'render', shot: -1})")
        page.locator("#shot").select_option(str(k))
        page.wait_for_function("window.tmviewer.state.shot === 1")
        page.evaluate("window.tmviewer.idle()")
        got_inputs = page.evaluate("window.tmviewer.lastInputs")
        for key in shot:
            np.testing.assert_allclose(got_inputs[key], shot[key], rtol=1e-5, atol=1e-6)
        photo = np.asarray(Image.open(io.BytesIO(photo_png(scene.capture, k))).convert("RGB"))
        render = srgb8(ort_render(graph(scene, True), shot["light"], shot["light_intensity"], shot["camera"]))
        # selecting a shot opens the split: photo on the left, render on the right
        assert page.evaluate("window.tmviewer.state.ab") == "split"
        page.evaluate("window.tmviewer.setState({sp: 0.5})")
        px = canvas(page)
        half = SIZE // 2
        assert np.array_equal(px[:, :half], photo[:, :half]), "split: left half is not the photo"
        assert_matches(px[:, half + 1 :], render[:, half + 1 :], "split: right half is the shot's render")
        save(page, artefacts, f"{mode_url[0]}-split")
        page.locator("#compare").select_option("side")
        page.evaluate("window.tmviewer.idle()")
        assert page.locator("#photo-box").is_visible()
        assert np.array_equal(canvas(page, "photo"), photo)
        assert_matches(canvas(page), render, "side by side: render")
        save(page, artefacts, f"{mode_url[0]}-side-by-side")
        page.locator("#compare").select_option("render")

    def test_url_follows_fast_changes_and_reproduces_the_view(self, browser, page, mode_url):
        """300 quick changes (a fast drag; browsers throttle history updates) end with the URL at the
        last state, and opening that URL shows the same frame."""
        page.evaluate("""async () => { for (let k = 0; k < 300; k++) {
            window.tmviewer.setState({laz: -60 + k * 0.3, lel: 20 + k * 0.1, ab: 'render', shot: -1});
            await new Promise((r) => setTimeout(r, 1)); }
            await window.tmviewer.idle(); }""")
        s = page_state(page)
        assert s["laz"] == pytest.approx(-60 + 299 * 0.3) and s["lel"] == pytest.approx(20 + 29.9)
        from torchmetal.viewer.browser import open_viewer

        again = open_viewer(browser, page.url)
        try:
            again.evaluate("window.tmviewer.idle()")
            assert page_state(again) == s
            assert np.array_equal(canvas(again), canvas(page))
        finally:
            again.close()

    def test_exposure_slider_reencodes(self, page, scene):
        page.evaluate("window.tmviewer.setState({laz: 10, lel: 45, ex: 1, shot: -1, ab: 'render', fl: 1})")
        frames = page.evaluate("window.tmviewer.frames")
        # one stop up: ex = 2, re-encoded without a new render
        page.evaluate("() => { const e = document.getElementById('exposure'); e.value = '1'; e.dispatchEvent(new Event('input')); }")
        page.evaluate("window.tmviewer.idle()")
        s = page_state(page)
        assert s["ex"] == pytest.approx(2.0)
        assert page.evaluate("window.tmviewer.frames") == frames
        assert_matches(canvas(page), expected(scene, s), "exposure x2")

    def test_camera_orbit_drag(self, page, scene):
        page.evaluate("window.tmviewer.setState({caz: 0, cel: 80, ct: 'point', cd: 1, ab: 'render', shot: -1})")
        box = page.locator("#view").bounding_box()
        x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        page.mouse.move(x, y)
        page.mouse.down()
        page.mouse.move(x - 60, y - 40, steps=4)
        page.mouse.up()
        page.evaluate("window.tmviewer.idle()")
        s = page_state(page)
        assert s["caz"] == pytest.approx(30, abs=1) and s["cel"] == pytest.approx(60, abs=1)
        assert_matches(canvas(page), expected(scene, s), "after camera orbit")


def flake_state(scene) -> dict:
    """Of a few lights, the one whose flakes-on render differs most from flakes-off (Python)."""
    best, best_n = None, -1
    for laz in (0, 90, 180, 270):
        for lel in (30, 55, 80):
            s = {"lt": "point", "laz": laz, "lel": lel, "ld": 1.5, "li": 1.0, "lc": [1, 1, 1], "ex": 1.0,
                 "ct": "ortho", "caz": 0, "cel": 90, "cd": 2.0, "fl": 1, "shot": -1, "ab": "render"}
            n = int((np.abs(expected(scene, s, True).astype(int) - expected(scene, s, False).astype(int)).max(axis=2) > 2).sum())
            if n > best_n:
                best, best_n = s, n
    return best


def test_config_is_shared(scene, served):
    """Both modes give the page the same material, graphs and shots (only mode/ort differ)."""
    import urllib.request

    static = json.loads((scene.site / "config.json").read_text())
    with urllib.request.urlopen(served.url + "config.json") as r:
        live = json.loads(r.read())
    for key in ("format", "version", "width", "height", "surface", "graphs", "shots"):
        assert static[key] == live[key], key
    assert (static["mode"], live["mode"]) == ("static", "served")


def test_file_url_says_how_to_serve(browser, scene):
    p = browser.new_page()
    try:
        p.goto((scene.site / "index.html").as_uri())
        assert "python3 -m http.server" in p.locator("#status").inner_text()
    finally:
        p.close()


def test_webgpu_switch_falls_back_to_wasm(browser, scene, tmp_path):
    """A site with ORT's WebGPU build, opened with ?ep=webgpu on a GPU-less browser, still renders right."""
    import shutil

    from torchmetal.formats.web import WEBGPU_FILES, find_ort_web
    from torchmetal.viewer.browser import open_viewer, serve_folder

    site = tmp_path / "site"
    shutil.copytree(scene.site, site, symlinks=True)
    dist, _ = find_ort_web(webgpu=True)
    for name in WEBGPU_FILES:
        (site / "ort" / name).symlink_to(dist / name)
    cfg = json.loads((site / "config.json").read_text())
    cfg["ort"]["webgpu"] = f"ort/{WEBGPU_FILES[0]}"
    (site / "config.json").write_text(json.dumps(cfg))
    httpd, url = serve_folder(site)
    try:
        p = open_viewer(browser, url + "?ep=webgpu" + CHOSEN[0])
        try:
            assert p.locator("#ep-box").is_visible() and p.locator("#ep").input_value() == "webgpu"
            label = p.locator("#mode").inner_text()
            assert "(WebGPU" in label or "no WebGPU adapter, using wasm" in label, label
            assert_matches(canvas(p), expected(scene, parse_hash(CHOSEN[0])), f"ep=webgpu ({label})")
        finally:
            p.close()
    finally:
        httpd.shutdown()
        httpd.server_close()


def test_material_without_flakes_disables_toggle(browser, scene, tmp_path):
    """A site with one (flake-free) graph: the checkbox is disabled and frames are that graph's."""
    from torchmetal.viewer.browser import open_viewer, serve_folder

    site = tmp_path / "site"
    site.mkdir()
    for f in scene.site.iterdir():
        if f.name not in ("config.json", "renderer.onnx"):
            (site / f.name).symlink_to(f)
    cfg = json.loads((scene.site / "config.json").read_text())
    cfg["graphs"] = {"plain": "renderer-noflakes.onnx"}
    (site / "config.json").write_text(json.dumps(cfg))
    httpd, url = serve_folder(site)
    try:
        p = open_viewer(browser, url + CHOSEN[0])
        try:
            assert p.locator("#flakes").is_disabled() and not p.locator("#flakes").is_checked()
            assert p.evaluate("window.tmviewer.lastFlakes") is False
            assert_matches(canvas(p), expected(scene, parse_hash(CHOSEN[0]), flakes=False), "no-flakes site")
        finally:
            p.close()
    finally:
        httpd.shutdown()
        httpd.server_close()
