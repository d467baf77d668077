"""NeRF2's signal rendering along a ray (XPengZhao/NeRF2 ``renderer.py``, ``Renderer.raw2outputs``).

A ray from the gateway carries S samples at distances ``t_0 = near, ..., t_{S-1} = far`` (uniform, both
ends included, no jitter).  With the network's raw outputs per sample:

* ``att_a = |leaky_relu(raw_0)|``, ``att_p = sigmoid(raw_1) 2 pi``, ``s_a = |leaky_relu(raw_2)|``,
  ``s_p = sigmoid(raw_3) 2 pi``;
* ``delta_i = t_{i+1} - t_i`` (``1e10`` for the last sample), ``alpha_i = 1 - exp(-att_a_i delta_i)``;
* accumulated attenuation ``T_i = prod_{k<i} (1 - alpha_k + 1e-10)`` (exclusive cumulative product);
* accumulated phase ``Phase_i = exp(j sum_{k<i} att_p_k delta_k)``: NeRF2 *adds* the phase delays
  ``att_p delta`` (exclusive cumulative sum, then one complex exponential), it does not multiply them;
* path loss ``0.025 / t_{i+1}`` (the distance of the *next* sample; ``1e10`` for the last one, so the
  last sample contributes nothing, as in NeRF2);
* received amplitude ``| sum_i s_a_i e^{j s_p_i} T_i Phase_i pathloss_i |``.

Two departures that change nothing NeRF2 computes: NeRF2 starts the phase sum at 1 rad instead of 0 (a
global phase, invisible in ``|.|``), and the complex sum is written as real and imaginary parts (no
complex dtype, so any device works); the amplitude is ``sqrt(re^2 + im^2 + 1e-12)`` so that its gradient
stays finite at 0.  Samples beyond an item's own count (batches mixing scenes or bands) are masked out.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

FAR = 1e10  # NeRF2's stand-in for "infinitely far": the last sample's step and path-loss distance
TRANSMITTANCE_EPS = 1e-10
AMPLITUDE_EPS = 1e-12


def sample_distances(near: float, far: torch.Tensor, samples: list[int]) -> torch.Tensor:
    """``[B, S_max]`` distances (m) of the samples from the gateway: ``near + (far_b - near) i / (S_b - 1)``
    (``torch.linspace(near, far_b, S_b)``; one sample at ``near`` when ``S_b = 1``).  Entries past an item's
    ``S_b`` continue the sequence (finite; :func:`render_rays` masks them)."""
    s = torch.as_tensor(samples, device=far.device, dtype=far.dtype)
    idx = torch.arange(max(samples), device=far.device, dtype=far.dtype)
    step = (far - near) / (s - 1).clamp_min(1)
    return near + idx[None, :] * step[:, None]


def render_rays(raw: torch.Tensor, t: torch.Tensor, samples: list[int], path_loss: float = 0.025) -> torch.Tensor:
    """Received amplitude ``[B, R]`` of the rays whose samples gave ``raw [B, R, S, 4]`` (fp32) at distances
    ``t [B, S]``; item b uses its first ``samples[b]`` samples."""
    B, S = t.shape
    real = torch.arange(S, device=t.device)[None, :] < torch.as_tensor(samples, device=t.device)[:, None]  # [B,S]
    last = torch.arange(S, device=t.device)[None, :] == torch.as_tensor(samples, device=t.device)[:, None] - 1
    t_next = torch.cat([t[:, 1:], t.new_full((B, 1), FAR)], dim=1).masked_fill(last, FAR)  # [B, S]
    delta = (t_next - t)[:, None, :]  # [B, 1, S]
    att_a = F.leaky_relu(raw[..., 0]).abs()
    att_p = torch.sigmoid(raw[..., 1]) * (2 * math.pi)
    s_a = F.leaky_relu(raw[..., 2]).abs()
    s_p = torch.sigmoid(raw[..., 3]) * (2 * math.pi)
    alpha = 1.0 - torch.exp(-att_a * delta)  # [B, R, S]
    trans = 1.0 - alpha + TRANSMITTANCE_EPS
    att = torch.cumprod(torch.cat([torch.ones_like(trans[..., :1]), trans[..., :-1]], dim=-1), dim=-1)
    step_phase = att_p * delta
    phase = torch.cumsum(torch.cat([torch.zeros_like(step_phase[..., :1]), step_phase[..., :-1]], dim=-1), dim=-1)
    weight = s_a * att * (path_loss / t_next)[:, None, :] * real[:, None, :]  # [B, R, S]
    angle = s_p + phase
    re = (weight * torch.cos(angle)).sum(-1)
    im = (weight * torch.sin(angle)).sum(-1)
    return torch.sqrt(re * re + im * im + AMPLITUDE_EPS)
