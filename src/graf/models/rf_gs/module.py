"""RF Gaussian splatting as a per-scene method: SwiftWRF's form (deformable 2-D Gaussians on the spectrum image),
rendered by the separable rasterizer of :mod:`.rasterizer` on any device.

A prediction for the transmitter at ``tgt_pos``: its position in the scene's normalised frame goes through the
deformation MLP of :class:`.gaussians.GaussianField`, which moves, widens and re-weights the N base Gaussians;
:func:`.rasterizer.render` sums them on the 90 x 360 grid.  Neighbor spectra are not read, unless ``base`` is
``knn``: then the Gaussians are a correction added to KNN's prediction (``model=rf_gs_knn``).  Training renders the
batch's whole spectra (``data.batch_size`` targets a step; no ray sampling: a spectrum costs one matrix product)
and minimises their MSE, the metric PSNR is computed from.  The raw sum is trained, unbounded (a Gaussian's
amplitude is signed); :meth:`RFGSModule.predict_spectra` clamps it to [0, 1], as every method's evaluation does.

**Densify and prune** (``densify_every`` > 0; 3D Gaussian splatting's rule, ranked rather than thresholded, since
the gradients' scale depends on the loss and the batch): the module sums, every step, the norm of the gradient of
each Gaussian's base mean and its ``|amplitude|`` averaged over the batch.  Every ``densify_every`` steps during the
first ``densify_until`` of the learning-rate schedule (``decay_steps``, by default the run's ``max_steps``; a
trajectory resumed point by point, as graf-curves runs it, keeps one schedule and so one densification period): a
Gaussian whose mean ``|amplitude|`` since the last plan is below ``prune_amplitude`` is removed, and the
``densify_fraction`` of the count with the largest mean gradient is split in two (:func:`.gaussians.split_rows`), up
to ``max_gaussians`` in all.  The optimiser's moments follow the rows (children take their parent's).

**Checkpoints** hold the Gaussians as trained, however many: a state dict of another count resizes the field
before it loads (a load pre-hook, so Lightning's ``load_from_checkpoint``, a resume and ``finetune.init_from``
alike), and the loaded model predicts as the saved one did.

**Memory**: a Gaussian count (``num_gaussians``; ``max_gaussians`` when densification may reach it) whose memory
(:func:`.gaussians.gaussian_bytes`: the parameter rows with gradients and Adam's moments, and ``chunk_spectra``
spectra's profiles) is more than the machine has free is refused in one line naming the setting, the count and the
estimate, before anything is allocated; on a GPU, against its free memory when training starts (:meth:`setup`).

**Per scene** (``per_scene = True``): one scene's field in that scene's frame; :func:`graf.run.build.build`
refuses, in one line, a run that trains it on several scenes or tests it on a scene it was not trained on.
"""

from __future__ import annotations

import math

import psutil
import torch
import torch.nn.functional as F

from graf.config_home import defaults_from
from graf.geometry.encoding import normalize_positions
from graf.models.base import SpectrumModule
from graf.models.knn.weights import idw_weights
from graf.models.rf_gs.gaussians import GaussianField, check_gaussian_memory, split_plan, split_rows
from graf.models.rf_gs.rasterizer import SIGMA_LIMIT, render
from graf.models.schedule import check_rates, exponential_record, run_steps, schedule_length

BASES = ("none", "knn")  # what the Gaussians are added to: nothing, or KNN's prediction (a correction of KNN)


