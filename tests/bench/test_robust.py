"""The robust section's tables (torchmetal.bench.robust): the real captures' default command against its target."""

from torchmetal.bench.robust import REAL_DEFAULT_TARGET_S, markdown, real_default_rows


def _row(capture, options, wall, **kw):
    return {"capture": capture, "options": options, "wall_s": wall, "complete": True, **kw}


def test_the_real_captures_default_command_is_checked_against_its_target():
    matrix = [_row("cards_blue", "default", REAL_DEFAULT_TARGET_S - 1), _row("cards_blue", "flakes on", 99.0),
              _row("yellow_box", "default", REAL_DEFAULT_TARGET_S + 0.5), _row("flakes_a", "default", 99.0),
              _row("uw_gray_sphere", "default", 5.0, error="boom")]
    lines = real_default_rows(matrix)
    body = [ln for ln in lines if ln.startswith("| ") and not ln.startswith("| capture")]
    assert body == [f"| cards_blue | {REAL_DEFAULT_TARGET_S - 1:.1f} | yes |",
                    f"| yellow_box | {REAL_DEFAULT_TARGET_S + 0.5:.1f} | NO |",
                    "| uw_gray_sphere | 5.0 | NO |"]  # a failed run never meets the target
    assert real_default_rows([_row("flakes_a", "default", 1.0)]) == []  # no real capture: no table
    assert "Default whole command on the shared real captures" in markdown({"matrix": matrix, "share": []})
