"""A console worth reading and figures a reader can compare: progress lines instead of redraws when stdout is
not a terminal, the understood third-party warnings filtered in one place, shared colour scales with colour bars."""

from __future__ import annotations

import io
import json
import logging
import subprocess
import sys
import warnings
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from lightning.pytorch.callbacks import TQDMProgressBar

import graf.plotting as plotting
from graf.console import KNOWN_WARNINGS, LineProgress, filter_known_warnings, progress_bar


class _Tiny(L.LightningModule):
    def __init__(self):
        super().__init__()
        self.lin = torch.nn.Linear(1, 1)

    def training_step(self, batch, i):
        loss = self.lin(batch[0]).pow(2).mean()
        self.log("train/loss", loss, prog_bar=True)
        return loss

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.01)


def _fit(callback, steps: int) -> None:
    data = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.ones(64, 1)), batch_size=2)
    trainer = L.Trainer(
        max_steps=steps,
        callbacks=[callback],
        logger=False,
        enable_checkpointing=False,
        enable_model_summary=False,
        accelerator="cpu",
    )
    trainer.fit(_Tiny(), data)


def test_line_progress_prints_a_line_every_n_steps_and_at_the_last():
    out = io.StringIO()
    _fit(LineProgress(every_n_steps=3, stream=out), steps=7)
    lines = out.getvalue().splitlines()
    assert [ln.split()[1] for ln in lines] == ["3/7", "6/7", "7/7"]
    assert all("train/loss" in ln and ln.endswith("steps/s") for ln in lines)
    assert "\r" not in out.getvalue()
    with pytest.raises(ValueError, match="every_n_steps"):
        LineProgress(every_n_steps=0)


def test_line_progress_is_silent_while_disabled_as_lightning_asks_of_a_progress_bar():
    """Lightning disables the bar on every rank but the first and its Tuner re-enables it (ProgressBar's
    disable/enable, which raise NotImplementedError unless a bar defines them)."""
    out = io.StringIO()
    bar = LineProgress(every_n_steps=1, stream=out)
    bar.disable()
    _fit(bar, steps=2)
    assert out.getvalue() == ""
    bar.enable()
    _fit(bar, steps=2)
    assert [ln.split()[1] for ln in out.getvalue().splitlines()] == ["1/2", "2/2"]


