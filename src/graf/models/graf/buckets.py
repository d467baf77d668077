"""Rays grouped for a training step: few groups of padded rays instead of one group per voxel count.

A step's rays have many voxel counts S (each ray is cut at its own exit of the scene box: 1 to 32 on the CPU
presets), and every group runs the whole ray pass (tens of small operations forward, more backward).  At GRaF's
widths a group's fixed cost is that of some hundreds of voxels, so one group per S spends much of a step on
overhead.  :func:`buckets` joins consecutive counts into groups whose rays are padded to the group's largest S;
padded voxels are masked out of the ray transformer's keys and of the mean over the ray, so each ray's output is
the same function as in its own group (within float rounding; tests/models/test_graf_fast_training.py).

The partition minimises ``groups x group_cost + padded voxels`` exactly (dynamic programming over the sorted
counts; a few dozen counts at most).  Choosing it reads the counts on the host, a synchronisation a GPU cannot
afford: there (:func:`static_shapes`) a step's rays go through **one** group padded to the scene's longest ray
(its length a Python int of the scene's table), with the mask made on the device and never read back.
"""

from __future__ import annotations

import torch

# A group's fixed cost in voxels (forward + backward of one ray pass), measured on the 2-core Xeon with the
# study preset (graf_cpu_scenes_ray_weights): a padded group of 1,024 rays x 24 voxels against 24 groups of 43 rays.
GROUP_COST_VOXELS = 384


def buckets(counts: dict[int, int], group_cost: float = GROUP_COST_VOXELS) -> list[list[int]]:
    """Voxel counts ``{S: rays with S voxels}`` -> groups of consecutive counts (ascending); each group is run
    padded to its largest S.  Minimises ``len(groups) * group_cost + sum(rays * largest S of their group)``."""
    sizes = sorted(counts)
    k = len(sizes)
    best = [0.0] + [float("inf")] * k  # best[i]: cost of the first i counts
    cut = [0] * (k + 1)
    for i in range(1, k + 1):
        rays = 0
        for j in range(i, 0, -1):  # the last group is sizes[j-1 : i], padded to sizes[i-1]
            rays += counts[sizes[j - 1]]
            c = best[j - 1] + group_cost + rays * sizes[i - 1]
            if c < best[i]:
                best[i], cut[i] = c, j - 1
    groups, i = [], k
    while i > 0:
        groups.append(sizes[cut[i] : i])
        i = cut[i]
    return groups[::-1]


def voxel_mask(samples: torch.Tensor, S: int) -> torch.Tensor | None:
    """``[n, S]`` True for each ray's own voxels (``samples [n]`` of them), or None when every ray has ``S``."""
    if bool((samples == S).all()):
        return None
    return padded_mask(samples, S)


def ray_groups(samples: torch.Tensor, padded: bool) -> list[tuple[torch.Tensor, int, torch.Tensor | None]]:
    """A step's rays by voxel count (``samples [n]``): ``(indices, S, per-ray counts or None)`` per group; one group
    per count, or (``padded``) the least-cost groups of :func:`buckets`, each padded to its largest S."""
    sizes, counts = torch.unique(samples, return_counts=True)
    if not padded:
        return [((samples == S).nonzero().flatten(), int(S), None) for S in sizes.tolist()]
    out = []
    for group in buckets(dict(zip(sizes.tolist(), counts.tolist()))):
        sel = ((samples >= group[0]) & (samples <= group[-1])).nonzero().flatten()
        out.append((sel, int(group[-1]), samples[sel]))
    return out


def static_shapes(model, device: torch.device) -> bool:
    """Whether a step runs the static path (one padded group, masks on the device, nothing read back to the host):
    ``model.static_shapes`` if set (True or False), else on every device but a CPU (where exact groups pay)."""
    flag = getattr(model, "static_shapes", None)
    return device.type != "cpu" if flag is None else bool(flag)


def padded_mask(samples: torch.Tensor, S: int) -> torch.Tensor:
    """``[n, S]`` True for each ray's own voxels (``samples [n]``), made on the device without reading it."""
    return torch.arange(S, device=samples.device)[None, :] < samples[:, None]
