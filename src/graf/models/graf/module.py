"""GRaF: geometry-aware radiance field with neural ray tracing (seed section 3, appendix D, figures 2-3).

For a target transmitter at P and its L neighbors (spectra SS_l at positions P_l), every spectrum pixel is
a ray from the gateway; the predicted value of a ray is

1. **Neighbor tokens** (once per neighbor spectrum per batch, never per ray): ``MLP1(ResNet18(SS_l) ⊕
   PE(P_l) ⊕ PE(P_l - P))`` -> ``d_model`` (16) tokens; padded neighbors are masked out.
2. **Voxel latents**: the S voxels along the ray (one wavelength apart unless capped at ``max_samples``,
   see :mod:`graf.geometry.rays`) are queries ``Linear(PE(x_s) ⊕ PE(dir) ⊕ PE(P))`` (voxel, ray direction,
   target) that attend to the neighbor tokens through ``scene_blocks`` post-norm cross-attention blocks
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

**Geometry, the same in every scene**: every position (voxels, target, neighbors) and direction is
expressed in the item's *gateway frame* (origin at the receiving array, its axes;
:func:`graf.geometry.encoding.to_gateway_frame`) in units of ``length_unit`` metres (4 m by default), so one
unit is the same length in every scene a model is trained or tested on; offsets ``P_l - P`` are rotated into
the same axes.  ``use_scene_index`` appends the scene index as a fourth coordinate of every absolute position (3-D PE:
63
dims, 4-D: 84 dims); offsets stay 3-D.

Training: ``rays_per_step`` random pixels per step, split evenly across the batch's targets (drawn
without replacement per target, seeded from the global step), per-ray L2 loss; Adam with an exponential
learning-rate decay by ``lr_decay`` over ``decay_steps`` steps (stepped every optimiser step).
Inference (:meth:`GRaFModule.predict_spectra`): all 32400 rays in chunks of at most ``chunk_rays`` rays
(over the whole batch); neighbor tokens are computed once per batch.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from graf.geometry.encoding import PositionalEncoding, sinusoidal_encoding, to_gateway_axes, to_gateway_frame
from graf.geometry.grid import N_AZIMUTH, N_ELEVATION, N_RAYS, local_directions
from graf.geometry.rays import box_segments, fp32, random_pixels, segment_samples
from graf.models.base import SpectrumModule, adam_exponential_decay
from graf.models.graf.attention import CrossAttentionBlock, SelfAttentionBlock
from graf.models.graf.encoder import ResNetEncoder
from graf.models.graf.ray_features import RayNeighborTokens, pad_wrap, pixel_window, sample_wrap
from graf.models.knn.weights import barycentric_weights, idw_weights

WEIGHTINGS = ("idw", "barycentric")
# how the rays read the neighbors: pooled (the seed's: one token per neighbor spectrum), ray (per-ray tokens
# from each neighbor's feature map and pixel values at the ray's own direction), ray_knn (ray, plus a per-ray
# convex combination of the neighbors' pixel values that equals IDW KNN at initialisation, corrected by the
# ray tracer), ray_weights (ray, and the output is only that per-ray convex combination, its weights corrected by
# the neighbor tokens and by the ray tracer's state: never an additive term, so every predicted pixel is a
# weighted average of what the neighbors measured there): see graf.models.graf.ray_features
NEIGHBOR_FEATURES = ("pooled", "ray", "ray_knn", "ray_weights")
KNN_BASED = ("ray_knn", "ray_weights")  # modes equal to IDW KNN at initialisation
LOSSES = ("mse", "log_mse")
LOG_MSE_EPS = 1e-6
# The scene index enters the PE as a coordinate ``index * SCENE_INDEX_SCALE``: with a raw integer n every
# sin(2^k pi n) is 0 and cos(2^k pi n) is 1 for k >= 1, so the PE would carry nothing but n and (-1)^n.
SCENE_INDEX_SCALE = (math.sqrt(5.0) - 1.0) / 2.0
AMPLITUDE_EPS = 1e-12
ATTENTION_KERNELS = ("auto", "sdpa", "math")
EVAL_CACHE_ITEMS = 16  # scene voxel tables kept at evaluation
EVAL_CACHE_FEATURES = 50_000  # encoded neighbor spectra kept at evaluation (x 512 floats at paper size)
SCENE_TABLE_VOXELS = 2_000_000  # scenes with more voxels per spectrum compute them per chunk instead of caching
SCENE_TABLE_CHUNK = 65_536  # voxels per piece while building a scene's table


def _mlp(d_in: int, hidden: int, d_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d_in, hidden), nn.ReLU(), nn.Linear(hidden, d_out))


class GRaFModule(SpectrumModule):
    INFERENCE_SETTINGS = ("chunk_rays",)  # graf-eval may change these on a trained checkpoint
    LAYOUT = 3
    LAYOUT_CHANGES = {
        2: "positions are now metres in the gateway frame (layout 1 normalised them by each scene's "
        "box), ray directions are encoded, and voxels are encoded by their distance in wavelengths "
        "(layout 1 had a learned voxel-index table sized by max_samples)",
        3: "each ray's voxels now run from its own entry to its own exit of the scene box (layout 2 "
        "cut every ray at the box's farthest corner), so the same weights see other voxels",
    }
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

    def __init__(
        self,
        encoder_widths: Sequence[int] = (64, 128, 256, 512),
        encoder_downsample: int = 1,
        d_model: int = 16,
        scene_blocks: int = 2,
        ray_blocks: int = 2,
        ray_heads: int = 10,
        ray_head_dim: int = 8,
        ffn_dim: int = 64,
        mlp_dim: int = 64,
        pe_freqs: int = 10,
        max_samples: int = 128,
        rays_per_step: int = 5120,
        chunk_rays: int = 4096,
        lr: float = 5e-4,
        lr_decay: float = 0.1,
        decay_steps: int = 300_000,
        residual: bool = False,
        weighting: str = "idw",
        use_scene_index: bool = False,
        loss: str = "mse",
        length_unit: float = 4.0,
        voxel_wavelengths: float = 1.0,
        ray_window: int = 0,
        attention: str = "auto",
        neighbor_features: str = "pooled",
        ray_feature_dim: int = 8,
        pixel_window: int = 1,
    ):
        super().__init__()
        if neighbor_features not in NEIGHBOR_FEATURES:
            raise ValueError(f"model.neighbor_features must be one of {NEIGHBOR_FEATURES}, got {neighbor_features!r}")
        if ray_feature_dim < 1 or pixel_window < 0:
            raise ValueError(
                f"model.ray_feature_dim must be >= 1 and model.pixel_window >= 0, got {ray_feature_dim}, {pixel_window}"
            )
        if neighbor_features in KNN_BASED and residual:
            raise ValueError(
                f"model.neighbor_features={neighbor_features} already adds its own per-ray KNN base: "
                "model.residual must be false"
            )
        if weighting not in WEIGHTINGS:
            raise ValueError(f"model.weighting must be one of {WEIGHTINGS}, got {weighting!r}")
        if loss not in LOSSES:
            raise ValueError(f"model.loss must be one of {LOSSES}, got {loss!r}")
        if min(d_model, scene_blocks, ray_heads, ray_head_dim, max_samples, rays_per_step, chunk_rays) < 1:
            raise ValueError("GRaF sizes must be positive")
        if d_model % 2:
            raise ValueError(
                f"model.d_model must be even (the voxel distance encoding is sin/cos pairs), got {d_model}"
            )
        if not length_unit > 0:
            raise ValueError(f"model.length_unit must be > 0 (metres), got {length_unit}")
        if not voxel_wavelengths > 0:
            raise ValueError(f"model.voxel_wavelengths must be > 0, got {voxel_wavelengths}")
        if ray_window < 0:
            raise ValueError(f"model.ray_window must be >= 0 (0: attention over the whole ray), got {ray_window}")
        if attention not in ATTENTION_KERNELS:
            raise ValueError(f"model.attention must be one of {ATTENTION_KERNELS}, got {attention!r}")
        encoder_widths = [int(w) for w in encoder_widths]  # plain ints in the checkpoint, not a ListConfig
        self.save_hyperparameters()
        self.d_model, self.max_samples = int(d_model), int(max_samples)
        self.rays_per_step, self.chunk_rays = int(rays_per_step), int(chunk_rays)
        self.lr, self.lr_decay, self.decay_steps = float(lr), float(lr_decay), int(decay_steps)
        self.residual, self.weighting, self.use_scene_index = bool(residual), weighting, bool(use_scene_index)
        self.loss_name, self.length_unit = loss, float(length_unit)
        self.sample_spacing, self.ray_window = float(voxel_wavelengths), int(ray_window)
        self.neighbor_features, self.pixel_window = neighbor_features, int(pixel_window)
        self.ray_aligned = neighbor_features != "pooled"
        self._ray_tables: dict = {}  # geometry only: per scene geometry and band, never stale
        self._eval_cache: dict = {}  # weights-dependent tables of evaluation (see _cached)
        d = self.d_model
        coord_dim = 4 if self.use_scene_index else 3

        self.pe = PositionalEncoding(pe_freqs)
        pe_abs, pe_off = self.pe.out_dim(coord_dim), self.pe.out_dim(3)
        self.encoder = ResNetEncoder(encoder_widths, in_channels=1, downsample=encoder_downsample)
        if self.ray_aligned:  # per-ray tokens (ray_features); no pooled token
            self.ray_proj = nn.Conv2d(self.encoder.out_dim, int(ray_feature_dim), 1)
            self.ray_tokens = RayNeighborTokens(int(ray_feature_dim), self.pixel_window, pe_off + 1, mlp_dim, d)
        else:
            self.mlp1 = _mlp(self.encoder.out_dim + pe_abs + pe_off, mlp_dim, d)
        # Linear(PE(voxel) ⊕ PE(ray direction) ⊕ PE(target)) split in three: the direction's part is computed
        # once per ray (it is constant along the ray) and the target's once per target
        self.query_voxel = nn.Linear(pe_abs, d)
        self.query_direction = nn.Linear(self.pe.out_dim(3), d, bias=False)
        self.query_target = nn.Linear(pe_abs, d, bias=False)
        self.scene_blocks = nn.ModuleList(
            CrossAttentionBlock(d, 1, d, ffn_dim, kernel=attention) for _ in range(scene_blocks)
        )
        self.mlp2 = _mlp(d, mlp_dim, d)
        # each voxel's place on the ray: a learned projection of a sinusoidal code of its distance from the
        # gateway in wavelengths (the same meaning in every scene and band, at any sample count)
        self.voxel_distance = nn.Linear(d, d)
        self.ray_blocks = nn.ModuleList(
            SelfAttentionBlock(d, ray_heads, ray_head_dim, ffn_dim, kernel=attention) for _ in range(ray_blocks)
        )
        if neighbor_features == "ray_weights":  # the ray tracer's state -> a query over the L per-ray tokens
            self.weight_query = nn.Linear(d, d)  # whose scores correct the convex weights (zero at init)
            nn.init.zeros_(self.weight_query.weight)
            nn.init.zeros_(self.weight_query.bias)
        else:
            self.head = nn.Linear(d, 2)
        if self.residual or neighbor_features == "ray_knn":  # the model starts as (per-ray) KNN
            nn.init.zeros_(self.head.weight)
            nn.init.zeros_(self.head.bias)
        self.register_buffer("ray_dirs", local_directions(dtype=torch.float32), persistent=False)

    @property
    def method(self) -> str:
        name = "graf-residual" if self.residual else "graf"
        return name if self.neighbor_features == "pooled" else f"{name}-{self.neighbor_features.replace('_', '-')}"

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

    def knn_weights(self, batch: dict) -> torch.Tensor:
        """``[B, L]`` convex weights of the residual's KNN base (as :class:`graf.models.knn.KNNModule`)."""
        args = (batch["tgt_pos"], batch["src_pos"], batch["src_mask"])
        return idw_weights(*args) if self.weighting == "idw" else barycentric_weights(*args)

    # ------------------------------------------------------------------ rays of a scene (geometry only)
    def ray_table(self, batch: dict, b: int) -> dict:
        """Voxels of every pixel's ray in item ``b``'s scene: ``t_in [P]`` (m, where the ray enters the scene
        box), ``step [P]`` (m, the voxel length), ``samples [P]`` (long) and the pixel order by sample count
        (``order [P]``); voxel ``s`` of a ray lies ``t_in + (s + 0.5) * step`` from the gateway.  Voxels are
        ``voxel_wavelengths`` long (1: the seed's wavelength voxel) unless ``max_samples`` caps a ray.  Computed
        once per scene geometry and band (cached; the key is the geometry itself, not a scene number)."""
        geo = (batch["gw_pos"][b], batch["gw_rot"][b], batch["bounds"][b])
        wl = float(batch["wavelength"][b])
        dev = self.ray_dirs.device
        key = (
            tuple(torch.cat([g.detach().double().flatten().cpu() for g in geo]).tolist()),
            wl,
            self.sample_spacing,
            self.max_samples,
            str(dev),
        )
        table = self._ray_tables.get(key)
        if table is None:
            t_in, t_out = box_segments(*(g.detach().cpu() for g in geo), local_directions(dtype=torch.float64))
            samples, step = segment_samples(t_in, t_out, self.sample_spacing * wl, self.max_samples)
            needed = torch.ceil((t_out - t_in) / (self.sample_spacing * wl) - 1e-6).clamp_min(1).long()
            table = {
                "t_in": t_in.float().to(dev),
                "step": step.float().to(dev),
                "samples": samples.to(dev),
                "order": torch.argsort(samples, stable=True).to(dev),
                "needed": needed,
                "offsets": (torch.cumsum(samples, 0) - samples).to(dev),
                "voxels": int(samples.sum()),
            }
            self._ray_tables[key] = table
        return table

    def samples_per_ray(self, batch: dict) -> list[int]:
        """The most voxels on any ray of each batch item (rays differ: each is cut at its own exit of the box)."""
        return [int(self.ray_table(batch, b)["samples"].max()) for b in range(batch["gw_pos"].shape[0])]

    def mean_samples_per_ray(self, batch: dict) -> list[float]:
        """Mean voxels per ray of each batch item (what the cost of a spectrum is proportional to)."""
        return [float(self.ray_table(batch, b)["samples"].float().mean()) for b in range(batch["gw_pos"].shape[0])]

    def ray_sampling(self, geometry: dict) -> dict:
        """Voxels per ray on one scene (``geometry``: ``gw_pos [1, 3]``, ``gw_rot [1, 3, 3]``, ``bounds [1, 2, 3]``,
        ``wavelength [1]``): their most, mean and total, the voxel length, and whether ``max_samples`` capped
        any ray (its voxels are then longer than ``voxel_wavelengths``)."""
        t = self.ray_table(geometry, 0)
        wl = float(geometry["wavelength"][0])
        capped = t["needed"] > t["samples"].cpu()
        return {
            "samples_per_ray": int(t["samples"].max()),
            "mean_samples_per_ray": float(t["samples"].float().mean()),
            "voxels_per_spectrum": t["voxels"],
            "sample_spacing_m": float(t["step"].max()),
            "sample_spacing_wavelengths": float(t["step"].max()) / wl,
            "nominal_spacing_wavelengths": self.sample_spacing,
            "capped": bool(capped.any()),
            "capped_rays": int(capped.sum()),
            "uncapped_samples": int(t["needed"].max()),
            "sampling": "ray-box: each ray from its entry to its exit of the scene box",
        }

    # ------------------------------------------------------------------ evaluation caches
    def _weights_stamp(self, *modules: nn.Module) -> tuple:
        """Changes whenever any parameter of ``modules`` is modified in place (optimiser step, load_state_dict)
        or replaced: a cache computed from these weights is valid while its stamp is unchanged."""
        return tuple((p.data_ptr(), p._version) for m in modules for p in m.parameters())

    def _cached(self, name: str, stamp: tuple, key, compute):
        """Evaluation-only memo (no autograd, eval mode): ``compute()`` once per ``key`` while ``stamp`` holds."""
        if self.training or torch.is_grad_enabled():
            return compute()
        store = self._eval_cache.setdefault(name, {"stamp": None, "items": {}})
        if store["stamp"] != stamp:
            store["stamp"], store["items"] = stamp, {}
        if key not in store["items"]:
            if len(store["items"]) >= EVAL_CACHE_ITEMS:
                store["items"].pop(next(iter(store["items"])))
            store["items"][key] = compute()
        return store["items"][key]

    def train(self, mode: bool = True):
        if mode:
            self._eval_cache = {}  # free evaluation tables while training (they are stale after a step anyway)
        return super().train(mode)

    def _spectrum_features(self, spectra: torch.Tensor) -> torch.Tensor:
        """Encoder features ``[N, C]`` of neighbor spectra ``[N, 90, 360]``.  At evaluation each distinct
        spectrum is encoded once (keyed by its bytes): a test set's targets share most of their neighbors."""
        if self.training or torch.is_grad_enabled():
            return self.encoder(spectra.unsqueeze(1).float())
        stamp = self._weights_stamp(self.encoder)
        keys = [hashlib.blake2b(x.contiguous().cpu().numpy().tobytes(), digest_size=16).digest() for x in spectra]
        store = self._eval_cache.get("features")
        if store is None or store["stamp"] != stamp:
            store = self._eval_cache["features"] = {"stamp": stamp, "items": {}}
        items = store["items"]
        missing = [i for i, k in enumerate(keys) if k not in items]
        if missing:
            feats = self.encoder(spectra[missing].unsqueeze(1).float())
            for i, f in zip(missing, feats):
                if len(items) >= EVAL_CACHE_FEATURES:
                    items.pop(next(iter(items)))
                items[keys[i]] = f
        return torch.stack([items[k] for k in keys])

    # ------------------------------------------------------------------ a batch
    def encode_neighbors(self, batch: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """``(tokens [B, L, d], mask [B, L])``; the encoder sees only the real neighbors' spectra."""
        spectra, mask = batch["src_spectra"], batch["src_mask"].bool()
        B, L = mask.shape
        real = self._spectrum_features(spectra[mask])  # [N_real, C]
        feats = real.new_zeros(B, L, real.shape[-1])
        feats[mask] = real
        src_pos, tgt_pos = batch["src_pos"].float(), batch["tgt_pos"].float()
        pe_pos = self.pe(self._coords(src_pos, batch))
        pe_off = self.pe(to_gateway_axes(src_pos - tgt_pos[:, None, :], batch["gw_rot"].float()) / self.length_unit)
        tokens = self.mlp1(torch.cat([feats.float(), pe_pos, pe_off], dim=-1))
        return torch.where(mask[..., None], tokens, torch.zeros_like(tokens)), mask

    def encode_ray_neighbors(self, batch: dict) -> dict:
        """Ray-aligned mode: each neighbor's projected feature map ``ray_maps [B, L, k, h, w + 2]`` (azimuth-padded,
        read per ray by :func:`sample_wrap`: bilinear at the ray's pixel, never upsampled whole), the
        spectra ``src [B, L, 90, 360]`` (padded ones zero), the geometry's share of the token MLP ``geo [B, L,
        hidden]`` and, for ``ray_knn``, IDW's log-weights ``idw_logits [B, L]``."""
        spectra, mask = batch["src_spectra"].float(), batch["src_mask"].bool()
        B, L = mask.shape
        maps = pad_wrap(self.ray_proj(self.encoder.forward_map(spectra[mask].unsqueeze(1))))  # [N, k, h, w + 2]
        ray_maps = maps.new_zeros(B, L, *maps.shape[1:])
        ray_maps[mask] = maps
        src_pos, tgt_pos = batch["src_pos"].float(), batch["tgt_pos"].float()
        offset = src_pos - tgt_pos[:, None, :]
        pe_off = self.pe(to_gateway_axes(offset, batch["gw_rot"].float()) / self.length_unit)
        dist_wl = torch.linalg.vector_norm(offset, dim=-1, keepdim=True) / batch["wavelength"].float()[:, None, None]
        ctx = {
            "ray_maps": ray_maps,
            "src": spectra.masked_fill(~mask[..., None, None], 0.0),
            "geo": self.ray_tokens.geometry(torch.cat([pe_off, torch.log1p(dist_wl)], dim=-1)),
        }
        if self.neighbor_features in KNN_BASED:
            ctx["idw_logits"] = torch.log(idw_weights(batch["tgt_pos"], batch["src_pos"], mask).float()).masked_fill(
                ~mask, float("-inf")
            )
        return ctx

    def prepare(self, batch: dict) -> dict:
        """Everything about a batch that does not depend on the rays: computed once per batch."""
        if self.ray_aligned:
            mask = batch["src_mask"].bool()
            tokens, extra = mask.new_zeros(mask.shape[0], 0), self.encode_ray_neighbors(batch)
        else:
            (tokens, mask), extra = self.encode_neighbors(batch), {}
        B = mask.shape[0]
        ctx = {
            **extra,
            "mask": mask,
            "tokens": tokens,
            "key_mask": None if bool(mask.all()) else mask,
            "target_query": self.query_target(self.pe(self._coords(batch["tgt_pos"].float(), batch))),  # [B, d]
            "tables": [self.ray_table(batch, b) for b in range(B)],
            "wavelength": batch["wavelength"].float(),
            "scene_index": batch["scene_index"],
        }
        if self.residual:
            w = self.knn_weights(batch).float()
            src = batch["src_spectra"].flatten(2).float()
            ctx["base_w"], ctx["base_src"] = w, src.masked_fill(~mask[..., None], 0.0)  # [B, L], [B, L, P]
        return ctx

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

        def compute():
            qs, cs = [], []
            for S in torch.unique(table["samples"]).tolist():
                sel = (table["samples"] == S).nonzero().flatten()
                for part in sel.split(max(1, SCENE_TABLE_CHUNK // S)):
                    n = part.numel()
                    q, c = self._voxel_inputs(
                        part,
                        table["t_in"][part],
                        table["step"][part],
                        torch.full((n,), wl, device=device),
                        torch.full((n,), scene_index, device=device, dtype=torch.long),
                        S,
                    )
                    qs.append((part, q)), cs.append(c)
            qf = torch.empty(table["voxels"], self.d_model, device=device, dtype=qs[0][1].dtype)
            cf = torch.empty(table["voxels"], self.d_model, device=device, dtype=cs[0].dtype)
            for (part, q), c in zip(qs, cs):
                idx = (table["offsets"][part][:, None] + torch.arange(q.shape[1], device=device)).flatten()
                qf[idx], cf[idx] = q.flatten(0, 1), c.flatten(0, 1)
            return qf, cf

        stamp = self._weights_stamp(self.query_voxel, self.query_direction, self.voxel_distance)
        key = (
            id(table),
            scene_index,
            wl,
            torch.get_autocast_dtype(device.type) if torch.is_autocast_enabled(device.type) else None,
        )
        return self._cached("voxels", stamp, key, compute)

    def _ray_transformer(self, v: torch.Tensor) -> torch.Tensor:
        """The ray blocks over ``v [n, S, d]``: full self-attention along the ray, or, with ``ray_window`` W
        and S > W, attention within consecutive windows of W voxels (cost linear in S; for large scenes)."""
        n, S, d = v.shape
        W = self.ray_window
        for blk in self.ray_blocks:
            if not W or S <= W:
                v = blk(v)
            else:
                k = S // W
                head = blk(v[:, : k * W].reshape(n * k, W, d)).view(n, k * W, d)
                v = head if k * W == S else torch.cat([head, blk(v[:, k * W :])], dim=1)
        return v

    def _render_group(self, ctx: dict, bi: torch.Tensor, pix: torch.Tensor, S: int) -> torch.Tensor:
        """``[n, 2]`` (re, im) of ``n`` rays with ``S`` voxels each (items ``bi [n]``, pixels ``pix [n]``)."""
        n = pix.shape[0]
        tables = ctx["tables"]
        one_item = bool((bi == bi[0]).all())
        if (
            one_item
            and not (self.training or torch.is_grad_enabled())
            and tables[int(bi[0])]["voxels"] <= SCENE_TABLE_VOXELS
        ):
            b = int(bi[0])
            t = tables[b]
            qf, cf = self._scene_voxels(t, float(ctx["wavelength"][b]), int(ctx["scene_index"][b]), pix.device)
            idx = t["offsets"][pix][:, None] + torch.arange(S, device=pix.device)
            q, code = qf[idx], cf[idx]
        else:
            t_in = torch.stack([tables[b]["t_in"] for b in range(len(tables))])[bi, pix]
            step = torch.stack([tables[b]["step"] for b in range(len(tables))])[bi, pix]
            q, code = self._voxel_inputs(pix, t_in, step, ctx["wavelength"][bi], ctx["scene_index"][bi], S)
        q = q + ctx["target_query"][bi][:, None, :]
        key_mask = ctx["key_mask"]
        base = None
        if self.ray_aligned:  # each ray's voxels attend to that ray's own neighbor tokens
            window = pixel_window(ctx["src"], bi, pix, self.pixel_window)  # [n, L, K]
            feats = sample_wrap(ctx["ray_maps"], bi, pix, ctx["ray_maps"].shape[-1] - 2)  # [n, L, k]
            ctx_tokens, logits = self.ray_tokens(feats, window, ctx["geo"][bi])
            x, km = q, None if key_mask is None else key_mask[bi]
            if self.neighbor_features == "ray_knn":  # convex weights at this pixel: IDW at init, then learned
                w = torch.softmax(ctx["idw_logits"][bi] + logits, dim=-1)
                base = (w * window[..., window.shape[-1] // 2]).sum(dim=-1)  # [n]
            elif self.neighbor_features == "ray_weights":
                logits = ctx["idw_logits"][bi] + logits
        elif one_item:  # every voxel of the group attends to the same target's neighbors: one long query axis
            b = int(bi[0])
            x = q.reshape(1, n * S, self.d_model)
            ctx_tokens, km = ctx["tokens"][b : b + 1], None if key_mask is None else key_mask[b : b + 1]
        else:  # each ray's voxels attend to its own target's neighbors
            x, ctx_tokens, km = q, ctx["tokens"][bi], None if key_mask is None else key_mask[bi]
        for blk in self.scene_blocks:
            x = blk(x, ctx_tokens, km)
        v = self.mlp2(x).view(n, S, self.d_model) + code
        v = self._ray_transformer(v)
        if self.neighbor_features == "ray_weights":  # the ray's state scores its neighbor tokens: the weights'
            state = self.weight_query(v.float().mean(dim=1))  # correction; the value is their convex combination
            scores = (state[:, None, :] * ctx_tokens.float()).sum(dim=-1) / math.sqrt(self.d_model)  # [n, L]
            w = torch.softmax(logits.float() + scores, dim=-1)
            value = (w * window[..., window.shape[-1] // 2].float()).sum(dim=-1)  # [n]
            return torch.stack([value, torch.zeros_like(value)], dim=-1)
        out = self.head(v.float().mean(dim=1)).float()
        if base is not None:  # ray_knn: the ray tracer corrects the per-ray KNN value (re + base, im)
            out = torch.stack([out[:, 0] + base.float(), out[:, 1]], dim=-1)
        return out

    def render(self, ctx: dict, pix: torch.Tensor) -> torch.Tensor:
        """Predicted values ``[B, R]`` of the pixels ``pix [B, R]`` (long, ``r * 360 + c``).  Rays are grouped
        by their voxel count (exactly, no padding or masks); nothing runs per ray in Python."""
        B, R = pix.shape
        tables = ctx["tables"]
        S_all = torch.stack([tables[b]["samples"][pix[b]] for b in range(B)]).flatten()  # [B * R]
        flat_pix = pix.flatten()
        bi = torch.arange(B, device=pix.device).repeat_interleave(R)
        order, outs = [], []
        for S in torch.unique(S_all).tolist():
            sel = (S_all == S).nonzero().flatten()
            order.append(sel)
            outs.append(self._render_group(ctx, bi[sel], flat_pix[sel], int(S)))
        out = torch.cat(outs)[torch.argsort(torch.cat(order))]  # back to (b, r) order
        re, im = out.view(B, R, 2).unbind(-1)
        if self.residual:
            with fp32(pix.device):
                src = ctx["base_src"].gather(2, pix[:, None, :].expand(-1, ctx["base_src"].shape[1], -1))
                re = re + torch.einsum("bl,blr->br", ctx["base_w"], src)
        return torch.sqrt(re * re + im * im + AMPLITUDE_EPS)

    # ------------------------------------------------------------------ Lightning API
    def predict_spectra(self, batch: dict) -> torch.Tensor:
        """Whole spectra ``[B, 90, 360]``: each item's pixels in order of voxel count, in chunks of at most
        ``chunk_rays`` rays over the batch (memory bounded by the chunk), so a chunk holds few groups."""
        ctx = self.prepare(batch)
        B = ctx["mask"].shape[0]
        order = torch.stack([t["order"] for t in ctx["tables"]])  # [B, P]
        per = max(1, self.chunk_rays // B)
        out = torch.cat([self.render(ctx, order[:, s : s + per]) for s in range(0, N_RAYS, per)], dim=1)
        spectra = torch.empty_like(out)
        spectra.scatter_(1, order, out)
        return spectra.view(B, N_ELEVATION, N_AZIMUTH).float()

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
