"""A run is read once: :class:`graf.app.spec.RunSpec` is the one reader of a config's scene selections, and the run
functions take its fields."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from graf.app.spec import RunSpec
from graf.errors import ConfigError

SRC = Path(__file__).resolve().parents[2] / "src" / "graf"
# a config's scene selection read directly: cfg.get("scene"), cfg["eval_scene"], cfg.scene
READS_SELECTION = re.compile(r"\bcfg(\.get\(\"(eval_)?scene\"|\[\"(eval_)?scene\"\]|\.(eval_)?scene\b)")


def test_only_the_spec_reads_a_configs_scene_selection():
    readers = sorted(
        f"{p.relative_to(SRC)}:{i}"
        for p in SRC.rglob("*.py")
        if p.name != "spec.py"
        for i, line in enumerate(p.read_text().splitlines(), 1)
        if READS_SELECTION.search(line) or "_scene_selection(" in line
    )
    assert readers == []


def test_a_spec_names_the_scenes_trained_and_tested_on(compose_cfg):
    spec = RunSpec.of(
        compose_cfg("train", ("scene=[conference_v1,office_v1]", "eval_scene=[conference_v2]", "trainer.max_steps=7"))
    )
    assert spec.scene_names == ["conference_v1", "office_v1"]
    assert spec.eval_scene_names == ["conference_v2"] and spec.tested_scenes == spec.eval_scenes
    assert spec.steps == 7 and spec.eval_band is None
    with pytest.raises(
        ConfigError, match=r"graf-simulate works on one scene; scene= selects 2 \(conference_v1, office_v1\)"
    ):
        spec.one_scene("graf-simulate")
    within = RunSpec.of(compose_cfg("train", ("scene=conference_v1",)))
    assert within.eval_scenes == () and within.tested_scenes == within.scenes
    assert within.one_scene("graf-simulate").name == "conference_v1"


def test_eval_scene_validation_reads_the_validation_layouts_of_the_training_families(compose_cfg):
    """``eval_scene=validation``: the families' validation layouts alone (the layouts ``heldout`` never tests), so
    a run that chooses something validates zero-shot on layouts no study tests on; a scene with none validates
    within-scene."""
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from graf.app.config import CONF_DIR
    from graf.app.spec import expand_heldout, heldout_scenes

    assert heldout_scenes(["conference_v1"], "validation") == ["conference_v4"]
    assert heldout_scenes(["conference_v1", "office_v2"], "validation") == ["conference_v4", "office_v4"]
    assert heldout_scenes(["rfid_s23"], "validation") == []
    assert "conference_v4" not in heldout_scenes(["conference_v1"], "auto")
    office = compose_cfg("train", ("scene=office_v1", "eval_scene=validation", "test=false"))
    rfid = compose_cfg("train", ("scene=rfid_s23", "eval_scene=validation"))
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):  # as a command's run is
        assert RunSpec.of(expand_heldout(office)).eval_scene_names == ["office_v4"]
        assert expand_heldout(rfid).eval_scene is None
