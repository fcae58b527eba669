"""The null test's detection threshold for the flake statistics (null_test.glint_snr)."""

from torchmetal.flakes.estimate.null_test import MAX_MIRRORED_SHARE, glint_snr


def _counts(positive, mirrored):
    return {"snr": [5.0, 7.0, 10.0, 15.0, 20.0, 30.0], "positive": positive, "mirrored": mirrored}


def test_clean_detections_keep_the_detectors_threshold():
    """The zoo's procedural flake scenes: mirrored ≤ 5 % of the positive locations at SNR 5 (flakes_half 4 of 96)."""
    assert glint_snr(_counts([96, 89, 83, 76, 73, 59], [4, 1, 0, 0, 0, 0]), 5.0) == 5.0


def test_misfit_raises_the_threshold_to_the_first_clean_rung():
    """flakes_orange (photo texture): 27 of 128 at SNR 5, 3 of 91 at 7 → 7; the card (cards_blue): 7 of 72 at 15, 0 of 21 at 20 → 20."""
    assert glint_snr(_counts([128, 91, 80, 70, 60, 45], [27, 3, 0, 0, 0, 0]), 5.0) == 7.0
    assert glint_snr(_counts([3733, 1225, 336, 72, 21, 3], [756, 219, 47, 7, 0, 0]), 5.0) == 20.0
    share = MAX_MIRRORED_SHARE
    assert glint_snr(_counts([100, 100, 0, 0, 0, 0], [round(100 * share), 50, 0, 0, 0, 0]), 5.0) == 5.0  # at the share


def test_never_below_the_detectors_threshold_nor_on_an_empty_rung():
    assert glint_snr(_counts([128, 91, 80, 70, 60, 45], [27, 3, 0, 0, 0, 0]), 10.0) == 10.0
    assert glint_snr(_counts([50, 40, 0, 0, 0, 0], [20, 20, 0, 0, 0, 0]), 5.0) == 5.0  # no clean rung: k_hi
