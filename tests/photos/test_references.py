"""Exposure and white balance from EXIF or the unclipped part of the paper band.

Generated photos with a clipped flash hotspot on the band, without EXIF, with the whole band
clipped (a dark sample exposed for), and with neither reference: each is used or rejected by what
can set its exposure, and the report says which reference set it.
"""

from types import SimpleNamespace

import numpy as np
import pytest

from torchmetal.errors import CaptureError
from torchmetal.photos import simulate as S
from torchmetal.photos.capture import _exposures, capture_from_photos
from torchmetal.photos.exif import read_exif
from torchmetal.photos.report import _text_lines, contact_image
from torchmetal.photos.white import SEGMENTS, WhiteReference, white_reference

from .conftest import FLASH, N

HOT = S.Hotspot(centre_mm=(27.0, 0.0), sigma_mm=4.0, peak=4.0)  # clips the band's right side over ~14 mm
FLOOD = S.Hotspot(centre_mm=(0.0, 0.0), sigma_mm=1e4, peak=3.0)  # the whole sheet 4x brighter: paper clipped
SPECIAL = {  # name: (pose index in photo_set, hotspot, EXIF stripped)
    "hot.jpg": (5, HOT, False), "hot_noexif.jpg": (2, HOT, True), "noexif.jpg": (4, None, True),
    "clipped.jpg": (7, FLOOD, False), "neither.jpg": (9, FLOOD, True),
    "clipped2.jpg": (3, FLOOD, False), "clipped3.jpg": (6, FLOOD, False),
}
BASE = 6  # the photo_set's first photos join the special ones


@pytest.fixture(scope="module")
def special(tmp_path_factory, photo_set, board, sheet, sample):
    names = list(SPECIAL)
    spec = [SPECIAL[k] for k in names]
    return S.phone_photos(tmp_path_factory.mktemp("refs"), board, sample, poses=[photo_set.poses[p] for p, _, _ in spec],
                          seed=7, flash_offset_mm=FLASH, sheet=sheet, supersample=1, names=names,
                          hotspots={k: h for k, (_, h, _) in enumerate(spec) if h is not None},
                          strip_exif=[k for k, (_, _, s) in enumerate(spec) if s])


@pytest.fixture(scope="module")
def mixed(photo_set, special, board):
    """The first BASE photos of photo_set, then hot, hot_noexif, noexif, clipped, neither."""
    paths = photo_set.paths[:BASE] + special.paths[:5]
    result = capture_from_photos(paths, board, flash_offset_mm=FLASH, resolution=N)
    truth = {p.name: (e.exposure, t) for p, e, t in zip(paths, photo_set.exif[:BASE] + special.exif[:5],
                                                           [*photo_set.tints[:BASE], *special.tints[:5]])}
    return result, truth, {r["file"]: r for r in result.report["photos"]}


def _wb_error(row, tint):
    undone = np.array(row["white_balance"]) * tint
    return float(np.abs(undone / undone[1] - 1).max())


def _exposure_error(row, truth, first):
    return row["exposure"] / (truth[row["file"]][0] / truth[first][0]) - 1


def test_hotspot_on_the_band_is_used_with_its_own_white_balance(mixed):
    result, truth, rows = mixed
    for name in ("hot.jpg", "hot_noexif.jpg"):
        r = rows[name]
        assert r["used"] and r["reason"] is None
        assert r["white_balance_source"] == "white_band"
        assert 0.5 < r["white_band_unclipped"] < 0.97  # the hotspot's part of the band is left out
        assert _wb_error(r, truth[name][1]) < 0.01  # measured 0.7 %, 0.5 %
    assert rows["hot.jpg"]["exposure_source"] == "exif"
    first = result.report["photos"][0]["file"]
    assert rows["hot.jpg"]["exposure"] == pytest.approx(truth["hot.jpg"][0] / truth[first][0], rel=1e-6)


def test_band_sets_the_exposure_without_exif(mixed, special):
    result, truth, rows = mixed
    stripped = read_exif(special.paths[list(SPECIAL).index("noexif.jpg")])
    assert stripped.exposure is None and stripped.make is None  # written without any EXIF
    first = result.report["photos"][0]["file"]
    for name in ("noexif.jpg", "hot_noexif.jpg"):
        r = rows[name]
        assert r["used"] and r["exposure_source"] == "white_band" and r["white_balance_source"] == "white_band"
        assert abs(_exposure_error(r, truth, first)) < 0.01  # measured -0.13 %, -0.05 %
        assert _wb_error(r, truth[name][1]) < 0.01
    assert rows["noexif.jpg"]["white_band_unclipped"] > 0.97
    # the capture's intensities follow the same relative exposures, with one unit for every shot
    cap, unit = result.capture, result.report["intensity_unit"]
    rel = np.array([rows[p]["exposure"] for p in (r["file"] for r in result.report["photos"] if r["used"])])
    assert np.allclose(cap.intensities[:, 0].double().numpy(), unit * rel, rtol=1e-5)
    assert all(r["exposure_source"] == "exif" for r in result.report["photos"][:BASE])


def test_clipped_band_with_exif_takes_the_set_median_white_balance(mixed):
    result, truth, rows = mixed
    r = rows["clipped.jpg"]
    assert r["used"] and r["exposure_source"] == "exif" and r["white_balance_source"] == "set_median"
    assert r["white_band_unclipped"] == 0.0
    own = np.array([x["white_balance"] for x in rows.values() if x["used"] and x["white_balance_source"] == "white_band"])
    assert np.allclose(r["white_balance"], np.median(own, 0), atol=1e-4)
    first = result.report["photos"][0]["file"]
    assert r["exposure"] == pytest.approx(truth["clipped.jpg"][0] / truth[first][0], rel=1e-6)


