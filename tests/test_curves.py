"""graf-curves (issue 22, point 4): one resumable trajectory per method, validated at each step, never tested."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest


@pytest.mark.slow  # 75 s on the 2-core CI machine: the default run must stay under 15 min
def test_curves_run_resume_and_validate_only(tmp_path, make_scene):
    folder = make_scene(n=24)
    out = tmp_path / "curves"
    q = lambda *o: "[" + ",".join(f"'{x}'" for x in o) + "]"  # noqa: E731  (a Hydra list of overrides)
    regime = q("scene=nerf2", f"scene.nerf2.path={folder}", "band=2.4ghz", "data.batch_size=2", "data.val_fraction=0.2",
               "trainer.limit_test_batches=1")
    small = ("model.rays_per_step=32", "model.max_samples=4", "model.encoder_widths=[4,8,8,8]")
    args = [sys.executable, "-m", "graf.cli.curves", f"out={out}", "threads=1", "steps=[1,2]",
            f"+regimes={{tiny: {{max_steps: 3, overrides: {regime}}}}}", "only_regimes=[tiny]",
            f"methods.pooled.overrides={q('model=graf_cpu', *small)}",
            f"methods.ray_knn.overrides={q('model=graf_cpu', 'model.neighbour_features=ray_knn', *small)}",
            "only_methods=[pooled,ray_knn]", f"hydra.run.dir={tmp_path / 'h'}"]
    p = subprocess.run([*args, "until=2"], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    res = json.loads((out / "results.json").read_text())
    assert [(r["method"], r["step"]) for r in res["rows"]] == [("pooled", 1), ("pooled", 2), ("ray_knn", 1), ("ray_knn", 2)]
    assert all(r["val_psnr"] is not None and r["val_reliance_db"] is not None for r in res["rows"])
    assert res["knn"]["tiny"]["val/psnr"] is not None and not res["failed"]
    step2 = json.loads((out / "tiny" / "ray_knn" / "step_2" / "results.json").read_text())
    assert step2["resumed"]["global_step"] == 1 and step2["training"]["steps_trained"] == 1  # one trajectory
    assert step2["metrics"]["test/psnr"] is None  # never tested
    first = (out / "tiny" / "pooled" / "step_1" / "results.json").stat().st_mtime
    p = subprocess.run(args, capture_output=True, text=True, timeout=600)  # again, to the budget: resumes
    assert p.returncode == 0, p.stderr[-3000:]
    assert (out / "tiny" / "pooled" / "step_1" / "results.json").stat().st_mtime == first  # not run again
    res = json.loads((out / "results.json").read_text())
    assert [r["step"] for r in res["rows"] if r["method"] == "pooled"] == [1, 2, 3]
    assert (out / "curves.png").is_file() and "knn (line)" in (out / "curves.md").read_text()
    assert sorted(p.parent.parent.name for p in (out / "tiny" / "pooled").rglob("last.ckpt")) == ["step_3"]
    # a run of a subset (one method, an earlier until) trains nothing and keeps every other published row
    subset = [a for a in args if not a.startswith("only_methods=")] + ["only_methods=[pooled]", "until=1"]
    p = subprocess.run(subset, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    again = json.loads((out / "results.json").read_text())
    assert again["rows"] == res["rows"] and "| ray_knn | 3 |" in (out / "curves.md").read_text()
