"""The validation layouts (conference_v4, office_v4: ``validation_only`` in their catalog entries): the catalog's
furniture and counts placed anew, the catalog's geometry rule kept, validated on (``test=false``, as graf-curves
runs) and refused as a test scene, in one line, before anything is built."""

from __future__ import annotations

import hydra
import pytest
from hydra import compose, initialize_config_dir

from graf.app.config import CONF_DIR
from graf.app.spec import RunSpec
from graf.cli import train as graf_train
from graf.run.build import check_not_validation_only
from tests.app.test_bad_values import QUICK, _main, _one_line

LAYOUTS = {"conference_v4": "conference_v1", "office_v4": "office_v1"}
WALL_GAP = 0.25  # the catalog's rule (scene_catalog/base/tracing.yaml): furniture at least 0.25 m off the walls


def _scene(name: str):
    with initialize_config_dir(str(CONF_DIR / "scene_catalog"), version_base="1.3"):
        return compose(config_name=name)


@pytest.mark.parametrize("name", LAYOUTS)
def test_a_validation_layout_places_the_catalogs_furniture_anew(name):
    cfg, base = _scene(name), _scene(LAYOUTS[name])
    assert cfg.validation_only is True and not base.get("validation_only")
    objects = {k: v for k, v in cfg.objects.items() if v is not None}
    assert objects.keys() == {k for k, v in base.objects.items() if v is not None}  # the same pieces, all of them
    moved = [k for k in objects if list(objects[k].center) != list(base.objects[k].center)]
    assert len(moved) >= len(objects) // 2  # a new layout, not a copy
    size = cfg.room.size
    for k, o in objects.items():
        for axis in (0, 1):  # off the walls (the floor and ceiling carry furniture)
            lo, hi = o.center[axis] - o.size[axis] / 2, o.center[axis] + o.size[axis] / 2
            assert lo >= WALL_GAP - 1e-9 and hi <= size[axis] - WALL_GAP + 1e-9, (k, axis)
    scene = hydra.utils.instantiate(cfg)
    assert scene.validation_only and "validation_only" not in scene.config()  # it does not shape the dataset
    assert len(scene.positions()) == cfg.transmitters.count == base.transmitters.count


@pytest.mark.parametrize(
    "override", ["eval_scene=conference_v4", "eval_scene=[office_v1,office_v4]", "scene=office_v4"]
)
def test_a_run_that_tests_on_a_validation_layout_is_refused_in_one_line(monkeypatch, capsys, tmp_path, override):
    out = tmp_path / "run"
    code, err = _main(
        monkeypatch, capsys, graf_train.main, "model=knn", "scene=conference_v1", override, *QUICK,
        f"hydra.run.dir={out}",
    )  # fmt: skip
    assert code == 2, err
    line = _one_line(err)
    assert "is a validation layout" in line and "test=false" in line
    assert not (out / "results.json").exists()


def test_validating_on_a_validation_layout_is_allowed(compose_cfg):
    cfg = compose_cfg("train", ("scene=conference_v1", "eval_scene=[conference_v4,office_v4]", "test=false"))
    check_not_validation_only(cfg, RunSpec.of(cfg).eval_scenes)  # no refusal
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        regime = compose(config_name="curves").regimes.cross_family_val
    assert "eval_scene=[conference_v4,office_v4]" in regime.overrides and regime.max_steps >= 10_000
