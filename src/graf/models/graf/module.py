"""GRaF: geometry-aware radiance field with neural ray tracing (seed section 3, appendix D, figures 2-3).

For a target transmitter at P and its L neighbours (spectra SS_l at positions P_l), every spectrum pixel is
a ray from the gateway; the predicted value of a ray is

1. **Neighbour tokens** (once per neighbour spectrum per batch, never per ray): ``MLP1(ResNet18(SS_l) ⊕
   PE(P_l) ⊕ PE(P_l - P))`` -> ``d_model`` (16) tokens; padded neighbours are masked out.
2. **Voxel latents**: the S voxels along the ray (one wavelength apart unless capped at ``max_samples``,
   see :mod:`graf.geometry.rays`) are queries ``Linear(PE(x_s) ⊕ PE(dir) ⊕ PE(P))`` (voxel, ray direction,
   target) that attend to the neighbour tokens through ``scene_blocks`` post-norm cross-attention blocks
   (1 head of width d), then ``MLP2``.
3. **Neural ray tracing**: voxel latents + a code of each voxel's distance from the gateway in wavelengths
   (``Linear(sinusoidal(dist / wavelength))``: continuous, so it means the same in every scene and band and
   at any S) go through ``ray_blocks``
   post-norm self-attention blocks (``ray_heads`` heads of ``ray_head_dim``), are mean-pooled over the
   ray, and ``Linear(d, 2)`` gives the received signal ``re + j im``; the prediction is its amplitude
   ``sqrt(re^2 + im^2 + eps)``.

``residual=True`` adds the KNN interpolation ``base = sum_l w_l SS_l(ray)`` (``weighting`` ``idw`` or
``barycentric``, :mod:`graf.models.knn.weights`) to the real part: ``|base + re + j im|``; the final
Linear is zero-initialised, so at initialisation the model *is* KNN.  (Then ``im`` sits at a stationary
point of ``|.|`` and keeps a zero gradient; ``re`` alone reaches every amplitude, so nothing is lost.)

**Geometry, the same in every scene**: every position (voxels, target, neighbours) and direction is
expressed in the item's *gateway frame* (origin at the receiving array, its axes;
:func:`graf.geometry.encoding.to_gateway_frame`) in units of ``length_unit`` metres (4 m by default), so one
unit is the same length in every scene a model is trained or tested on; offsets ``P_l - P`` are rotated into
the same axes.  ``use_scene_index`` appends the scene index as a fourth coordinate of every absolute position (3-D PE: 63
dims, 4-D: 84 dims); offsets stay 3-D.

Training: ``rays_per_step`` random pixels per step, split evenly across the batch's targets (drawn
without replacement per target, seeded from the global step), per-ray L2 loss; Adam with an exponential
learning-rate decay by ``lr_decay`` over ``decay_steps`` steps (stepped every optimiser step).
Inference (:meth:`GRaFModule.predict_spectra`): all 32400 rays in chunks of at most ``chunk_rays`` rays
(over the whole batch); neighbour tokens are computed once per batch.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from graf.models.base import SpectrumModule, adam_exponential_decay
from graf.models.graf.attention import CrossAttentionBlock, SelfAttentionBlock
from graf.models.graf.encoder import ResNetEncoder
from graf.geometry.encoding import PositionalEncoding, sinusoidal_encoding, to_gateway_axes, to_gateway_frame
from graf.geometry.grid import local_directions
from graf.geometry.rays import fp32, num_samples, random_pixels, render_spectra, voxel_distances
from graf.models.knn.weights import barycentric_weights, idw_weights

WEIGHTINGS = ("idw", "barycentric")
LOSSES = ("mse", "log_mse")
LOG_MSE_EPS = 1e-6
# The scene index enters the PE as a coordinate ``index * SCENE_INDEX_SCALE``: with a raw integer n every
# sin(2^k pi n) is 0 and cos(2^k pi n) is 1 for k >= 1, so the PE would carry nothing but n and (-1)^n.
SCENE_INDEX_SCALE = (math.sqrt(5.0) - 1.0) / 2.0
AMPLITUDE_EPS = 1e-12



def _mlp(d_in: int, hidden: int, d_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d_in, hidden), nn.ReLU(), nn.Linear(hidden, d_out))


class GRaFModule(SpectrumModule):
    INFERENCE_SETTINGS = ("chunk_rays",)  # graf-eval may change these on a trained checkpoint
    LAYOUT = 2
    LAYOUT_CHANGES = {2: "positions are now metres in the gateway frame (layout 1 normalised them by each scene's "
                         "box), ray directions are encoded, and voxels are encoded by their distance in wavelengths "
                         "(layout 1 had a learned voxel-index table sized by max_samples)"}
    sample_spacing = 1.0  # voxels one wavelength long (seed D), unless max_samples caps S
    """Args (all in ``conf/model/graf.yaml``):
        encoder_widths / encoder_downsample: ResNet-18 stage widths; average pooling of the spectra first.
        d_model: token / voxel latent width (16).
        scene_blocks: cross-attention blocks of the scene representation (1 head of width d_model).
        ray_blocks / ray_heads / ray_head_dim: the ray transformer's self-attention blocks.
        ffn_dim: hidden width of every Transformer block's FFN.  mlp_dim: hidden width of MLP1 and MLP2.
        pe_freqs: positional-encoding frequency bands (10: 3 -> 63 dims).
        max_samples: cap on the voxels per ray (S = min(max_samples, ceil(ray_length / wavelength))).
        rays_per_step: rays per training step, split evenly across the batch's targets.
        chunk_rays: rays per forward chunk at inference (bounds memory).
        lr / lr_decay / decay_steps: Adam; the lr is multiplied by lr_decay over decay_steps steps.
        residual / weighting: predict |KNN(weighting) + re + j im| instead of |re + j im|.
        loss: ``mse`` (the seed's per-ray L2) or ``log_mse`` (the mean over the batch's targets of
            log(MSE of the target's rays + 1e-6): the training counterpart of the mean per-spectrum PSNR, so
            spectra that are already well predicted are not traded for the badly predicted ones).
        use_scene_index: 4-D positions (x, y, z, scene index) for cross-scene training.
    """

    def __init__(self, encoder_widths: Sequence[int] = (64, 128, 256, 512), encoder_downsample: int = 1,
                 d_model: int = 16, scene_blocks: int = 2, ray_blocks: int = 2, ray_heads: int = 10,
                 ray_head_dim: int = 8, ffn_dim: int = 64, mlp_dim: int = 64, pe_freqs: int = 10,
                 max_samples: int = 128, rays_per_step: int = 5120, chunk_rays: int = 4096, lr: float = 5e-4,
                 lr_decay: float = 0.1, decay_steps: int = 300_000, residual: bool = False,
                 weighting: str = "idw", use_scene_index: bool = False, loss: str = "mse", length_unit: float = 4.0):
        super().__init__()
        if weighting not in WEIGHTINGS:
            raise ValueError(f"model.weighting must be one of {WEIGHTINGS}, got {weighting!r}")
        if loss not in LOSSES:
            raise ValueError(f"model.loss must be one of {LOSSES}, got {loss!r}")
        if min(d_model, scene_blocks, ray_heads, ray_head_dim, max_samples, rays_per_step, chunk_rays) < 1:
            raise ValueError("GRaF sizes must be positive")
        if d_model % 2:
            raise ValueError(f"model.d_model must be even (the voxel distance encoding is sin/cos pairs), got {d_model}")
        if not length_unit > 0:
            raise ValueError(f"model.length_unit must be > 0 (metres), got {length_unit}")
        encoder_widths = [int(w) for w in encoder_widths]  # plain ints in the checkpoint, not a ListConfig
        self.save_hyperparameters()
        self.d_model, self.max_samples = int(d_model), int(max_samples)
        self.rays_per_step, self.chunk_rays = int(rays_per_step), int(chunk_rays)
        self.lr, self.lr_decay, self.decay_steps = float(lr), float(lr_decay), int(decay_steps)
        self.residual, self.weighting, self.use_scene_index = bool(residual), weighting, bool(use_scene_index)
        self.loss_name, self.length_unit = loss, float(length_unit)
        d = self.d_model
        coord_dim = 4 if self.use_scene_index else 3

        self.pe = PositionalEncoding(pe_freqs)
        pe_abs, pe_off = self.pe.out_dim(coord_dim), self.pe.out_dim(3)
        self.encoder = ResNetEncoder(encoder_widths, in_channels=1, downsample=encoder_downsample)
        self.mlp1 = _mlp(self.encoder.out_dim + pe_abs + pe_off, mlp_dim, d)
        # Linear(PE(voxel) ⊕ PE(ray direction) ⊕ PE(target)) split in three: the direction's part is computed
        # once per ray (it is constant along the ray) and the target's once per target
        self.query_voxel = nn.Linear(pe_abs, d)
        self.query_direction = nn.Linear(self.pe.out_dim(3), d, bias=False)
        self.query_target = nn.Linear(pe_abs, d, bias=False)
        self.scene_blocks = nn.ModuleList(CrossAttentionBlock(d, 1, d, ffn_dim) for _ in range(scene_blocks))
        self.mlp2 = _mlp(d, mlp_dim, d)
        # each voxel's place on the ray: a learned projection of a sinusoidal code of its distance from the
        # gateway in wavelengths (the same meaning in every scene and band, at any sample count)
        self.voxel_distance = nn.Linear(d, d)
        self.ray_blocks = nn.ModuleList(SelfAttentionBlock(d, ray_heads, ray_head_dim, ffn_dim)
                                        for _ in range(ray_blocks))
        self.head = nn.Linear(d, 2)
        if self.residual:
            nn.init.zeros_(self.head.weight)
            nn.init.zeros_(self.head.bias)
        self.register_buffer("ray_dirs", local_directions(dtype=torch.float32), persistent=False)

    @property
    def method(self) -> str:
        return "graf-residual" if self.residual else "graf"

    # ------------------------------------------------------------------ building blocks
    def _with_scene(self, x: torch.Tensor, scene_index: torch.Tensor) -> torch.Tensor:
        """Gateway-frame coordinates ``[B, ..., 3]`` (+ the scaled scene index as a 4th coordinate)."""
        if not self.use_scene_index:
            return x
        s = scene_index.to(device=x.device, dtype=x.dtype) * SCENE_INDEX_SCALE
        s = s.view((x.shape[0],) + (1,) * (x.dim() - 1)).expand(*x.shape[:-1], 1)
        return torch.cat([x, s], dim=-1)

    def _coords(self, p: torch.Tensor, batch: dict) -> torch.Tensor:
        """World positions ``[B, ..., 3]`` -> coordinates in the item's gateway frame in units of ``length_unit``
        metres, the same scale in every scene (+ the scaled scene index)."""
        x = to_gateway_frame(p.float(), batch["gw_pos"].float(), batch["gw_rot"].float()) / self.length_unit
        return self._with_scene(x, batch["scene_index"])

    def encode_neighbours(self, batch: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """``(tokens [B, L, d], mask [B, L])``; the encoder sees only the real neighbours' spectra."""
        spectra, mask = batch["src_spectra"], batch["src_mask"].bool()
        B, L = mask.shape
        real = self.encoder(spectra[mask].unsqueeze(1).float())  # [N_real, C]
        feats = real.new_zeros(B, L, real.shape[-1])
        feats[mask] = real
        src_pos, tgt_pos = batch["src_pos"].float(), batch["tgt_pos"].float()
        pe_pos = self.pe(self._coords(src_pos, batch))
        pe_off = self.pe(to_gateway_axes(src_pos - tgt_pos[:, None, :], batch["gw_rot"].float()) / self.length_unit)
        tokens = self.mlp1(torch.cat([feats.float(), pe_pos, pe_off], dim=-1))
        return torch.where(mask[..., None], tokens, torch.zeros_like(tokens)), mask

    def knn_weights(self, batch: dict) -> torch.Tensor:
        """``[B, L]`` convex weights of the residual's KNN base (as :class:`graf.models.knn.KNNModule`)."""
        args = (batch["tgt_pos"], batch["src_pos"], batch["src_mask"])
        return idw_weights(*args) if self.weighting == "idw" else barycentric_weights(*args)

    def samples_per_ray(self, batch: dict) -> list[int]:
        """Voxels per ray of each batch item: one wavelength apart over the scene's ray length, capped."""
        return num_samples(batch["ray_length"], batch["wavelength"], self.max_samples)

    def prepare(self, batch: dict) -> dict:
        """Everything about a batch that does not depend on the rays: computed once per batch."""
        tokens, mask = self.encode_neighbours(batch)
        samples = self.samples_per_ray(batch)
        dist = voxel_distances(batch["ray_length"].float(), samples)
        S = max(samples)
        smask = torch.arange(S, device=tokens.device)[None, :] < torch.as_tensor(samples, device=tokens.device)[:, None]
        ctx = {
            "tokens": tokens,
            "key_mask": None if bool(mask.all()) else mask,
            "target_query": self.query_target(self.pe(self._coords(batch["tgt_pos"].float(), batch))),  # [B, d]
            "samples": samples,
            "sample_mask": None if min(samples) == S else smask,  # [B, S]
            "dist": dist,  # [B, S] metres
            "voxel_code": self.voxel_distance(sinusoidal_encoding(dist / batch["wavelength"].float()[:, None],
                                                                  self.d_model)),  # [B, S, d]
            "scene_index": batch["scene_index"],
        }
        if self.residual:
            w = self.knn_weights(batch).float()
            src = batch["src_spectra"].flatten(2).float()
            ctx["base_w"], ctx["base_src"] = w, src.masked_fill(~mask[..., None], 0.0)  # [B, L], [B, L, P]
        return ctx

    def render(self, ctx: dict, pix: torch.Tensor) -> torch.Tensor:
        """Predicted values ``[B, R]`` of the pixels ``pix [B, R]`` (long, ``r * 360 + c``)."""
        B, R = pix.shape
        S = max(ctx["samples"])
        with fp32(pix.device):  # geometry in fp32 also under autocast: PE phases reach 2^9 pi x
            # in the gateway frame a voxel is its distance times the pixel's (local) direction: no rotation
            dirs = self.ray_dirs[pix].float()  # [B, R, 3]
            pos = (ctx["dist"][:, None, :, None] / self.length_unit) * dirs[:, :, None, :]  # [B, R, S, 3]
            pe = self.pe(self._with_scene(pos, ctx["scene_index"]))
            pe_dir = self.pe(dirs)  # [B, R, 63]: ray directions (unit vectors, gateway frame)
        q = self.query_voxel(pe) + (self.query_direction(pe_dir) + ctx["target_query"][:, None, :])[:, :, None, :]
        q = q.flatten(1, 2)  # [B, R*S, d]: each target's voxels attend to that target's neighbours
        for blk in self.scene_blocks:
            q = blk(q, ctx["tokens"], ctx["key_mask"])
        v = (self.mlp2(q).view(B, R, S, self.d_model) + ctx["voxel_code"][:, None]).reshape(B * R, S, self.d_model)
        smask = ctx["sample_mask"]
        rmask = None if smask is None else smask[:, None, :].expand(B, R, S).reshape(B * R, S)
        for blk in self.ray_blocks:
            v = blk(v, rmask)
        v = v.float()
        if rmask is None:
            pooled = v.mean(dim=1)
        else:
            m = rmask[..., None].float()
            pooled = (v * m).sum(dim=1) / m.sum(dim=1)
        re, im = self.head(pooled).float().view(B, R, 2).unbind(-1)
        if self.residual:
            with fp32(pix.device):
                src = ctx["base_src"].gather(2, pix[:, None, :].expand(-1, ctx["base_src"].shape[1], -1))
                re = re + torch.einsum("bl,blr->br", ctx["base_w"], src)
        return torch.sqrt(re * re + im * im + AMPLITUDE_EPS)

    # ------------------------------------------------------------------ Lightning API
    def predict_spectra(self, batch: dict) -> torch.Tensor:
        ctx = self.prepare(batch)
        return render_spectra(self.render, ctx, batch["tgt_pos"].shape[0], self.chunk_rays, ctx["tokens"].device)

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        B = batch["tgt_pos"].shape[0]
        pix = random_pixels(B, self.rays_per_step, self.global_step, batch["tgt_pos"].device)
        pred = self.render(self.prepare(batch), pix)
        target = batch["tgt_spectrum"].flatten(1).gather(1, pix).float()
        if self.loss_name == "mse":
            loss = F.mse_loss(pred.float(), target)
        else:  # per-target MSE [B] -> mean log
            loss = torch.log((pred.float() - target).pow(2).mean(dim=1) + LOG_MSE_EPS).mean()
        self.log("train/loss", loss, prog_bar=True, batch_size=B)
        return loss

    def configure_optimizers(self):
        return adam_exponential_decay(self, self.lr, self.lr_decay, self.decay_steps)