def check_settings(s: dict) -> None:
    """Refuse, in one line naming the setting, a value the module cannot use."""
    check_rates(s["lr"], s["lr_decay"])
    counts = ("num_gaussians", "max_gaussians", "depth", "width", "chunk_spectra")
    for key in counts:
        if not (isinstance(s[key], int) and s[key] >= 1):
            raise ValueError(f"model.{key}={s[key]!r}: must be an integer >= 1")
    if s["max_gaussians"] < s["num_gaussians"]:
        raise ValueError(f"model.max_gaussians={s['max_gaussians']}: must be >= model.num_gaussians")
    if s["base"] not in BASES:
        raise ValueError(f"model.base={s['base']!r}: must be one of {BASES}")
    if not (isinstance(s["pe_freqs"], int) and s["pe_freqs"] >= 0):
        raise ValueError(f"model.pe_freqs={s['pe_freqs']!r}: must be an integer >= 0")
    if s["decay_steps"] is not None and not (isinstance(s["decay_steps"], int) and s["decay_steps"] >= 1):
        raise ValueError(f"model.decay_steps={s['decay_steps']!r}: must be null or an integer >= 1")
    if not (isinstance(s["densify_every"], int) and s["densify_every"] >= 0):
        raise ValueError(f"model.densify_every={s['densify_every']!r}: must be an integer >= 0 (0: never)")
    ranges = {  # (low, high, low inclusive)
        "lr_means": (0.0, math.inf, False),
        "sigma_min": (0.0, SIGMA_LIMIT, False),
        "sigma_max": (0.0, SIGMA_LIMIT, False),
        "init_sigma": (0.0, SIGMA_LIMIT, False),
        "max_shift": (0.0, 180.0, True),
        "head_init": (0.0, math.inf, True),
        "init_amplitude": (-math.inf, math.inf, True),
        "densify_until": (0.0, 1.0, True),
        "densify_fraction": (0.0, 1.0, True),
        "prune_amplitude": (0.0, math.inf, True),
    }
    for key, (lo, hi, closed) in ranges.items():
        v = s[key]
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v <= hi
        if not (ok and (v >= lo if closed else v > lo)):
            raise ValueError(f"model.{key}={v!r}: must be a finite number in {'[' if closed else '('}{lo}, {hi}]")
    if not (s["sigma_min"] < s["sigma_max"] <= SIGMA_LIMIT and s["sigma_min"] <= s["init_sigma"] <= s["sigma_max"]):
        raise ValueError(
            f"model.sigma_min / init_sigma / sigma_max = {s['sigma_min']} / {s['init_sigma']} / {s['sigma_max']}: "
            f"must satisfy sigma_min <= init_sigma <= sigma_max <= {SIGMA_LIMIT:g} deg and sigma_min < sigma_max"
        )
    check_memory(s, psutil.virtual_memory().available, "this machine")


def check_memory(s: dict, available: int, where: str) -> None:
    """Refuse a Gaussian count the memory ``where`` has free cannot hold (:func:`.gaussians.check_gaussian_memory`),
    before it is allocated: ``num_gaussians``, and ``max_gaussians`` where densification may reach it."""
    for key in ("num_gaussians", "max_gaussians") if s["densify_every"] else ("num_gaussians",):
        check_gaussian_memory(key, s[key], s["width"], s["chunk_spectra"], available, where)


def follow_rows(optimizer: torch.optim.Optimizer, moved: dict, index: torch.Tensor) -> None:
    """Point ``optimizer`` at the new per-Gaussian parameters (``moved``: old -> new) and carry Adam's moments
    along the rows ``index`` (each new row takes the moments of the row it was made from)."""
    for group in optimizer.param_groups:
        group["params"] = [moved.get(p, p) for p in group["params"]]
    for old, new in moved.items():
        state = optimizer.state.pop(old, None)
        if state is None:
            continue
        for key in ("exp_avg", "exp_avg_sq"):
            if key in state:
                state[key] = state[key][index]
        optimizer.state[new] = state


