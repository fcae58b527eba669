"""The 3D preview (preview.js): the glTF export in three.js on a plane and a sphere, both modes.

Playwright drives the page: screenshots of the preview before and after a pointer drag (tilt) and
after moving the light with the page's own control; the pixels must change and the page must log
no console errors. Screenshots go to the artefacts folder (``preview_<mode>_*.png``).
"""

from __future__ import annotations

import io
import json
import re

import numpy as np
import pytest

MODES = ("served", "static")


def shot(page, selector: str = "#preview") -> tuple[bytes, np.ndarray]:
    from PIL import Image

    png = page.locator(selector).screenshot()
    return png, np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float64)


def wait_frames(page, more_than: int) -> int:
    page.wait_for_function(f"window.tmviewer.preview && window.tmviewer.preview.frames > {more_than}", timeout=30_000)
    return page.evaluate("window.tmviewer.preview.frames")


@pytest.fixture(scope="module", params=MODES)
def preview_page(request, browser, served, static_url):
    url = served.url if request.param == "served" else static_url
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(f"pageerror: {e}"))
    page.on("console", lambda m: errors.append(f"console.{m.type}: {m.text}") if m.type == "error" else None)
    page.goto(url)
    page.wait_for_function("window.tmviewer && (window.tmviewer.frames > 0 || window.tmviewer.error)", timeout=60_000)
    page.evaluate("window.tmviewer.previewReady")
    assert not page.evaluate("window.tmviewer.preview && window.tmviewer.preview.error"), page.evaluate("window.tmviewer.preview.error")
    wait_frames(page, 0)
    yield request.param, page, errors
    page.close()


def test_preview_drag_and_light_change_the_pixels(preview_page, artefacts):
    mode, page, errors = preview_page
    assert page.evaluate("document.getElementById('preview-box').hidden") is False
    png0, before = shot(page)
    (artefacts / f"preview_{mode}_before.png").write_bytes(png0)
    # the preview shows something: the plane and the sphere are lit (not a black canvas)
    h, w, _ = before.shape
    for half in (before[:, : w // 2], before[:, w // 2:]):
        assert half.mean() > 10 and half.std() > 5, (mode, half.mean(), half.std())

    box = page.locator("#preview").bounding_box()
    x0, y0 = box["x"] + box["width"] * 0.25, box["y"] + box["height"] * 0.5
    n = page.evaluate("window.tmviewer.preview.frames")
    page.mouse.move(x0, y0)
    page.mouse.down()
    for k in range(1, 9):
        page.mouse.move(x0 + 10 * k, y0 + 8 * k)
    page.mouse.up()
    wait_frames(page, n)
    page.evaluate("new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
    tilt = page.evaluate("window.tmviewer.preview.tilt")
    assert abs(tilt["x"]) > 10 and abs(tilt["z"]) > 10, tilt
    png1, dragged = shot(page)
    (artefacts / f"preview_{mode}_dragged.png").write_bytes(png1)
    changed = float((np.abs(dragged - before).max(axis=2) > 8).mean())
    assert changed > 0.05, f"{mode}: only {changed:.3f} of the preview's pixels changed after the drag"

    # the light control moves the preview's light too (and the texture view's)
    n = page.evaluate("window.tmviewer.preview.frames")
    page.evaluate("window.tmviewer.setState({laz: -150, lel: 25})")
    wait_frames(page, n)
    page.evaluate("new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
    png2, relit = shot(page)
    (artefacts / f"preview_{mode}_relit.png").write_bytes(png2)
    page.screenshot(path=str(artefacts / f"preview_{mode}_page.png"))
    changed = float((np.abs(relit - dragged).max(axis=2) > 8).mean())
    assert changed > 0.05, f"{mode}: only {changed:.3f} of the preview's pixels changed with the light"
    assert not errors, errors


def test_preview_config_and_assets(preview_page, scene):
    from torchmetal.viewer.three import FILES, IMPORT_MAP

    mode, page, _ = preview_page
    cfg = page.evaluate("window.tmviewer.config")
    assert cfg["preview"] == {"glb": "material.glb", "three": cfg["preview"]["three"]}
    assert cfg["preview"]["three"].startswith("0.187.")
    for name in ("material.glb", *FILES):
        status = page.evaluate("u => fetch(u).then(r => r.status)", name)
        assert status == 200, (mode, name, status)
    index = page.evaluate("fetch('index.html').then(r => r.text())")
    found = json.loads(re.search(r'<script type="importmap">(.*?)</script>', index).group(1))
    assert found == IMPORT_MAP
    if mode == "static":  # the site carries everything: three.js and the glb are files of the folder
        assert (scene.site / "material.glb").is_file() and all((scene.site / n).is_file() for n in FILES)


def test_preview_pages_load_nothing_from_elsewhere(scene):
    for name in ("index.html", "preview.js", "viewer.js"):
        text = (scene.site / name).read_text()
        assert not re.search(r"(https?:)?//[a-z0-9.-]+\.[a-z]{2,}", text, re.I), name


def test_site_without_three_has_no_preview(browser, scene, tmp_path, monkeypatch):
    """Without three.js the site is written without the preview, and the page says so (no errors)."""
    from torchmetal.formats.web import write
    from torchmetal.viewer import three
    from torchmetal.viewer.browser import open_viewer, serve_folder

    monkeypatch.setattr(three, "find_three", lambda three_dir=None: None)
    site = write(scene.material, tmp_path / "site")
    assert not (site / "material.glb").exists() and not (site / "three").exists()
    cfg = json.loads((site / "config.json").read_text())
    assert cfg["preview"] is None and "npm ci" in cfg["preview_note"]
    httpd, url = serve_folder(site)
    try:
        page = open_viewer(browser, url)
        page.evaluate("window.tmviewer.previewReady")
        assert page.evaluate("document.getElementById('preview-box').hidden") is True
        assert "three.js not found" in page.evaluate("window.tmviewer.preview.error")
        page.close()
    finally:
        httpd.shutdown()
        httpd.server_close()