def test_neither_exif_nor_band_is_rejected_with_one_line(mixed):
    result, _, rows = mixed
    r = rows["neither.jpg"]
    assert not r["used"] and r["shot"] is None and "\n" not in r["reason"]
    assert r["white_band_unclipped"] == 0.0 and "exposure_source" not in r and "exposure" not in r
    assert result.capture.num_shots == BASE + 4
    assert [x["used"] for x in result.report["photos"]].count(False) == 1


def test_contact_sheet_names_the_references(mixed):
    result, _, rows = mixed
    lines = {r["file"]: _text_lines(r) for r in result.report["photos"]}
    assert "EXIF" in lines["hot.jpg"][3] and "white band" in lines["noexif.jpg"][3]
    assert "set median" in lines["clipped.jpg"][3] and lines["neither.jpg"][0].endswith("REJECTED")
    assert all(len(line) <= 58 for ls in lines.values() for line in ls[1:])
    assert contact_image(result).shape[0] > 0


def test_no_band_in_any_photo_is_one_clear_error(special, photo_set, board):
    paths = [special.paths[list(SPECIAL).index(k)] for k in ("clipped.jpg", "clipped2.jpg", "clipped3.jpg")]
    with pytest.raises(CaptureError, match="white paper band") as e:
        capture_from_photos(paths, board, flash_offset_mm=FLASH, resolution=16, intrinsics=photo_set.intrinsics)
    assert "\n" not in str(e.value)


# white_reference and _exposures on their own


def _band(level=(0.5, 0.6, 0.7), n_side=200, seed=0, noise=0.01):
    """Band points (k, 3) m around a 50 mm window, their values for a flash 0.3 m above (relative
    noise ``noise``), the flash, the irradiance (k,)."""
    rng = np.random.default_rng(seed)
    t = rng.uniform(-0.028, 0.028, (4, n_side))
    off = rng.uniform(0.026, 0.028, (4, n_side))
    xy = np.concatenate([np.stack([off[0], t[0]], 1), np.stack([-off[1], t[1]], 1),
                         np.stack([t[2], off[2]], 1), np.stack([t[3], -off[3]], 1)])
    pts = np.concatenate([xy, np.zeros((len(xy), 1))], 1)
    light = np.array([0.05, 0.02, 0.3])
    lv = light - pts
    irr = lv[:, 2] / (lv * lv).sum(1) ** 1.5
    vals = irr[:, None] * np.asarray(level)[None] * (1 + noise * rng.standard_normal((len(pts), 3)))
    return pts, vals, light, irr


def test_white_reference_leaves_out_the_clip_and_its_halo():
    pts, clean, light, irr = _band()
    seen, half = np.ones(len(pts), bool), (0.025, 0.025)
    r = np.linalg.norm(pts[:, :2] - [0.027, 0.0], axis=1) * 1000  # mm from a hotspot on the right side
    vals = clean * (1 + 4 * np.exp(-r**2 / 128))[:, None]  # peak 4, sigma 8 mm
    clipped = r < 12.0
    ref = white_reference(pts, vals, clipped, seen, light, half)
    truth = white_reference(pts, clean, np.zeros(len(pts), bool), seen, light, half)
    assert truth.unclipped == 1.0 and truth.segments == SEGMENTS
    assert ref.level is not None and np.abs(ref.level / truth.level - 1).max() < 0.005  # measured 0.2 %
    assert 0.7 < ref.unclipped < 0.95 and 10 <= ref.segments < SEGMENTS
    # what it avoids: the brighter half of all unclipped points (the former estimate) is pulled up by the halo
    norm = vals[~clipped] / irr[~clipped, None]
    naive = np.median(norm[norm.mean(1) >= np.median(norm.mean(1))], 0)
    assert naive[1] / truth.level[1] - 1 > 0.005  # measured 0.9 %


def test_white_reference_without_a_usable_band():
    pts, vals, light, _ = _band(noise=0.0)
    ref = white_reference(pts, vals, np.ones(len(pts), bool), np.ones(len(pts), bool), light, (0.025, 0.025))
    assert ref.level is None and ref.unclipped == 0.0 and ref.segments == 0 and "\n" not in ref.reason
    unseen = white_reference(pts, vals, np.zeros(len(pts), bool), np.zeros(len(pts), bool), light, (0.025, 0.025))
    assert unseen.level is None and unseen.unclipped == 0.0


def _obs(exposure):
    return SimpleNamespace(exif=SimpleNamespace(exposure=exposure), reason=None)


def test_exposures_from_exif_band_or_both():
    lv = lambda g: WhiteReference(np.array([0.9 * g, g, 1.1 * g]), 1.0, SEGMENTS)  # noqa: E731
    none = WhiteReference(None, 0.0, 0, "clipped")
    # EXIF and band on one scale: 10 band units per unit EXIF exposure
    obs = [_obs(2.0), _obs(None), _obs(4.0)]
    rel, gains, unit, src = _exposures(obs, [0, 1, 2], {0: lv(20.0), 1: lv(30.0), 2: none})
    assert rel == pytest.approx({0: 1.0, 1: 1.5, 2: 2.0}) and unit == pytest.approx(20.0)
    assert src == {0: ("exif", "white_band"), 1: ("white_band", "white_band"), 2: ("exif", "set_median")}
    assert np.allclose(gains[2], [1 / 0.9, 1, 1 / 1.1])
    # no photo with both: EXIF alone cannot be put on the band's scale, those photos are rejected
    obs = [_obs(None), _obs(2.0), _obs(None)]
    rel, _, _, src = _exposures(obs, [0, 1, 2], {0: lv(20.0), 1: none, 2: lv(10.0)})
    assert rel == pytest.approx({0: 1.0, 2: 0.5}) and obs[1].reason and obs[0].reason is None
