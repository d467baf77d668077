"""GRaF: geometry-aware radiance field with neural ray tracing (the paper's section 3, supplement D, figures 2-3).

For a target transmitter at P and its L neighbors (spectra SS_l at positions P_l), every spectrum pixel is
a ray from the gateway; the predicted value of a ray is

1. **Neighbor features** (``model/features=<mode>``, the modes in :mod:`graf.models.graf.features`): the
   paper's ``pooled`` makes one token ``MLP1(ResNet18(SS_l) ⊕ PE(P_l) ⊕ PE(P_l - P))`` -> ``d_model`` (16) per
   neighbor spectrum, once per batch; padded neighbors are masked out.
2. **Voxel latents**: the S voxels along the ray (one wavelength apart unless capped at ``max_samples``,
   see :mod:`graf.geometry.rays`) are queries ``Linear(PE(x_s) ⊕ PE(dir) ⊕ PE(P))`` (voxel, ray direction,
   target) that attend to the neighbor tokens through ``scene_blocks`` post-norm cross-attention blocks
   (1 head of width d), then ``MLP2``.
3. **Neural ray tracing**: voxel latents + a code of each voxel's distance from the gateway in wavelengths
   (``Linear(sinusoidal(dist / wavelength))``: continuous, so it means the same in every scene and band and
   at any S) go through ``ray_blocks`` post-norm self-attention blocks (``ray_heads`` heads of
   ``ray_head_dim``) and are mean-pooled over the ray; the component turns that state into the received
   signal ``re + j im`` (``Linear(d, 2)``; ``ray_weights``: ``(value, 0)``); the prediction is its amplitude
   ``sqrt(re^2 + im^2 + eps)``.

``residual=True`` (with ``pooled`` or ``ray``) adds the KNN interpolation to the real part, ``|base + re + j
im|``, and starts as KNN (:mod:`graf.models.graf.features.residual`).

**Geometry, the same in every scene**: positions and directions in the item's gateway frame in units of
``length_unit`` metres (:func:`graf.geometry.encoding.to_gateway_frame`); ``use_scene_index`` appends the scene
index as a fourth coordinate of absolute positions.

Training: ``rays_per_step`` random pixels a step (seeded by the step), per-ray L2 loss, Adam decayed by ``lr_decay``
over ``decay_steps``.  Inference: all 32400 rays in chunks of ``chunk_rays`` (:mod:`graf.models.graf.inference`).  Off
a CPU, the static path (:mod:`graf.models.graf.buckets`).  Old checkpoints load through :mod:`.legacy`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from functools import partial

import torch
import torch.nn.functional as F
from torch import nn

from graf.config_home import defaults_from
from graf.geometry.encoding import PositionalEncoding, sinusoidal_encoding, to_gateway_axes, to_gateway_frame
from graf.geometry.grid import N_AZIMUTH, N_ELEVATION, local_directions
from graf.geometry.rays import fp32, random_pixels
from graf.models.base import SpectrumModule, adam_exponential_decay
from graf.models.graf.attention import CrossAttentionBlock, MultiHeadAttention, SelfAttentionBlock
from graf.models.graf.buckets import padded_mask, ray_groups, static_shapes, voxel_mask
from graf.models.graf.cache import EvalCache, weights_stamp
from graf.models.graf.encoder import ResNetEncoder
from graf.models.graf.features import PAPER_MODE, Dims, build_features
from graf.models.graf.features.base import mlp
from graf.models.graf.features.ray_reading import rows
from graf.models.graf.features.residual import KNNBase, NoBase
from graf.models.graf.inference import SerialThreads, fast_path, ray_pass, rays_in_chunks, split_batch
from graf.models.graf.legacy import (
    LAYOUT_CHANGES,
    upgrade_arguments,
    upgrade_hparams,
    upgrade_optimizer_states,
    upgrade_state_dict,
)
from graf.models.graf.pieces import piece_prediction
from graf.models.graf.settings import check_settings
from graf.models.graf.tables import flat_scene_voxels, geometry_key, ray_sampling_summary, scene_ray_table

LOG_MSE_EPS = 1e-6
# The scene index enters the PE as a coordinate ``index * SCENE_INDEX_SCALE``: with a raw integer n every
# sin(2^k pi n) is 0 and cos(2^k pi n) is 1 for k >= 1, so the PE would carry nothing but n and (-1)^n.
SCENE_INDEX_SCALE = (math.sqrt(5.0) - 1.0) / 2.0
AMPLITUDE_EPS = 1e-12
SCENE_TABLE_VOXELS = 2_000_000  # scenes with more voxels per spectrum compute them per chunk instead of caching


@defaults_from("model/graf.yaml")
class GRaFModule(SpectrumModule):
    """GRaF, the generalizable RF radiance field of the paper (its parts: the module's docstring above); ``features``
    picks how rays read the neighbors (pooled: the paper's; ray, ray_knn, ray_weights).

    Args (their defaults in ``conf/model/graf.yaml``, the one place they are stated: :mod:`graf.config_home`):
        encoder_widths / encoder_downsample: ResNet-18 stage widths; average pooling of the spectra first.
        d_model: token / voxel latent width (16).
        scene_blocks: cross-attention blocks of the scene representation (1 head of width d_model).
        ray_blocks / ray_heads / ray_head_dim: the ray transformer's self-attention blocks.
        ffn_dim: hidden width of every Transformer block's FFN.  mlp_dim: hidden width of MLP1 and MLP2.
        pe_freqs: positional-encoding frequency bands (10: 3 -> 63 dims).
        max_samples: cap on the voxels per ray (S = min(max_samples, ceil(ray_length / wavelength))).
        rays_per_step: rays per training step, split evenly across the batch's targets.
        chunk_rays: rays per forward chunk at inference (bounds memory).
        lr / lr_decay / decay_steps: Adam; the lr is multiplied by lr_decay over decay_steps steps (null: the run's).
        residual / weighting: predict |KNN(weighting) + re + j im| instead of |re + j im| (pooled and ray).
        loss: ``mse`` (per-ray L2) or ``log_mse`` (mean over targets of log(per-target MSE + 1e-6)).
        use_scene_index: 4-D positions (x, y, z, scene index) for cross-scene training.
        fast_training / train_pieces / fast_inference: a CPU's fast paths (graf.models.graf.pieces, .inference).
        features: the neighbor-feature component's config (``conf/model/features/<mode>.yaml``) or a mode's name.
    """

    renders_rays = True  # prepare(batch) and render(ctx, pix): graf.models.base.Method
    INFERENCE_SETTINGS = ("chunk_rays", "fast_inference", "fast_training", "train_pieces")  # how fast, not what
    LAYOUT = 3
    LAYOUT_CHANGES = LAYOUT_CHANGES  # graf.models.graf.legacy: what each layout changed
    upgrade_hparams = staticmethod(upgrade_hparams)  # a checkpoint's hyperparameters in the current form

    def __init__(
        self,
        *,
        encoder_widths: Sequence[int],
        encoder_downsample: int,
        d_model: int,
        scene_blocks: int,
        ray_blocks: int,
        ray_heads: int,
        ray_head_dim: int,
        ffn_dim: int,
        mlp_dim: int,
        pe_freqs: int,
        max_samples: int,
        rays_per_step: int,
        chunk_rays: int,
        lr: float,
        lr_decay: float,
        decay_steps: int | None,
        residual: bool,
        weighting: str,
        use_scene_index: bool,
        loss: str,
        length_unit: float,
        voxel_wavelengths: float,
        ray_window: int,
        attention: str,
        fast_inference: bool,
        fast_training: bool,
        train_pieces: int | None,
        features: Mapping | str = PAPER_MODE,
        **legacy,
    ):
        super().__init__()
        # the checkpoint records plain ints (not a ListConfig) and the component's config as a plain dict (the
        # deprecated keyword arguments folded into it)
        encoder_widths = [int(w) for w in encoder_widths]
        features, legacy = upgrade_arguments(features, legacy), {}
        self.save_hyperparameters()
        check_settings(self.hparams)
        self.d_model, self.max_samples, self.rays_per_step = int(d_model), int(max_samples), int(rays_per_step)
        self.chunk_rays, self.lr, self.lr_decay = int(chunk_rays), float(lr), float(lr_decay)
        self.decay_steps = None if decay_steps is None else int(decay_steps)
        self.residual, self.use_scene_index = bool(residual), bool(use_scene_index)
        self.loss_name, self.length_unit = loss, float(length_unit)
        self.sample_spacing, self.ray_window = float(voxel_wavelengths), int(ray_window)
        self.fast_inference, self.fast_training = fast_inference, fast_training  # checked: true or false
        self.train_pieces = train_pieces  # checked: a positive int, or None: torch's threads
        self.static_shapes: bool | None = None  # the static path: None, off a CPU (graf.models.graf.buckets)
        self._ray_tables: dict = {}  # geometry only: per scene geometry and band, never stale
        self.eval_cache = EvalCache()  # weights-dependent tables of evaluation (see _cached)
        self.base = KNNBase(weighting) if self.residual else NoBase()
        self.build_layers(self.hparams)
        self.register_buffer("ray_dirs", local_directions(dtype=torch.float32), persistent=False)
        self.register_load_state_dict_pre_hook(upgrade_state_dict)  # checkpoints written before the components

    def build_layers(self, hp: Mapping) -> None:
        """The encoder, the neighbor-feature component (its parameters right after the encoder's), the voxel
        queries, the scene blocks, MLP2, the ray transformer, and last the component's output (in the order
        of the model before the components, so a seed draws the same initial weights)."""
        d, coord_dim = self.d_model, 4 if self.use_scene_index else 3
        self.pe = PositionalEncoding(hp["pe_freqs"])
        pe_abs, pe_off = self.pe.out_dim(coord_dim), self.pe.out_dim(3)
        self.encoder = ResNetEncoder(hp["encoder_widths"], in_channels=1, downsample=hp["encoder_downsample"])
        dims = Dims(self.encoder.out_dim, pe_abs, pe_off, hp["mlp_dim"], d)
        self.features = build_features(hp["features"], dims, self.residual, defer_output=True)
        # Linear(PE(voxel) ⊕ PE(ray direction) ⊕ PE(target)) split in three: the direction's part is computed
        # once per ray (it is constant along the ray) and the target's once per target
        self.query_voxel = nn.Linear(pe_abs, d)
        self.query_direction = nn.Linear(self.pe.out_dim(3), d, bias=False)
        self.query_target = nn.Linear(pe_abs, d, bias=False)
        ffn, kernel = hp["ffn_dim"], hp["attention"]
        self.scene_blocks = nn.ModuleList(
            CrossAttentionBlock(d, 1, d, ffn, kernel=kernel) for _ in range(hp["scene_blocks"])
        )
        self.mlp2 = mlp(d, hp["mlp_dim"], d)
        # each voxel's place on the ray: a learned projection of a sinusoidal code of its distance from the
        # gateway in wavelengths (the same meaning in every scene and band, at any sample count)
        self.voxel_distance = nn.Linear(d, d)
        self.ray_blocks = nn.ModuleList(
            SelfAttentionBlock(d, hp["ray_heads"], hp["ray_head_dim"], ffn, kernel=kernel)
            for _ in range(hp["ray_blocks"])
        )
        self.features.make_output(dims, self.residual)  # last, as before the components: same seed, same weights
        for m in self.modules():
            if isinstance(m, MultiHeadAttention):
                m.fused_training = bool(hp.get("fast_training", True))

    @property
    def method(self) -> str:
        """The name results and tables key on: graf / graf-residual, then the component's suffix (-ray, ...)."""
        return ("graf-residual" if self.residual else "graf") + self.features.method_suffix

    # ------------------------------------------------------------------ building blocks
    def _with_scene(self, x: torch.Tensor, scene_index: torch.Tensor) -> torch.Tensor:
        """Gateway-frame coordinates ``[B, ..., 3]`` (+ the scaled scene index as a 4th coordinate)."""
        if not self.use_scene_index:
            return x
        s = scene_index.to(device=x.device, dtype=x.dtype) * SCENE_INDEX_SCALE
        s = s.view((x.shape[0],) + (1,) * (x.dim() - 1)).expand(*x.shape[:-1], 1)
        return torch.cat([x, s], dim=-1)

    def coords(self, p: torch.Tensor, batch: dict) -> torch.Tensor:
        """World positions ``[B, ..., 3]`` -> coordinates in the item's gateway frame in units of ``length_unit``
        metres, the same scale in every scene (+ the scaled scene index)."""
        x = to_gateway_frame(p.float(), batch["gw_pos"].float(), batch["gw_rot"].float()) / self.length_unit
        return self._with_scene(x, batch["scene_index"])

    def neighbor_offsets(self, batch: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """``(P_l - P [B, L, 3] in metres, PE of it in the gateway axes in units of length_unit)``."""
        offset = batch["src_pos"].float() - batch["tgt_pos"].float()[:, None, :]
        return offset, self.pe(to_gateway_axes(offset, batch["gw_rot"].float()) / self.length_unit)

    # ------------------------------------------------------------------ rays of a scene (geometry only)
    def ray_table(self, batch: dict, b: int) -> dict:
        """Voxels of every pixel's ray in item ``b``'s scene (:func:`~graf.models.graf.tables.scene_ray_table`; voxel
        ``s`` of a ray lies ``t_in + (s + 0.5) * step`` from the gateway), once per geometry and band (cached)."""
        geo = (batch["gw_pos"][b], batch["gw_rot"][b], batch["bounds"][b])
        keys = batch.get("ray_table_keys")  # read on the host before the batch moved (on_before_batch_transfer)
        key = keys[b] if keys is not None else geometry_key(*geo, batch["wavelength"][b])
        dev = self.ray_dirs.device
        full = (key, self.sample_spacing, self.max_samples, str(dev))
        if full not in self._ray_tables:
            self._ray_tables[full] = scene_ray_table(geo, key[-1], self.sample_spacing, self.max_samples, dev)
        return self._ray_tables[full]

    def on_before_batch_transfer(self, batch, dataloader_idx: int = 0):
        """On the static path (:func:`graf.models.graf.buckets.static_shapes`) the batch's scene-table keys are read
        here, on the host, so that a step on the device never copies geometry back to find its tables."""
        if isinstance(batch, dict) and "gw_pos" in batch and static_shapes(self, self.device):
            geo = zip(batch["gw_pos"], batch["gw_rot"], batch["bounds"], batch["wavelength"])
            batch = {**batch, "ray_table_keys": [geometry_key(*g) for g in geo]}
        return batch

    def samples_per_ray(self, batch: dict) -> list[int]:
        """The most voxels on any ray of each batch item (rays differ: each is cut at its own exit of the box)."""
        return [self.ray_table(batch, b)["most"] for b in range(batch["gw_pos"].shape[0])]

    def mean_samples_per_ray(self, batch: dict) -> list[float]:
        """Mean voxels per ray of each batch item (what the cost of a spectrum is proportional to)."""
        return [float(self.ray_table(batch, b)["samples"].float().mean()) for b in range(batch["gw_pos"].shape[0])]

    def ray_sampling(self, geometry: dict) -> dict:
        """Voxels per ray on one scene (``geometry``: ``gw_pos [1, 3]``, ``gw_rot [1, 3, 3]``, ``bounds [1, 2, 3]``,
        ``wavelength [1]``): :func:`~graf.models.graf.tables.ray_sampling_summary`."""
        return ray_sampling_summary(self.ray_table(geometry, 0), float(geometry["wavelength"][0]), self.sample_spacing)

    # ------------------------------------------------------------------ evaluation caches
    def _cached(self, name: str, stamp: tuple, key, compute):
        """Evaluation-only memo (no autograd, eval mode): ``compute()`` once per ``key`` while ``stamp`` holds."""
        if self.training or torch.is_grad_enabled():
            return compute()
        return self.eval_cache.memo(name, stamp, key, compute)

    def train(self, mode: bool = True):
        if mode:  # free the evaluation tables while training (stale after a step anyway)
            self.eval_cache.clear()
        return super().train(mode)

    def spectrum_features(self, spectra: torch.Tensor) -> torch.Tensor:
        """Encoder features ``[N, C]`` of neighbor spectra ``[N, 90, 360]``.  At evaluation each distinct
        spectrum is encoded once (keyed by its bytes): a test set's targets share most of their neighbors."""
        if self.training or torch.is_grad_enabled():
            return self.encoder(spectra.unsqueeze(1).float())
        return self.eval_cache.encoded(self.encoder, spectra, split_batch)

    # ------------------------------------------------------------------ a batch
    def prepare(self, batch: dict) -> dict:
        """Everything about a batch that does not depend on the rays: computed once per batch (the component's
        context, the KNN base's with ``residual``, the target's query and the items' ray tables)."""
        mask = batch["src_mask"].bool()
        B, static = mask.shape[0], static_shapes(self, mask.device)
        return {
            **self.features.prepare(self, batch),
            **self.base.prepare(batch, mask),
            "mask": mask,
            "key_mask": mask if static else None if bool(mask.all()) else mask,  # static: never read back
            "target_query": self.query_target(self.pe(self.coords(batch["tgt_pos"].float(), batch))),  # [B, d]
            "tables": [self.ray_table(batch, b) for b in range(B)],
            "wavelength": batch["wavelength"].float(),
            "scene_index": batch["scene_index"],
        }

    # ------------------------------------------------------------------ rays
    def _voxel_inputs(
        self,
        pix: torch.Tensor,
        t_in: torch.Tensor,
        step: torch.Tensor,
        wl: torch.Tensor,
        scene_index: torch.Tensor,
        S: int,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(query [n, S, d], distance code [n, S, d])`` of the voxels of ``n`` rays with ``S`` voxels each:
        ``Linear(PE(voxel)) + Linear(PE(direction))`` and ``Linear(sinusoidal(distance / wavelength))``."""
        with fp32(pix.device):  # geometry in fp32 also under autocast: PE phases reach 2^9 pi x
            dist = t_in[:, None] + (torch.arange(S, device=pix.device, dtype=torch.float32) + 0.5) * step[:, None]
            dirs = self.ray_dirs[pix].float()  # [n, 3] (gateway frame: a voxel is its distance times the direction)
            pos = (dist[..., None] / self.length_unit) * dirs[:, None, :]  # [n, S, 3]
            pe = self.pe(self._with_scene(pos, scene_index))
            pe_dir = self.pe(dirs)
            code = sinusoidal_encoding(dist / wl[:, None], self.d_model)
        return self.query_voxel(pe) + self.query_direction(pe_dir)[:, None, :], self.voxel_distance(code)

    def _scene_voxels(self, table: dict, wl: float, scene_index: int, device) -> tuple[torch.Tensor, torch.Tensor]:
        """``_voxel_inputs`` of every voxel of a scene's spectrum, flat ``[V, d]`` (pixel-major, offsets in the
        table): computed once per scene and weights at evaluation (the gateway does not move)."""

        stamp = weights_stamp(self.query_voxel, self.query_direction, self.voxel_distance)
        autocast = torch.get_autocast_dtype(device.type) if torch.is_autocast_enabled(device.type) else None
        compute = partial(flat_scene_voxels, table, self._voxel_inputs, wl, scene_index, self.d_model, device)
        return self._cached("voxels", stamp, (id(table), scene_index, wl, autocast), compute)

    def _render_group(self, ctx, bi, pix, S: int, samples=None, static: bool = False) -> torch.Tensor:
        """``[n, 2]`` (re, im) of rays of ``S`` voxels (``samples [n]``: padded to ``S``) of items ``bi``; ``static``:
        nothing read back to the host (no per-item shortcut, the mask made whatever it holds)."""
        n = pix.shape[0]
        tables = ctx["tables"]
        one_item = not static and bool((bi == bi[0]).all())
        if (
            one_item
            and not (self.training or torch.is_grad_enabled())
            and tables[int(bi[0])]["voxels"] <= SCENE_TABLE_VOXELS
        ):
            b = int(bi[0])
            t = tables[b]
            qf, cf = self._scene_voxels(t, float(ctx["wavelength"][b]), int(ctx["scene_index"][b]), pix.device)
            offs = t["offsets"][pix]
            start, steps = int(offs[0]), torch.arange(n, device=pix.device) * S
            if torch.equal(offs - start, steps):  # consecutive rays of the table (predict_spectra's chunks): a slice
                q, code = qf[start : start + n * S].view(n, S, -1), cf[start : start + n * S].view(n, S, -1)
            else:
                idx = offs[:, None] + torch.arange(S, device=pix.device)
                q, code = qf[idx], cf[idx]
        else:
            t_in, step = (torch.stack([t[k] for t in tables])[bi, pix] for k in ("t_in", "step"))
            q, code = self._voxel_inputs(pix, t_in, step, ctx["wavelength"][bi], ctx["scene_index"][bi], S)
        q = q + rows(ctx["target_query"], bi)[:, None, :]
        x, tokens, key_mask, ray = self.features.scene_inputs(ctx, q, bi, pix, one_item)
        fast = fast_path(self.fast_inference, self.training, x)
        voxels = padded_mask(samples, S) if static else None if samples is None else voxel_mask(samples, S)
        return self.features.output(ray_pass(self, x, tokens, key_mask, code, fast, voxels), ray)

    def render(self, ctx: dict, pix: torch.Tensor) -> torch.Tensor:
        """Predicted values ``[B, R]`` of the pixels ``pix [B, R]`` (long, ``r * 360 + c``): rays grouped by voxel count
        (exactly, or padded in the few groups of :func:`~graf.models.graf.buckets.buckets` when training on the fast
        path), or on the static path all in one group padded to the longest ray, masked; nothing runs per ray."""
        B, R = pix.shape
        tables = ctx["tables"]
        S_all = torch.stack([tables[b]["samples"][pix[b]] for b in range(B)]).flatten()  # [B * R]
        flat_pix = pix.flatten()
        bi = torch.arange(B, device=pix.device).repeat_interleave(R)
        if static_shapes(self, pix.device) and not self.ray_window:  # windows need exact groups
            out = self._render_group(ctx, bi, flat_pix, max(t["most"] for t in tables), S_all, static=True)
        else:
            order, outs, padded = [], [], self.fast_training and torch.is_grad_enabled() and not self.ray_window
            for sel, S, samples in ray_groups(S_all, padded):
                order.append(sel)
                outs.append(self._render_group(ctx, bi[sel], flat_pix[sel], S, samples))
            out = torch.cat(outs)[torch.argsort(torch.cat(order))]  # back to (b, r) order
        re, im = out.view(B, R, 2).unbind(-1)
        re = self.base.add(ctx, pix, re)
        return torch.sqrt(re * re + im * im + AMPLITUDE_EPS)

    # ------------------------------------------------------------------ Lightning API
    def predict_spectra(self, batch: dict) -> torch.Tensor:
        """Whole spectra ``[B, 90, 360]``: each item's pixels in order of voxel count, in chunks of at most
        ``chunk_rays`` rays over the batch (memory bounded by the chunk), so a chunk holds few groups."""
        with SerialThreads(batch["tgt_pos"].device):
            ctx = self.prepare(batch)
        order = torch.stack([t["order"] for t in ctx["tables"]])  # [B, P]
        out = rays_in_chunks(lambda pix: self.render(ctx, pix), order, self.chunk_rays)
        spectra = torch.empty_like(out)
        spectra.scatter_(1, order, out)
        return spectra.view(-1, N_ELEVATION, N_AZIMUTH).float()

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        B = batch["tgt_pos"].shape[0]
        pix = random_pixels(B, self.rays_per_step, self.global_step, batch["tgt_pos"].device)
        pred = piece_prediction(self, batch, pix) if self.fast_training else None  # None: not on the fast path here
        if pred is None:
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

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        super().on_load_checkpoint(checkpoint)
        upgrade_optimizer_states(self, checkpoint)  # a checkpoint written before the components: the new order
