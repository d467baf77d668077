"""NeRF2 (Zhao et al., MobiCom 2023) as a per-scene baseline: a radiance field of the scene queried along
each spectrum ray, with no neighbor spectra (the batch's ``src_*`` entries are ignored).

Each pixel ``p = r * 360 + c`` is a ray from the gateway (directions of :mod:`graf.geometry.grid`, rotated
by ``gw_rot``).  S samples along it (:func:`.renderer.sample_distances`) go through :class:`.NeRF2Network`
with the ray's world direction and the target transmitter's position, and :func:`.renderer.render_rays`
turns them into the ray's amplitude.

Choices (where this module is not NeRF2's code verbatim):

* **Ray extent from the scene and band.**  NeRF2 hard-codes near 0, far 5 m and 64 samples for its RFID
  scene (whose tags lie 4.96-5.49 m from the gateway: its rays stop short of 95% of them).  Here
  ``near`` is a setting (default 0, NeRF2's), ``far`` is the batch's ``ray_length`` (the scene box's
  farthest corner from the gateway: 5.56 m on rfid_s23), and
  ``S = min(max_samples, ceil((far - near) / (sample_spacing * wavelength)))`` (:func:`rays.num_samples`).
  ``sample_spacing`` 0.25 wavelengths is NeRF2's own spacing on RFID (5 m / 63 steps = 7.9 cm, 0.24 lambda
  at 915 MHz), and ``max_samples`` 64 is NeRF2's count, so rfid_s23 gets NeRF2's 64 samples and a
  scene smaller than 64 quarter wavelengths gets fewer.
* **Raw coordinates in metres**, as NeRF2: the encoding's frequencies then keep a physical scale (finest
  period 2 pi / 512 m = 1.2 cm in every scene), which a per-scene normalisation would not.
* **Rays per step** are ``rays_per_step`` random pixels split evenly across the batch's targets (seeded
  from the global step, as GRaF); NeRF2 shuffles single rays across all training spectra, so a step here
  sees ``data.batch_size`` spectra rather than up to 8192.  The loss is NeRF2's: MSE of the ray amplitude
  against the spectrum value.
* Inference renders all 32400 rays in chunks of ``chunk_rays`` rays (over the whole batch), so memory is
  bounded; geometry, encodings and rendering stay fp32 under autocast, the MLPs follow autocast.

Optimiser as NeRF2: Adam (``lr``, ``weight_decay``) and a cosine schedule (``t_max``, ``eta_min``) stepped
every optimiser step (``t_max`` null: the run's ``max_steps``, :mod:`graf.models.schedule`); like NeRF2's
``CosineAnnealingLR`` it rises again after ``t_max`` steps.  NeRF2 is
per-scene: for another scene it is fine-tuned from weights trained elsewhere
(``NeRF2Module.load_from_checkpoint``, which restores the sizes too; ``ray_dirs`` is rebuilt, not stored).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

from graf.config_home import defaults_from
from graf.geometry.grid import local_directions
from graf.geometry.rays import fp32, num_samples, random_pixels, render_spectra, world_directions
from graf.models.base import SpectrumModule
from graf.models.nerf2.network import NeRF2Network
from graf.models.nerf2.renderer import render_rays, sample_distances
from graf.models.schedule import check_rates, cosine_record, run_steps, schedule_length


@defaults_from("model/nerf2.yaml")
class NeRF2Module(SpectrumModule):
    """NeRF2 (Zhao et al., MobiCom 2023), the per-scene baseline: an MLP field of attenuation and radiance over one
    scene, rendered along each ray of the spectrum from the gateway; trained on one scene, it reads no neighbors
    and refuses a test on another scene.

    Args (their defaults in ``conf/model/nerf2.yaml``, the one place they are stated: :mod:`graf.config_home`):
        depth / width / skips: the attenuation MLP (8 x 256, point encoding re-entered after layer 4).
        pe_freqs: encoding frequencies of points, view directions and transmitter (10: 3 -> 63 dims).
        near: distance (m) of the first sample from the gateway.
        max_samples / sample_spacing: S = min(max_samples, ceil((ray_length - near) / (sample_spacing * wavelength))).
        path_loss: numerator of NeRF2's path-loss term ``path_loss / r``.
        rays_per_step: rays per training step, split evenly across the batch's targets.
        chunk_rays: rays per forward chunk at inference (bounds memory).
        lr / weight_decay: Adam.  t_max / eta_min: cosine learning-rate schedule (in optimiser steps).
    """

    renders_rays = True  # prepare(batch) and render(ctx, pix): graf.models.base.Method
    INFERENCE_SETTINGS = ("chunk_rays",)  # graf-eval may change these on a trained checkpoint
    uses_neighbors = False  # one scene's field: no neighbor is read, so no reliance to measure

    def __init__(
        self,
        *,
        depth: int,
        width: int,
        skips: Sequence[int],
        pe_freqs: int,
        near: float,
        max_samples: int,
        sample_spacing: float,
        path_loss: float,
        rays_per_step: int,
        chunk_rays: int,
        lr: float,
        weight_decay: float,
        t_max: int | None,
        eta_min: float,
    ):
        super().__init__()
        positive = {
            "max_samples": max_samples,
            "sample_spacing": sample_spacing,
            "path_loss": path_loss,
            "rays_per_step": rays_per_step,
            "chunk_rays": chunk_rays,
            "t_max": 1 if t_max is None else t_max,
        }
        check_rates(lr)
        for key, value in positive.items():
            if not value > 0:
                raise ValueError(f"model.{key} must be positive, got {value!r}")
        if near < 0:
            raise ValueError(f"model.near must be >= 0 (m), got {near!r}")
        if not (0 <= weight_decay < float("inf") and 0 <= eta_min < float("inf")):  # nan and inf refused too
            raise ValueError(
                f"model.weight_decay and model.eta_min must be finite and >= 0, got {weight_decay!r}, {eta_min!r}"
            )
        skips = [int(s) for s in skips]  # plain ints in the checkpoint, not a ListConfig
        self.save_hyperparameters()
        self.near, self.max_samples, self.sample_spacing = float(near), int(max_samples), float(sample_spacing)
        self.path_loss, self.rays_per_step, self.chunk_rays = float(path_loss), int(rays_per_step), int(chunk_rays)
        self.lr, self.weight_decay = float(lr), float(weight_decay)
        self.t_max, self.eta_min = (None if t_max is None else int(t_max)), float(eta_min)
        self.network = NeRF2Network(depth, width, skips, pe_freqs)
        self.register_buffer("ray_dirs", local_directions(dtype=torch.float32), persistent=False)

    @property
    def method(self) -> str:
        return "nerf2"

    # ------------------------------------------------------------------ rays
    def samples_per_ray(self, batch: dict) -> list[int]:
        """Samples per ray of each batch item: ``sample_spacing`` wavelengths apart from near to far, capped."""
        far = batch["ray_length"].float()
        return num_samples(far - self.near, batch["wavelength"].float() * self.sample_spacing, self.max_samples)

    def prepare(self, batch: dict) -> dict:
        """Per-batch ray geometry: sample counts, distances ``t [B, S]``, gateway and transmitter."""
        far = batch["ray_length"].float()
        if bool((far <= self.near).any()):
            raise ValueError(
                f"model.near ({self.near} m) must be below the scene's ray_length ({float(far.min()):.4g} m)"
            )
        samples = self.samples_per_ray(batch)
        return {
            "samples": samples,
            "t": sample_distances(self.near, far, samples),
            "gw_pos": batch["gw_pos"].float(),
            "gw_rot": batch["gw_rot"].float(),
            "tx": batch["tgt_pos"].float(),
        }

    def render(self, ctx: dict, pix: torch.Tensor) -> torch.Tensor:
        """Predicted amplitudes ``[B, R]`` of the pixels ``pix [B, R]`` (long, ``r * 360 + c``)."""
        with fp32(pix.device):
            dirs = world_directions(ctx["gw_rot"], self.ray_dirs[pix])  # [B, R, 3]
            pts = ctx["gw_pos"][:, None, None, :] + ctx["t"][:, None, :, None] * dirs[:, :, None, :]  # [B, R, S, 3]
        raw = self.network(pts, dirs, ctx["tx"][:, None, :])  # [B, R, S, 4]
        with fp32(pix.device):
            return render_rays(raw.float(), ctx["t"], ctx["samples"], self.path_loss)

    # ------------------------------------------------------------------ Lightning API
    def predict_spectra(self, batch: dict) -> torch.Tensor:
        ctx = self.prepare(batch)
        return render_spectra(self.render, ctx, batch["tgt_pos"].shape[0], self.chunk_rays, self.ray_dirs.device)

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        B = batch["tgt_pos"].shape[0]
        pix = random_pixels(B, self.rays_per_step, self.global_step, batch["tgt_pos"].device)
        pred = self.render(self.prepare(batch), pix)
        target = batch["tgt_spectrum"].flatten(1).gather(1, pix).float()
        loss = F.mse_loss(pred, target)
        self.log("train/loss", loss, prog_bar=True, batch_size=B)
        return loss

    def configure_optimizers(self):
        opt = torch.optim.Adam(self.parameters(), lr=self.lr, weight_decay=self.weight_decay)
        length = schedule_length(self, self.t_max, "t_max")
        self.schedule_record = cosine_record(self.lr, self.eta_min, length, run_steps(self))
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=length, eta_min=self.eta_min)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step", "frequency": 1}}
