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
