"""graf.reports.published.choose (scripts/choose_graf.py, the site): the studies' GRaF is chosen from validation
curves by a fixed rule."""

from __future__ import annotations

import pytest

from graf.errors import UserError
from graf.reports import published as choose_graf


def _row(regime, method, step, psnr, ssim, lpips):
    return {
        "regime": regime,
        "method": method,
        "step": str(step),
        "val_psnr": str(psnr),
        "val_ssim": str(ssim),
        "val_lpips": str(lpips),
        "val_reliance_db": "1.0",
    }


def test_best_mean_rank_at_the_largest_common_step_wins_and_later_points_of_one_mode_are_ignored():
    rows = [
        _row("a", "x", 100, 20, 0.7, 0.3),
        _row("a", "y", 100, 19, 0.8, 0.2),
        _row("a", "x", 1000, 30, 0.9, 0.1),  # only x reached 1000: not compared
        _row("b", "x", 100, 18, 0.6, 0.4),
        _row("b", "y", 100, 18.5, 0.5, 0.3),
    ]
    chosen, table = choose_graf.choose(rows, ["x", "y"])
    assert chosen == "y"  # y wins 4 of the 6 figures at step 100
    assert {t["step"] for t in table} == {100}


def test_a_tie_in_rank_goes_to_the_higher_mean_psnr():
    rows = [
        _row("a", "x", 100, 21, 0.6, 0.3),
        _row("a", "y", 100, 20, 0.7, 0.2),  # x wins 1 of 3
        _row("b", "x", 100, 19, 0.8, 0.3),
        _row("b", "y", 100, 18.9, 0.7, 0.2),
    ]  # x wins 2 of 3
    chosen, table = choose_graf.choose(rows, ["x", "y"])
    assert {t["mean_rank"] for t in table} == {1.5}
    assert chosen == "x"


def test_a_mode_missing_from_a_regime_is_an_error():
    with pytest.raises(UserError, match="no points of"):
        choose_graf.choose(
            [_row("a", "x", 100, 20, 0.7, 0.3), _row("b", "y", 100, 20, 0.7, 0.3), _row("a", "y", 100, 20, 0.7, 0.3)],
            ["x", "y"],
        )


def test_a_regime_in_progress_is_named_with_its_missing_modes_and_kept_out_of_the_choice():
    rows = [
        _row("done", "x", 100, 20, 0.7, 0.3),
        _row("done", "y", 100, 21, 0.8, 0.2),
        _row("running", "x", 100, 30, 0.9, 0.1),  # y has no point here yet
    ]
    ready, waiting = choose_graf.regimes_ready(rows, ["x", "y"])
    assert ready == ["done"]
    assert waiting == {"running": ["y"]}
    chosen, table = choose_graf.choose([r for r in rows if r["regime"] in ready], ["x", "y"])
    assert chosen == "y"  # the running regime's better x point does not count
    assert {t["regime"] for t in table} == {"done"}