def test_the_progress_callback_is_a_bar_on_a_terminal_lines_elsewhere_and_nothing_when_off(monkeypatch):
    assert progress_bar(enabled=False, every_n_steps=5) is None
    assert isinstance(progress_bar(every_n_steps=5), LineProgress)  # pytest's captured stdout: no terminal

    class Tty(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setattr(sys, "stdout", Tty())
    assert isinstance(progress_bar(every_n_steps=5), TQDMProgressBar)


def test_known_third_party_warnings_are_filtered_with_a_reason_and_others_kept():
    assert all(len(reason) > 40 for _, reason in KNOWN_WARNINGS)  # each says why it is understood
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        filter_known_warnings()
        warnings.warn(
            "Your `IterableDataset` has `__len__` defined. In combination with ...", UserWarning, stacklevel=1
        )
        warnings.warn("`isinstance(treespec, LeafSpec)` is deprecated, use ...", FutureWarning, stacklevel=1)
        warnings.warn(
            "neighbors: radius 10.0 wavelengths held fewer than L=4 candidates", UserWarning, stacklevel=1
        )  # graf's own
        warnings.warn("something nobody has looked at", DeprecationWarning, stacklevel=1)
    assert [str(w.message)[:20] for w in seen] == ["neighbors: radius 10", "something nobody has"]


def test_lightnings_tips_are_dropped_and_its_other_messages_kept(caplog):
    filter_known_warnings()
    lg = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    with caplog.at_level(logging.INFO, logger="lightning.pytorch.utilities.rank_zero"):
        lg.info("💡 Tip: For seamless cloud logging and experiment tracking, try installing [litlogger]")
        lg.info("GPU available: False, used: False")
    assert [r.getMessage() for r in caplog.records] == ["GPU available: False, used: False"]


def _captured_figure(monkeypatch, fn):
    figs = []
    monkeypatch.setattr(plotting, "save_figure", lambda fig, path, dpi=80: figs.append(fig) or Path(path))
    fn()
    return figs[0]


def test_true_and_predicted_spectra_share_one_scale_with_a_colour_bar(monkeypatch):
    rng = np.random.default_rng(0)
    target = rng.random((3, 90, 360)) * 0.5  # a target far from the prediction's range
    pred = np.clip(target + 0.3, 0, 1)
    fig = _captured_figure(
        monkeypatch, lambda: plotting.plot_spectra_grid(pred, target, np.arange(3), "unused.png", max_rows=3)
    )
    spectra = [ax.images[0] for ax in fig.axes if ax.images and "error" not in ax.get_title() and ax.get_title()]
    errors = [ax.images[0] for ax in fig.axes if ax.images and "error" in ax.get_title()]
    assert len(spectra) == 6 and len(errors) == 3
    assert {im.get_clim() for im in spectra} == {(0.0, 1.0)}  # true and predicted: one scale, whatever the data
    assert len({im.get_clim() for im in errors}) == 1  # the errors: one scale for the figure
    labels = [ax.get_ylabel() for ax in fig.axes if not ax.get_title()]  # the colour bars' axes
    assert plotting.SPECTRUM_LABEL in labels and "|predicted - true|" in labels


def test_a_studys_matrices_share_one_scale_across_methods(tmp_path, monkeypatch):
    from graf.reports import figures as report_figures

    figs = []
    monkeypatch.setattr(report_figures, "save_figure", lambda fig, path, dpi=80: figs.append(fig) or Path(path))
    rows = [
        {"method": "graf", "steps": "300", "trained_on": "a", "eval_scene": e, "test/psnr": p, "test/ssim": 0.5}
        for e, p in (("a", 20.0), ("b", 18.0))
    ] + [{"method": "knn", "steps": "0", "trained_on": "-", "eval_scene": e, "test/psnr": p} for e, p in (("a", 16.0),)]
    report_figures.matrix_figures(rows, tmp_path)
    psnr = next(f for f in figs if "PSNR" in f._suptitle.get_text())
    clims = {ax.images[0].get_clim() for ax in psnr.axes if ax.images}
    assert clims == {(16.0, 20.0)}  # graf's and knn's cells on the same scale
    assert "one colour scale" in psnr._suptitle.get_text()  # said once, in the title
    assert any("higher is better" in ax.get_ylabel() for ax in psnr.axes)  # the colour bar's unit and direction
    assert json.loads((tmp_path / "matrix.json").read_text())["knn"]["PSNR"]["values"][0][0] == 16.0


@pytest.mark.slow
def test_the_main_jobs_console_fits_on_one_screen(tmp_path):
    """The main job (4 steps here) with stdout to a pipe: progress lines, no redraws, no third-party noise, and
    it ends with its table, the regime line and the paths of its results and figure."""
    exe = str(Path(sys.executable).parent / "graf-train")
    p = subprocess.run(
        [exe, "experiment=graf_rfid_s23", "trainer.max_steps=4", "model.rays_per_step=64", "data.batch_size=2",
         "callbacks.progress_bar.every_n_steps=2", "logger=none", f"hydra.run.dir={tmp_path}"],
        capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr[-3000:]
    console = p.stdout + p.stderr
    lines = console.splitlines()
    assert "\r" not in console and "Tip:" not in console
    assert not any("LeafSpec" in ln or "IterableDataset" in ln for ln in lines)
    assert len(lines) <= 30, console
    assert [ln.split()[1] for ln in lines if ln.startswith("step ")] == ["2/4", "4/4"]
    tail = lines[-5:]
    assert tail[0].startswith("graf-ray-weights") and tail[1].startswith("knn")
    assert tail[2].startswith("regime: sparse")
    assert tail[3] == f"results: {tmp_path / 'results.json'}" and tail[4] == f"figure: {tmp_path / 'spectra.png'}"
