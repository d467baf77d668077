"""The commands' entry points (graf.cli.entry.graf_command): a mistake Hydra would report as a page (an unknown
option of a config group, ``+key=`` on a key that exists) is one line with exit code 2, a constructor's refusal of
a value names the setting, a multirun ends with one line per failed job and how many failed, and the old spelling
("neighbour") still works with a warning."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import hydra
import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import MissingConfigException
from omegaconf import OmegaConf

from graf.app.config import CONF_DIR
from graf.app.overrides import RENAMED_KEYS, modernize
from graf.cli import evaluate as graf_eval
from graf.cli import train as graf_train
from graf.errors import user_message

BIN = Path(sys.executable).parent
HINT = "(HYDRA_FULL_ERROR=1 shows the full traceback)"


def _main(monkeypatch, capsys, main, *args: str) -> tuple[int | None, str, str]:
    """Run a command's ``main`` with this command line; its exit code (None: returned), stdout and stderr."""
    monkeypatch.setattr(sys, "argv", ["graf", *args])
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    code = None
    try:
        main()
    except SystemExit as exc:
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize(
    "arg, says",
    [
        ("band=5ghz", "band=5ghz: no such option of 'band'; the options are 1.8ghz, 2.4ghz, 3ghz, 915mhz"),
        ("eval_scene=nowhere", "eval_scene=nowhere: no such option of 'eval_scene'; the options are bedroom,"),
        ("model=graf_xl", "model=graf_xl: no such option of 'model'; the options are graf, graf_cpu,"),
        ("scene=nowhere", "scene=nowhere: no such option of 'scene'; the options are bedroom,"),
        ("model=knn,graf_xl", "model=graf_xl: no such option of 'model'"),  # every value of a sweep
        ("scene=[rfid_s23,nowhere]", "scene=nowhere: no such option of 'scene'"),  # every item of a list
        ("model.no_such_key=1", "model.no_such_key=1: no such setting (to add one, write +model.no_such_key=1)"),
    ],
)
def test_an_unknown_group_option_or_key_is_one_line_with_exit_code_2(monkeypatch, capsys, arg, says):
    """They were Hydra's 13-22 lines (the options, the config search path) with exit code 1."""
    flags = ("-m",) if "," in arg else ()
    code, _, err = _main(monkeypatch, capsys, graf_train.main, *flags, arg)
    assert code == 2
    assert err.splitlines() == [err.splitlines()[0], HINT] and err.startswith(f"error: {says}"), err


def test_a_plus_on_a_key_that_exists_says_to_drop_it(monkeypatch, capsys):
    """``+model.lr=0.1`` where model.lr exists was Hydra's 6 lines ("An item is already at 'model.lr'")."""
    code, _, err = _main(monkeypatch, capsys, graf_eval.main, "model=knn_dl", "+model.lr=0.1")
    assert code == 2
    assert err.splitlines() == ["error: +model.lr=0.1: model.lr is already set; drop the '+' (model.lr=0.1)", HINT]


