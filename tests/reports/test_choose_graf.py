"""graf.reports.choices.choose (scripts/choose_graf.py, the site): the studies' GRaF is chosen from validation
curves by a fixed rule."""

from __future__ import annotations

import pytest

from graf.errors import UserError
from graf.reports import choices as choose_graf


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


def test_a_continuing_regime_makes_no_choice_and_reports_its_curves_beside_its_parents():
    rows = [
        _row("d", "x", 1000, 20, 0.7, 0.3),
        _row("d", "y", 1000, 22, 0.8, 0.2),
        _row("d30", "x", 1000, 20.5, 0.7, 0.3),
        _row("d30", "x", 3000, 22.5, 0.75, 0.25),  # its best: ahead of the choice y in PSNR only
        _row("d30", "x", 9000, 21.0, 0.7, 0.3),
    ]
    choices, waiting, beside = choose_graf.choose_per_regime(rows, ["x", "y"], {"d30": "d"})
    assert waiting == {}  # d30 has no y and is not "in progress" for it
    assert [(regime, chosen) for regime, chosen, _ in choices] == [("d", "y"), (None, "y")]
    assert all(t["regime"] == "d" for _, _, table in choices for t in table)  # d30's points never rank
    [(regime, parent, chosen, table)] = beside
    assert (regime, parent, chosen) == ("d30", "d", "y")
    got = [(t["mode"], t["step"], t["point"], t["ahead"]) for t in table]
    assert got == [("y", 1000, "chosen", []), ("x", 3000, "best", ["val_psnr"]), ("x", 9000, "last", [])]


def test_the_curves_config_names_the_30k_regime_a_continuation_of_regime_d():
    assert choose_graf.continued_regimes() == {"cross_family_val_30k": "cross_family_val"}


def test_a_continues_key_naming_no_regime_stops_with_the_file_and_key(tmp_path, monkeypatch):
    import graf.app.config
    from graf.errors import ConfigError

    (tmp_path / "curves.yaml").write_text("regimes:\n  d: {max_steps: 10}\n  d30: {max_steps: 30, continues: dd}\n")
    monkeypatch.setattr(graf.app.config, "CONF_DIR", str(tmp_path))
    with pytest.raises(ConfigError, match=r"curves.yaml: regimes.d30.continues: 'dd' is not another regime"):
        choose_graf.continued_regimes()


def test_the_main_jobs_rule_takes_the_best_point_that_leads_knn_in_all_three_figures():
    """The main job's rule (conf/experiment/graf_rfid_s23.yaml): a point ahead in PSNR but behind in LPIPS is out;
    of the points ahead in all three, the highest PSNR, the fewest steps within 0.1 dB; none: None."""
    from graf.reports.choices import leading_knn

    def row(mode, step, psnr, ssim, lpips):
        return {"regime": "m", "method": mode, "step": str(step), "val_psnr": str(psnr), "val_ssim": str(ssim),
                "val_lpips": str(lpips), "val_reliance_db": "1.0"}  # fmt: skip

    knn = {"val/psnr": 15.0, "val/ssim": 0.64, "val/lpips": 0.243}
    rows = [
        row("ray_weights", 300, 16.5, 0.66, 0.254),  # ahead in PSNR and SSIM, behind in LPIPS: out
        row("ray_knn", 300, 17.30, 0.70, 0.230),
        row("ray_knn", 500, 17.35, 0.71, 0.220),  # within 0.1 dB of the best: the fewer steps win
        row("pooled", 500, 14.0, 0.40, 0.800),
        {**row("ray", 100, 99.0, 0.99, 0.01), "regime": "other"},  # another regime: not read
    ]
    chosen, table = leading_knn(rows, knn, "m")
    assert (chosen["mode"], chosen["step"]) == ("ray_knn", 300)
    assert [(t["mode"], t["step"], t["leads"]) for t in table] == [
        ("pooled", 500, False), ("ray_knn", 300, True), ("ray_knn", 500, True), ("ray_weights", 300, False)
    ]  # fmt: skip
    assert leading_knn(rows[:1], knn, "m")[0] is None
    with pytest.raises(UserError, match="no KNN line"):
        leading_knn(rows, {"val/psnr": 15.0}, "m")
