"""A plugin that fails says so in one line (exit code 2) naming the plugin: a module that cannot be imported, a
study axis whose reader raises, a metric whose function raises or returns anything but one value per spectrum
(graf.plugins, docs/extending.md)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from graf.errors import PluginError, is_user_error
from graf.metrics.names import Metric
from graf.metrics.spectrum_metrics import RegisteredMean


def _graf(module: str, *args: str, plugin: str, path: Path) -> subprocess.CompletedProcess:
    env = {
        **os.environ,
        "GRAF_PLUGINS": plugin,
        "PYTHONPATH": os.pathsep.join([str(path), os.environ.get("PYTHONPATH", "")]),
        "OMP_NUM_THREADS": "1",
    }
    env.pop("HYDRA_FULL_ERROR", None)
    return subprocess.run([sys.executable, "-m", module, *args], env=env, capture_output=True, text=True, timeout=300)


def _error_lines(p: subprocess.CompletedProcess) -> list[str]:
    return [ln for ln in p.stderr.splitlines() if ln.strip() and not ln.startswith("[")]


def test_a_plugin_that_cannot_be_imported_is_one_line_with_exit_code_2(tmp_path):
    (tmp_path / "broken_plugin.py").write_text("import no_such_module_of_anyone\n")
    p = _graf("graf.cli.report", "--help", plugin="broken_plugin", path=tmp_path)
    lines = _error_lines(p)
    assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr
    assert lines[0] == (
        "error: GRAF_PLUGINS: plugin module 'broken_plugin' could not be imported: ModuleNotFoundError: "
        "No module named 'no_such_module_of_anyone'"
    ), p.stderr


def test_a_study_axis_whose_reader_raises_is_one_line_naming_it_and_its_plugin(tmp_path):
    (tmp_path / "axis_plugin.py").write_text(
        "from graf.reports.axes import Axis, register\n"
        "register(Axis('boom', of_job=lambda r: r['config']['no_such_setting']))\n"
    )
    job = tmp_path / "runs" / "job0"
    job.mkdir(parents=True)
    (job / "results.json").write_text(json.dumps({"method": "knn", "scene": "s", "config": {}, "metrics": {}}))
    p = _graf(
        "graf.cli.report",
        f"runs={tmp_path / 'runs'}",
        f"hydra.run.dir={tmp_path / 'logs'}",
        plugin="axis_plugin",
        path=tmp_path,
    )
    lines = _error_lines(p)
    assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr
    assert lines[0] == "error: study axis 'boom' (plugin module axis_plugin) failed: KeyError: 'no_such_setting'"


def _fails(pred, target):
    raise ZeroDivisionError("the plugin's own bug")


@pytest.mark.parametrize(
    "fn, says",
    [
        (_fails, f"metric 'mine' (plugin module {__name__}) failed: ZeroDivisionError: the plugin's own bug"),
        (
            lambda p, t: (p - t).abs().mean(dim=(1, 2), keepdim=True),  # [N, 1, 1]: broadcast into NaN before
            f"metric 'mine' (plugin module {__name__}): per_spectrum returned shape [3, 1, 1] for 3 spectra of shape "
            "[3, 90, 360]; it must return a tensor of shape [3], one value per spectrum",
        ),
        (lambda p, t: (p - t).abs().mean(), "per_spectrum returned shape [] for 3 spectra"),  # one for the batch
        (lambda p, t: [0.0] * p.shape[0], "per_spectrum returned a list for 3 spectra"),
    ],
)
def test_a_metric_that_raises_or_returns_another_shape_is_one_line_naming_it(fn, says):
    metric = RegisteredMean(Metric("mine", "mine", "", False, "{:.2f}", per_spectrum=fn))
    pred, target = torch.rand(3, 90, 360), torch.rand(3, 90, 360)
    with pytest.raises(PluginError) as info:
        metric.update(pred, target)
    assert says in str(info.value) and "\n" not in str(info.value) and is_user_error(info.value)


def test_a_metric_of_one_value_per_spectrum_is_averaged_as_before():
    metric = RegisteredMean(Metric("mine", "mine", "", False, "{:.2f}", per_spectrum=lambda p, t: p.mean(dim=(1, 2))))
    pred = torch.full((2, 90, 360), 0.25)
    metric.update(pred, torch.ones(2, 90, 360))
    assert float(metric.compute()) == pytest.approx(0.25)


def test_a_checkpoint_of_a_plugins_method_names_a_class_graf_loads(tmp_path, monkeypatch):
    """graf-eval takes the class from the checkpoint: a plugin's method (its module loaded by GRAF_PLUGINS, or a
    submodule of it) is loaded; a module no plugin loaded is not imported, and a class that is no method is
    refused, each in one line."""
    from graf import plugins
    from graf.models.base import CheckpointError, checkpoint_class

    package = tmp_path / "tiny_plugin_68"
    package.mkdir()
    method = (
        "from graf.models.base import SpectrumModule\nclass Tiny(SpectrumModule):\n    pass\nclass NotOne:\n    pass\n"
    )
    (package / "__init__.py").write_text(method)
    (package / "more.py").write_text(method)
    marker = tmp_path / "imported"
    (tmp_path / "unloaded_68.py").write_text(f"open({str(marker)!r}, 'w').close()\n" + method)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(plugins, "LOADED", [])
    for name in ("tiny_plugin_68", "tiny_plugin_68.more"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    assert plugins.load_plugins("tiny_plugin_68") == ["tiny_plugin_68"]
    assert checkpoint_class("tiny_plugin_68.Tiny", "a.ckpt").__name__ == "Tiny"
    assert checkpoint_class("tiny_plugin_68.more.Tiny", "a.ckpt").__module__ == "tiny_plugin_68.more"  # a submodule
    with pytest.raises(CheckpointError, match=r"a.ckpt: names tiny_plugin_68.NotOne, which is not one of graf's"):
        checkpoint_class("tiny_plugin_68.NotOne", "a.ckpt")
    with pytest.raises(CheckpointError, match=r"tiny_plugin_68.Gone, which this version of graf or of its plugin"):
        checkpoint_class("tiny_plugin_68.Gone", "a.ckpt")
    with pytest.raises(CheckpointError) as info:
        checkpoint_class("unloaded_68.Tiny", "a.ckpt")
    assert "load the plugin that defines it (GRAF_PLUGINS=unloaded_68); not imported" in str(info.value)
    assert "\n" not in str(info.value) and not marker.exists()
    for name in ("tiny_plugin_68", "tiny_plugin_68.more"):
        sys.modules.pop(name, None)