def test_the_console_script_says_it_in_one_line(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0"}
    p = subprocess.run([str(BIN / "graf-eval"), "scene=nowhere"], capture_output=True, text=True, env=env, cwd=tmp_path)
    assert p.returncode == 2 and p.stderr.splitlines()[0].startswith("error: scene=nowhere: no such option"), p.stderr
    assert len(p.stderr.splitlines()) == 2


def test_hydra_full_error_leaves_the_error_to_hydra(monkeypatch):
    monkeypatch.setattr(sys, "argv", ["graf-train", "band=5ghz"])
    monkeypatch.setenv("HYDRA_FULL_ERROR", "1")
    with pytest.raises(MissingConfigException, match="Could not find 'band/5ghz'"):
        graf_train.main()


def _instantiate_error(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("eval", overrides=list(overrides))
    with pytest.raises(Exception) as info:
        hydra.utils.instantiate(cfg.neighbors)
    return info.value, cfg


@pytest.mark.parametrize(
    "override, says",
    [
        ("neighbors.L=abc", "neighbors.L=abc: must be an integer"),
        ("neighbors.L_train=[3,x]", "neighbors.L_train=[3, x]: must be a list of integers"),
        ("neighbors.radius=far", "neighbors.radius=far: must be a number or null"),
    ],
)
def test_a_constructor_refusing_a_value_names_the_setting_and_the_value(override, says):
    """``neighbors.L=abc`` said ``invalid literal for int() with base 10: 'abc'``: which setting?"""
    exc, cfg = _instantiate_error("neighbors=fixed", override)
    assert user_message(exc, cfg) == says
    assert "(in neighbors)" in user_message(exc)  # without the config: the node at least


class Picky:
    """A constructor that refuses a value with its own message, naming the setting."""

    def __init__(self, count: int = 1) -> None:
        if count is None:
            raise ValueError("count=null is filled in by the run; give a number")


def test_a_constructors_own_message_naming_the_setting_stands():
    cfg = OmegaConf.create({"picky": {"_target_": f"{__name__}.Picky", "count": None}})
    with pytest.raises(Exception) as info:
        hydra.utils.instantiate(cfg.picky)
    assert user_message(info.value, cfg) == "count=null is filled in by the run; give a number (in picky)"


@pytest.mark.slow  # moved from the default run to keep it under 5 min on the 2-core machine (issue 68)
def test_a_multirun_prints_one_line_per_failed_job_and_how_many_failed(tmp_path):
    """One job's user error was a 33-line traceback and exit code 1; failed.json keeps the job as before."""
    sweep = tmp_path / "sweep"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0"}
    args = ["-m", "model=knn", "neighbors=fixed", "neighbors.L=abc,4", "logger=none", "plot_count=0"]
    quick = ["data.test_subset=2", "trainer.enable_progress_bar=false", f"hydra.sweep.dir={sweep}"]
    p = subprocess.run([str(BIN / "graf-eval"), *args, *quick], capture_output=True, text=True, env=env, timeout=300)
    lines = [ln for ln in p.stderr.splitlines() if not ln.startswith("[")]  # Hydra's log lines: [time][name]
    assert p.returncode == 2, p.stderr[-3000:]
    job = "job 0 (model=knn neighbors=fixed neighbors.L=abc logger=none plot_count=0 data.test_subset=2"
    assert lines[0].startswith(job) and lines[0].endswith("failed: neighbors.L=abc: must be an integer"), lines
    assert lines[1:] == [f"1 of 2 jobs failed (listed in {sweep / 'failed.json'})"], lines
    assert "Traceback" not in p.stderr
    assert [f["job"] for f in json.loads((sweep / "failed.json").read_text())] == [0]
    assert (sweep / "1" / "results.json").is_file()


def test_the_old_spelling_is_brought_up_to_date_with_a_warning(tmp_path):
    args, warnings = modernize(
        [
            "-m",
            "experiment=neighbour_count",
            "hparams_search=neighbour_count",
            "+model.neighbour_features=ray",
            "model.neighbor_features=ray_knn",
            "data.neighbour_pool=3",
            "seed=neighbour",  # a value of a setting, not of a group: a user's own string
        ]
    )
    assert args == [
        "-m",
        "experiment=neighbor_count",
        "hparams_search=neighbor_count",
        "+model/features=ray",
        "model/features=ray_knn",
        "data.neighbor_pool=3",
        "seed=neighbour",
    ]
    assert warnings == [
        "warning: 'experiment=neighbour_count' is deprecated; write 'experiment=neighbor_count'",
        "warning: 'hparams_search=neighbour_count' is deprecated; write 'hparams_search=neighbor_count'",
        "warning: '+model.neighbour_features=ray' is deprecated; write '+model/features=ray'",
        "warning: 'model.neighbor_features=ray_knn' is deprecated; write 'model/features=ray_knn'",
        "warning: 'data.neighbour_pool=3' is deprecated; write 'data.neighbor_pool=3'",
    ]
    assert RENAMED_KEYS["model.neighbor_features"] == "model/features"
    # a rename to a config group applies once the group exists (here: a config folder without it)
    (tmp_path / "model").mkdir()
    assert modernize(["model.neighbour_features=ray"], conf_dir=tmp_path)[0] == ["model.neighbor_features=ray"]


@pytest.mark.parametrize(
    "old, shown",
    [
        ("experiment=neighbour_count", "task_name: neighbor_count"),
        ("hparams_search=neighbour_count", "task_name: search_neighbor_count"),
        ("model.neighbour_features=ray", "_target_: graf.models.graf.features.RayFeatures"),
        ("model=graf_cpu_scenes_ray", "_target_: graf.models.graf.features.RayWeightsFeatures"),  # renamed preset
        ("model=graf_cpu_ray", "_target_: graf.models.graf.features.RayWeightsFeatures"),
    ],
)
def test_a_command_given_the_old_spelling_runs_the_new_one(monkeypatch, capsys, old, shown):
    model = ("model=graf_cpu",) if "features" in old else ()  # the renamed presets build what they built
    code, out, err = _main(monkeypatch, capsys, graf_train.main, *model, old, "--cfg", "job")
    assert code is None and shown in out, out[-2000:]
    assert err.splitlines()[0].startswith(f"warning: '{old}' is deprecated; write '"), err