@defaults_from("model/rf_gs.yaml")
class RFGSModule(SpectrumModule):
    """RF Gaussian splatting (SwiftWRF's deformable 2-D Gaussians), a per-scene method: N Gaussians on the
    spectrum grid, moved, widened and re-weighted by an MLP of the transmitter position, summed by a separable
    rasterizer (one matrix product per spectrum); trained on one scene, it reads no neighbors and refuses a test on
    another scene.

    Args (their defaults in ``conf/model/rf_gs.yaml``, the one place they are stated: :mod:`graf.config_home`):
        num_gaussians: Gaussians of a fresh model.  max_gaussians: the most densification may reach.
        depth / width / pe_freqs: the deformation MLP (ReLU layers) and its encoding of the normalised transmitter
            position (frequencies ``2^k pi``, k < pe_freqs, and the raw input).
        init_sigma / init_amplitude: widths (deg) and amplitude of the fresh Gaussians.
        sigma_min / sigma_max: the widths' bounds (deg; sigma_max at most 60).
        max_shift: the largest offset (deg) the MLP gives a mean, per axis (``max_shift tanh(.)``).
        head_init: standard deviation of the MLP head's initial weights (small: every transmitter starts near the
            base Gaussians).
        lr: Adam learning rate of widths, amplitudes and the MLP.  lr_means: of the means (deg per step, roughly).
        lr_decay / decay_steps: both rates fall by lr_decay over decay_steps optimiser steps (null: the run's).
        densify_every / densify_until / densify_fraction / prune_amplitude: densification and pruning (module
            docstring); densify_every 0: never.
        chunk_spectra: spectra rendered at once at inference (bounds memory).
        base: ``none`` (the Gaussians are the spectrum) or ``knn`` (they are added to KNN's prediction, the
            inverse-distance mean of the neighbors' spectra, power 1 as ``model=knn``: RF-GS as a per-scene
            correction of KNN, ``model=rf_gs_knn``).
    """

    INFERENCE_SETTINGS = ("chunk_spectra",)
    uses_neighbors = False  # one scene's field: no neighbor is read, so no reliance to measure
    per_scene = True  # trained on one scene, tested only there (graf.run.build refuses anything else)

    def __init__(
        self,
        *,
        num_gaussians: int,
        max_gaussians: int,
        depth: int,
        width: int,
        pe_freqs: int,
        init_sigma: float,
        init_amplitude: float,
        sigma_min: float,
        sigma_max: float,
        max_shift: float,
        head_init: float,
        lr: float,
        lr_means: float,
        lr_decay: float,
        decay_steps: int | None,
        densify_every: int,
        densify_until: float,
        densify_fraction: float,
        prune_amplitude: float,
        chunk_spectra: int,
        base: str,
    ):
        super().__init__()
        check_settings(dict(locals()))
        self.save_hyperparameters()
        self.base = str(base)
        self.uses_neighbors = self.base == "knn"  # a correction of KNN reads the neighbors (its test measures reliance)
        self.lr, self.lr_means, self.lr_decay = float(lr), float(lr_means), float(lr_decay)
        self.decay_steps = None if decay_steps is None else int(decay_steps)
        self.max_gaussians, self.chunk_spectra = int(max_gaussians), int(chunk_spectra)
        self.densify_every, self.densify_until = int(densify_every), float(densify_until)
        self.densify_fraction, self.prune_amplitude = float(densify_fraction), float(prune_amplitude)
        sizes = (num_gaussians, depth, width, pe_freqs)
        self.field = GaussianField(*sizes, init_sigma, init_amplitude, sigma_min, sigma_max, max_shift, head_init)
        self.stats: dict | None = None  # densification statistics since the last plan
        self.densify_stop = 0.0  # the last step that densifies (configure_optimizers)

    @property
    def method(self) -> str:
        return "rf-gs" if self.base == "none" else f"rf-gs-{self.base}"

    def setup(self, stage: str) -> None:
        """On an accelerator that says how much memory it has free (a GPU), refuse a Gaussian count it cannot hold
        (:func:`check_memory`), before the Gaussians are moved there (the machine's memory was checked when the
        module was made)."""
        device = self.trainer.strategy.root_device if getattr(self, "_trainer", None) is not None else None
        free = getattr(torch.get_device_module(device), "mem_get_info", None) if device is not None else None
        if free is not None and device.type != "cpu":
            check_memory(dict(self.hparams), free(device)[0], f"{device.type} device {device}")

    # ------------------------------------------------------------------ rendering
    def gaussians(self, batch: dict) -> dict[str, torch.Tensor]:
        """The deformed Gaussians ``[B, N]`` of the batch's targets (their positions in their scene's frame)."""
        return self.field(normalize_positions(batch["tgt_pos"].float(), batch["bounds"].float()))

    def render(self, batch: dict) -> torch.Tensor:
        """Raw spectra ``[B, 90, 360]`` (float32, unbounded) of the batch's targets."""
        return self.compose(batch, self.gaussians(batch))

    def compose(self, batch: dict, g: dict[str, torch.Tensor]) -> torch.Tensor:
        """The Gaussians ``g`` rendered, added to KNN's prediction when ``base`` is ``knn``."""
        out = render(g["elevation"], g["azimuth"], g["sigma_el"], g["sigma_az"], g["amplitude"])
        if self.base == "knn":
            w = idw_weights(batch["tgt_pos"], batch["src_pos"], batch["src_mask"], power=1.0)
            out = out + torch.einsum("bl,blhw->bhw", w.float(), batch["src_spectra"].float())
        return out

    def predict_spectra(self, batch: dict) -> torch.Tensor:
        B = batch["tgt_pos"].shape[0]
        parts = []
        for i in range(0, B, self.chunk_spectra):
            keys = ("tgt_pos", "bounds") + (("src_pos", "src_mask", "src_spectra") if self.base == "knn" else ())
            part = {k: batch[k][i : i + self.chunk_spectra] for k in keys}
            parts.append(self.render(part).clamp(0.0, 1.0))
        return torch.cat(parts)

    # ------------------------------------------------------------------ training
    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        B = batch["tgt_pos"].shape[0]
        g = self.gaussians(batch)
        pred = self.compose(batch, g)
        loss = F.mse_loss(pred, batch["tgt_spectrum"].float())
        if self.densify_every:
            self.gather_stat("magnitude", g["amplitude"].detach().abs().mean(0))
        self.log("train/loss", loss, prog_bar=True, batch_size=B)
        self.log("train/gaussians", float(self.field.count), batch_size=B)
        return loss

    def gather_stat(self, key: str, value: torch.Tensor) -> None:
        n = self.field.count
        if self.stats is None or self.stats["score"].shape[0] != n:
            zeros = torch.zeros(n, device=value.device)
            self.stats = {"score": zeros, "magnitude": zeros.clone(), "steps": 0}
        self.stats[key] += value
        self.stats["steps"] += key == "score"

    def on_after_backward(self) -> None:
        f = self.field
        if self.densify_every and f.elevation.grad is not None and f.azimuth.grad is not None:
            self.gather_stat("score", torch.sqrt(f.elevation.grad.square() + f.azimuth.grad.square()).detach())

    def on_train_batch_end(self, outputs, batch, batch_idx: int) -> None:
        step = int(self.global_step)
        if self.densify_every and step % self.densify_every == 0 and step <= self.densify_stop:
            self.densify_and_prune()

    def densify_and_prune(self, optimizer: torch.optim.Optimizer | None = None) -> int:
        """Prune and split as the module docstring says, carrying the optimiser's moments along; returns the new
        Gaussian count.  ``optimizer``: the module's own (Lightning's) when None and a trainer is attached."""
        if self.stats is None or not self.stats["steps"]:
            return self.field.count
        steps = self.stats["steps"]
        score, magnitude = self.stats["score"] / steps, self.stats["magnitude"] / steps
        keep, split = split_plan(score, magnitude, self.densify_fraction, self.prune_amplitude, self.max_gaussians)
        if optimizer is None and getattr(self, "_trainer", None) is not None:
            optimizer = self.optimizers(use_pl_optimizer=False)
        index, moved = split_rows(self.field, keep.to(score.device), split.to(score.device))
        if optimizer is not None:
            follow_rows(optimizer, moved, index)
        self.stats = None
        return self.field.count

    def configure_optimizers(self):
        f = self.field
        means = [f.elevation, f.azimuth]
        rest = [p for p in self.parameters() if all(p is not m for m in means)]
        opt = torch.optim.Adam([{"params": means, "lr": self.lr_means}, {"params": rest, "lr": self.lr}])
        length = schedule_length(self, self.decay_steps, "decay_steps")
        self.densify_stop = self.densify_until * length  # of the schedule: a resumed trajectory (graf-curves) keeps it
        self.schedule_record = exponential_record(self.lr, self.lr_decay, length, run_steps(self))
        sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=self.lr_decay ** (1.0 / length))
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step", "frequency": 1}}
