"""KNN-DL: the L neighbors' spectra fused with per-pixel weight maps that a small network predicts from
the geometry of target and neighbors (the learned-weights baseline of supplement E.2, built on the linear
fusion of appendix A.2).

    pred[b, p] = sum_l w[b, l, p] * SS_l[p]

**Weights.** :class:`.weightnet.WeightNet` maps the relative geometry of each (target, neighbor) pair
(PE of the normalised offset, distance in wavelengths, distance rank, neighbor count, plus a DeepSets
mean over the target's neighbors) and each ray direction to two coarse maps (``map_size``, default
18 x 72, i.e. 5 deg cells), upsampled bilinearly (circular in azimuth) to 90 x 360:

    w = softmax_l( log w_idw + logit )  +  s * (t - mean_real(t)),   t = tanh(correction)

- The **convex part** is a per-pixel softmax over the real neighbors with the log of the IDW weights
  (1/d, :func:`graf.models.knn.idw_weights`) as a fixed bias.  The decoder's last layer is
  zero-initialised, so at step 0 the model *is* IDW KNN and training starts from it.  A convex
  combination keeps the interpolation theorem's guarantee (supplement A.1): the error is bounded by the
  neighbors' spread, whatever the network outputs.
- The **signed correction** (bound ``signed_scale`` = s) lets a weight go negative or above 1, as the
  per-target weight matrices of supplement A.2 do (their normalised values span -1..1, Fig 1b), i.e. it allows
  extrapolation beyond the neighbors' hull along a pixel's dominant trend.  It is centred over the real
  neighbors, so the weights still sum to 1 (an affine combination: a spectrum common to all neighbors
  is reproduced exactly), and bounded, so a badly predicted correction cannot blow a pixel up.
  ``signed_scale: 0`` gives the purely convex model.  (In 300-step CPU runs on rfid_s23 the two were
  within 0.3 dB PSNR of each other, with dense and with sparse neighbors; the default keeps the signed
  part because the A.2 weights are signed.)

Padded neighbors (``src_mask`` False) get weight exactly 0 (``-inf`` logit, masked correction).  A
neighbor at distance 0 from the target takes the whole IDW bias (the others' bias is ``-inf``), so the
convex part is that neighbor; only the bounded correction can move weight to the others.  With L = 1
the weight is 1.

**Neighbor spectra never enter the weight network**: the weights depend on geometry only, so one
trained model serves every target of a scene and applies to any set of neighbors.  The network is
small: with the defaults 14,914 parameters (per-neighbor MLP 42 -> 64, DeepSets 64 -> 64, decoder
32 -> 32 -> 2 per cell); one forward costs B x L x 1,296 cells of a 32-wide MLP plus the upsampling
(on one CPU core: a training step of 4 targets with up to 10 neighbors ~0.06 s, the 40 test spectra of
rfid_s23 with L = 10 ~0.26 s).

**Training**: the whole 90 x 360 map of every target of the batch (cheap here: nothing is rendered per
ray), L2 loss; Adam with an exponential learning-rate decay by ``lr_decay`` over ``decay_steps`` steps
(stepped every optimiser step), as GRaF.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F

from graf.config_home import defaults_from
from graf.geometry.encoding import normalize_offsets
from graf.geometry.grid import N_AZIMUTH, N_ELEVATION
from graf.models.base import SpectrumModule, adam_exponential_decay
from graf.models.knn.weights import idw_weights
from graf.models.knn_dl.weightnet import WeightNet, upsample_maps
from graf.models.schedule import check_rates, is_number


@defaults_from("model/knn_dl.yaml")
class KNNDLModule(SpectrumModule):
    """KNN-DL (the learned-weights baseline of the paper's supplement E.2): the neighbors' spectra fused with per-pixel
    weight maps a small network predicts from the geometry of target and neighbors.

    Args (their defaults in ``conf/model/knn_dl.yaml``, the one place they are stated: :mod:`graf.config_home`):
    map_size: coarse weight-map grid (h, w); h divides 90, w divides 360.
    hidden / decoder_hidden: widths of the per-neighbor MLP and of the per-cell decoder.
    pe_freqs / dir_freqs: positional-encoding bands of the offset and of the ray direction.
    max_rank: scale of the rank and neighbor-count features: the largest L the model will see.  The config's
        ``null`` is the run's neighbor selector's largest L (``max_L``), filled in when a run builds the model
        (:func:`graf.run.build.run_model_config`); constructed directly, give a number (default 10).
    signed_scale: bound of the signed, zero-sum weight correction (0: convex weights only).
    idw_power: the IDW bias is log(1 / d^idw_power).
    lr / lr_decay / decay_steps: Adam; the lr is multiplied by lr_decay over decay_steps steps (null: the run's).
    """

    def __init__(
        self,
        *,
        map_size: Sequence[int],
        hidden: int,
        decoder_hidden: int,
        pe_freqs: int,
        dir_freqs: int,
        max_rank: int | None,
        signed_scale: float,
        idw_power: float,
        lr: float,
        lr_decay: float,
        decay_steps: int | None,
    ):
        super().__init__()
        if max_rank is None:
            raise ValueError(
                "model.max_rank=null is the run's largest neighbor count L, filled in when graf-train or graf-eval "
                "builds the model; constructed outside a run, give a number"
            )
        map_size = [int(v) for v in map_size]  # plain ints in the checkpoint, not a ListConfig
        if len(map_size) != 2 or min(map_size) < 1 or N_ELEVATION % map_size[0] or N_AZIMUTH % map_size[1]:
            raise ValueError(f"model.map_size must be [h, w] with h dividing 90 and w dividing 360, got {map_size}")
        for key, value in (
            ("hidden", hidden),
            ("decoder_hidden", decoder_hidden),
            ("max_rank", max_rank),
            ("decay_steps", 1 if decay_steps is None else decay_steps),
        ):
            if int(value) < 1:
                raise ValueError(f"model.{key} must be >= 1, got {value}")
        for key, value in (("pe_freqs", pe_freqs), ("dir_freqs", dir_freqs)):
            if int(value) < 0:
                raise ValueError(f"model.{key} must be >= 0, got {value}")
        if signed_scale < 0:
            raise ValueError(f"model.signed_scale must be >= 0, got {signed_scale}")
        if not (is_number(idw_power) and math.isfinite(idw_power) and idw_power > 0):
            raise ValueError(f"model.idw_power={idw_power}: must be a finite number > 0 (the IDW exponent)")
        check_rates(lr, lr_decay)
        self.save_hyperparameters()
        self.signed_scale, self.idw_power = float(signed_scale), float(idw_power)
        self.lr, self.lr_decay = float(lr), float(lr_decay)
        self.decay_steps = None if decay_steps is None else int(decay_steps)
        self.net = WeightNet(map_size, int(hidden), int(decoder_hidden), int(pe_freqs), int(dir_freqs), int(max_rank))

    @property
    def method(self) -> str:
        return "knn-dl"

    def fusion_weights(self, batch: dict) -> torch.Tensor:
        """``[B, L, 90, 360]`` per-pixel weights; 0 for padded neighbors, summing to 1 over l."""
        mask = batch["src_mask"].bool()
        tgt, src = batch["tgt_pos"].float(), batch["src_pos"].float()
        offset = src - tgt[:, None, :]
        maps = upsample_maps(
            self.net(
                normalize_offsets(offset, batch["bounds"].float()),
                offset,
                batch["wavelength"].float(),
                mask,
                batch["gw_rot"].float(),
            )
        )
        bias = torch.log(idw_weights(tgt, src, mask, power=self.idw_power))  # -inf where the IDW weight is 0
        w = torch.softmax(bias[..., None, None] + maps[:, :, 0], dim=1)
        if self.signed_scale > 0:
            m = mask[..., None, None].to(w.dtype)
            t = torch.tanh(maps[:, :, 1]) * m
            w = w + self.signed_scale * (t - m * t.sum(dim=1, keepdim=True) / m.sum(dim=1, keepdim=True))
        return w

    def predict_spectra(self, batch: dict) -> torch.Tensor:
        w = self.fusion_weights(batch)
        src = batch["src_spectra"].float().masked_fill(~batch["src_mask"].bool()[..., None, None], 0.0)
        return (w * src).sum(dim=1)

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        loss = F.mse_loss(self.predict_spectra(batch), batch["tgt_spectrum"].float())
        self.log("train/loss", loss, prog_bar=True, batch_size=batch["tgt_pos"].shape[0])
        return loss

    def configure_optimizers(self):
        return adam_exponential_decay(self, self.lr, self.lr_decay, self.decay_steps)
