"""The worked examples of docs/extending.md: a metric, a study axis and methods added by a plugin
(tests/plugins/toy_plugin.py) through graf's interface only, and seen to reach results.json, the per-spectrum
records, graf-report's tables, its intervals and a figure; a trained plugin method round-trips (trained,
checkpointed, read back by graf-eval, benchmarked by graf-bench), and an installed plugin is found by its entry
point."""

from __future__ import annotations

import csv
import gzip
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PLUGINS = ROOT / "tests" / "plugins"


def _run(module: str, *args: str, env: dict) -> subprocess.CompletedProcess:
    return _run_args(["-m", module, *args], env=env)


def _run_code(code: str, *args: str) -> subprocess.CompletedProcess:
    return _run_args(["-c", code, *args], env=_plugin_env())


def _run_args(args: list[str], env: dict) -> subprocess.CompletedProcess:
    p = subprocess.run([sys.executable, *args], env=env, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    return p


def _plugin_env(**extra: str) -> dict:
    return {
        **os.environ,
        "GRAF_PLUGINS": "toy_plugin",
        "PYTHONPATH": os.pathsep.join([str(PLUGINS), os.environ.get("PYTHONPATH", "")]),
        "OMP_NUM_THREADS": "1",
        **extra,
    }


@pytest.fixture(scope="module")
def study(tmp_path_factory) -> Path:
    """Four jobs of the toy method (L 2 and 4, two search radii), KNN tested beside each, and their report."""
    sweep = tmp_path_factory.mktemp("extending") / "study"
    env = _plugin_env()
    _run(
        "graf.cli.train",
        "-m",
        "model=neighbor_mean",  # found in the plugin's own conf folder (toy_plugin: add_conf)
        "neighbors.L=2,4",
        "neighbors.radius=5.0,10.0",
        "data.test_subset=8",
        "logger=none",
        "plot_count=0",
        "trainer.enable_progress_bar=false",
        f"hydra.sweep.dir={sweep}",
        env=env,
    )
    _run("graf.cli.report", f"runs={sweep}", f"hydra.run.dir={sweep}/report_logs", env=env)
    return sweep


@pytest.mark.slow  # moved from the default run to keep it under 5 min on the 2-core machine (issue 68)
def test_a_registered_metric_reaches_the_records_the_report_and_a_figure(study):
    jobs = sorted(study.glob("*/results.json"))
    assert len(jobs) == 4
    result = json.loads(jobs[0].read_text())
    assert result["method"] == "neighbor-mean"  # the method's default name, from its class
    assert "test/peak_error" in result["metrics"] and "test/peak_error" in result["baselines"]["knn"]["metrics"]
    with gzip.open(jobs[0].parent / result["per_spectrum"], "rt") as f:
        rows = list(csv.DictReader(f))
    assert {r["method"] for r in rows} == {"neighbor-mean", "knn"} and all(float(r["peak_error"]) >= 0 for r in rows)
    table = (study / "report.md").read_text()
    assert "peak error" in table
    header = (study / "table.md").read_text().splitlines()[0]  # graf-table's (the sweep's callback): the registry's
    assert "| peak error |" in header and header.index("LPIPS") < header.index("peak error")
    intervals = json.loads((study / "intervals.json").read_text())["rows"]
    paired = [r for r in intervals if r["metric"] == "peak_error" and r["method"] == "neighbor-mean"]
    assert paired and all(r["vs_knn"]["n_spectra"] == 8 for r in paired)  # paired with KNN over the same spectra
    report = json.loads((study / "report.json").read_text())
    assert "vs_L.png" in report["figures"] and "peak error" in report["vs_L"]["neighbor-mean"]["2"]  # a panel of it


@pytest.mark.slow  # moved from the default run to keep it under 5 min on the 2-core machine (issue 68)
def test_a_registered_axis_splits_the_tables_and_the_intervals_cells(study):
    table = (study / "report.md").read_text()
    assert "radius" in table
    rows = json.loads((study / "intervals.json").read_text())["rows"]
    assert {r["radius"] for r in rows} == {"5.0", "10.0"}  # one cell per value, each paired on its own
    assert json.loads((study / "report.json").read_text())["axes"] == ["L", "radius"]


@pytest.mark.slow  # moved from the default run to keep it under 5 min on the 2-core machine (issue 68)
def test_a_method_of_a_plugin_runs_through_the_configs_and_reaches_the_report(study):
    rows = json.loads((study / "rows.json").read_text())["rows"]
    assert {r["method"] for r in rows} == {"neighbor-mean", "knn"}
    mean = [r for r in rows if r["method"] == "neighbor-mean"]
    assert len(mean) == 4 and all(r["steps"] == "0" for r in mean)  # nothing to train: tested only


def test_every_method_of_the_platform_is_a_method():
    from graf.models.base import Method
    from graf.models.graf import GRaFModule
    from graf.models.knn import KNNModule
    from graf.models.knn_dl import KNNDLModule
    from graf.models.nerf2 import NeRF2Module

    for model in (
        GRaFModule(d_model=8),
        KNNModule(),
        KNNDLModule(max_rank=4),
        NeRF2Module(depth=2, width=16, skips=[]),
    ):
        assert isinstance(model, Method), type(model).__name__
        assert model.method and isinstance(model.INFERENCE_SETTINGS, tuple)
    assert (
        KNNModule().has_trainable_parameters is False
        and NeRF2Module(depth=2, width=16, skips=[]).uses_neighbors is False
    )


CURVES_WITH_A_PLUGIN_METRIC = """
import json, sys
from pathlib import Path
from omegaconf import OmegaConf
from graf.studies.curves import collect
from graf.studies.curves_outputs import write_outputs

out = Path(sys.argv[1])
figures = {"val/psnr": 20.0, "val/ssim": 0.5, "val/lpips": 0.3, "val/reliance_db": 1.0, "val/peak_error": 12.5}
for folder, m in (("r/knn", figures), ("r/toy/step_10", {**figures, "val/peak_error": 7.25})):
    (out / folder).mkdir(parents=True)
    (out / folder / "results.json").write_text(json.dumps({"global_step": 10, "metrics": m}))
cfg = OmegaConf.create({"regimes": {"r": {"max_steps": 10}}, "methods": {"toy": {}}, "steps": [10]})
rows, knn = collect(out, cfg)
write_outputs(out, rows, knn, [])
if len(sys.argv) > 2:  # the site's hooks too (docs_hooks/: they import one another by name; they need mkdocs)
    sys.path.insert(0, sys.argv[2])
    import curve_facts as facts
    from hooks import _figures

    facts.CURVES = out
    print(json.dumps({"block": facts.block("r"), "search": _figures({"test/peak_error": 3.0, "test/psnr": 20.0})}))
"""


def test_a_registered_metric_reaches_the_curves(tmp_path):
    """graf-curves' table, csv and figure read the registry: a plugin's metric is in each, with its label and number
    format."""
    _run_code(CURVES_WITH_A_PLUGIN_METRIC, str(tmp_path))
    assert "val_peak_error" in (tmp_path / "curves.csv").read_text().splitlines()[0]
    assert (
        "| val peak error |" in (tmp_path / "curves.md").read_text()
        and "| 7.2 |" in (tmp_path / "curves.md").read_text()
    )
    assert (tmp_path / "curves.png").is_file()


def test_a_registered_metric_reaches_the_sites_tables(tmp_path):
    """The site's curve facts and its search tables read the registry: a plugin's metric is in each, with its label,
    unit and number format (the site's hooks need mkdocs, installed by the docs extra that CI installs)."""
    pytest.importorskip("mkdocs")
    p = _run_code(CURVES_WITH_A_PLUGIN_METRIC, str(tmp_path), str(ROOT / "docs_hooks"))
    seen = json.loads(p.stdout.splitlines()[-1])
    assert "peak error 12.5 deg" in seen["block"] and "| 7.2 |" in seen["block"]  # KNN's line, the point's figure
    assert seen["search"][:5] == ["20.00", "-", "-", "3.0", "-"]  # PSNR, SSIM, LPIPS, peak error, reliance


def test_a_registration_too_late_to_reach_every_reader_is_refused():
    """Registered after the reports were imported, a metric or an axis would be silently left out of them."""
    import graf.reports.rows  # noqa: F401  (a reader of both registries)
    from graf.metrics.names import Metric, register
    from graf.reports.axes import Axis
    from graf.reports.axes import register as register_axis

    with pytest.raises(ValueError, match="register it in a plugin"):
        register(Metric("late", "late", "", True, "{:.1f}", per_spectrum=lambda p, t: p.mean(dim=(1, 2))))
    with pytest.raises(ValueError, match="register it in a plugin"):
        register_axis(Axis("late", of_job=lambda r: 0))


@pytest.mark.slow  # about 40 s: four commands in subprocesses
def test_a_plugin_method_trains_checkpoints_and_is_read_back_by_graf_eval_and_graf_bench(tmp_path):
    env = _plugin_env()
    common = ["data.test_subset=4", "logger=none", "plot_count=0", "trainer.enable_progress_bar=false"]
    _run("graf.cli.train", "model=neighbor_gain", "trainer.max_steps=5", *common, f"hydra.run.dir={tmp_path / 'train'}",
         env=env)  # fmt: skip
    trained = json.loads((tmp_path / "train" / "results.json").read_text())
    ckpt = tmp_path / "train" / "checkpoints" / "last.ckpt"
    assert trained["method"] == "neighbor-gain" and trained["global_step"] == 5 and ckpt.is_file()
    _run("graf.cli.evaluate", f"ckpt_path={ckpt}", *common[:3], f"hydra.run.dir={tmp_path / 'eval'}", env=env)
    evaluated = json.loads((tmp_path / "eval" / "results.json").read_text())
    assert evaluated["method"] == "neighbor-gain"
    assert evaluated["metrics"]["test/psnr"] == pytest.approx(trained["metrics"]["test/psnr"], abs=1e-6)  # its weights
    refused = subprocess.run(
        [sys.executable, "-m", "graf.cli.evaluate", f"ckpt_path={ckpt}", "model.lr=0.1", *common[:3],
         f"hydra.run.dir={tmp_path / 'eval2'}"], env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert refused.returncode == 2 and "cannot change the trained checkpoint" in refused.stderr  # its config found
    _run("graf.cli.studies.bench", "+model@models.gain=neighbor_gain", "bench.models=[gain,knn]", "bench.scenes=[real]",
         "quick=true", "threads=1", f"hydra.run.dir={tmp_path / 'bench'}", env=env)  # fmt: skip
    rows = json.loads((tmp_path / "bench" / "results.json").read_text())["rows"]
    gain = next(r for r in rows if r["method"] == "neighbor-gain")
    assert gain["trainable_parameters"] == 1 and gain["train_s_per_step"] > 0 and gain["samples_per_ray"] is None


def test_an_installed_plugin_is_found_by_its_entry_point(tmp_path):
    """Installed the way pip installs it (its distribution's metadata on the path, with the entry point of
    tests/plugins/pyproject.toml), the toy plugin is imported with graf, its conf folder registered, and no
    GRAF_PLUGINS set."""
    dist = tmp_path / "graf_toy_plugin-0.1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: graf-toy-plugin\nVersion: 0.1.0\n")
    (dist / "entry_points.txt").write_text("[graf.plugins]\ntoy = toy_plugin\n")
    env = {k: v for k, v in _plugin_env().items() if k != "GRAF_PLUGINS"}
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), env["PYTHONPATH"]])
    code = "import graf.plugins as p; print(p.LOADED, [d.name for d in p.CONF_DIRS])"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "['toy_plugin'] ['conf']"
