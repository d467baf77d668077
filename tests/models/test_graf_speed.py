"""GRaF's fast paths give the same answers as the plain ones: ray-box voxels, per-scene voxel tables and
encoded-spectrum caches at evaluation, rays grouped by voxel count, the explicit-matmul attention kernel, and
windowed ray attention for large scenes."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from graf.geometry.grid import local_directions
from graf.geometry.rays import box_segments, segment_samples
from graf.models.graf.attention import math_attention
from graf.models.graf.inference import ray_transformer
from tests.models.test_graf_model import _datamodule, _eval_batch, _small


@pytest.fixture
def tiny(make_scene):
    return _datamodule(make_scene(n=16))


def test_rays_run_from_their_entry_to_their_exit_of_the_box():
    box = torch.tensor([[0.0, 0.0, 0.0], [4.0, 3.0, 2.5]])
    gw = torch.tensor([1.0, 1.5, 1.0])
    dirs = torch.tensor([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [0.6, 0.8, 0.0]])
    t_in, t_out = box_segments(gw, torch.eye(3), box, dirs)
    assert torch.allclose(t_in, torch.zeros(4, dtype=t_in.dtype))
    assert torch.allclose(t_out, torch.tensor([3.0, 1.5, 1.5, 1.5 / 0.8], dtype=t_out.dtype))
    # every voxel centre of every grid ray lies inside the box (nothing sampled outside the scene)
    grid = local_directions(dtype=torch.float64)
    rot = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    t_in, t_out = box_segments(gw, rot, box, grid)
    samples, step = segment_samples(t_in, t_out, 0.125, 10_000)
    assert torch.all(step <= 0.125 + 1e-9) and int(samples.max()) == math.ceil(float(t_out.max()) / 0.125 - 1e-6)
    s = torch.arange(int(samples.max()), dtype=torch.float64)
    dist = t_in[:, None] + (s + 0.5) * step[:, None]
    pts = gw.double() + dist[..., None] * (grid @ rot.double().T)[:, None, :]
    real = s[None, :] < samples[:, None]
    inside = ((pts >= box[0].double() - 1e-9) & (pts <= box[1].double() + 1e-9)).all(-1)
    assert inside[real].all()
    # a gateway outside the box: rays enter late or miss (a zero-length segment, one voxel, nothing infinite)
    t_in, t_out = box_segments(torch.tensor([-1.0, 1.5, 1.25]), torch.eye(3), box, grid)
    assert torch.isfinite(t_in).all() and torch.isfinite(t_out).all() and (t_out >= t_in).all()
    hit = t_out > t_in
    assert 0 < int(hit.sum()) < len(grid) and torch.all(t_in[hit] >= 1.0 - 1e-9)


def test_cached_and_grouped_inference_equals_the_plain_forward(tiny):
    """predict_spectra (pixels sorted by voxel count, chunked, scene voxel table and encoder cache) equals
    render over all pixels with autograd on (no caches), for any chunk size."""
    model = _small(max_samples=8, chunk_rays=777)
    b = _eval_batch(tiny)
    assert len(set(model.ray_table(b, 0)["samples"].tolist())) > 1  # rays of several lengths
    with torch.no_grad():
        fast = model.predict_spectra(b)
        again = model.predict_spectra(b)  # from the caches
        model.chunk_rays = 40_000
        whole = model.predict_spectra(b)
    plain = model.render(model.prepare(b), torch.arange(32400).expand(2, -1)).detach().view(2, 90, 360)
    assert (
        torch.allclose(fast, plain, atol=1e-5)
        and torch.allclose(fast, again, atol=1e-6)  # bitwise too, unless the machine's load changed the threads
        and torch.allclose(whole, plain, atol=1e-5)
    )


@pytest.mark.parametrize("shape", [(7, 10, 13, 8), (3, 1, 50, 16)])
def test_math_attention_kernel_equals_sdpa(shape, monkeypatch):
    import graf.models.graf.attention as attention

    monkeypatch.setattr(attention, "MATH_SCORES_PER_PIECE", 2000)  # several pieces
    g = torch.Generator().manual_seed(0)
    B, H, N, D = shape
    q, k, v = (torch.randn(B, H, N, D, generator=g) for _ in range(3))
    assert torch.allclose(math_attention(q, k, v), F.scaled_dot_product_attention(q, k, v), atol=1e-5)
    mask = torch.rand(B, 1, 1, N, generator=g) > 0.3
    mask[..., 0] = True
    assert torch.allclose(
        math_attention(q, k, v, mask), F.scaled_dot_product_attention(q, k, v, attn_mask=mask), atol=1e-5
    )


def test_kernels_give_the_same_model(tiny):
    b = _eval_batch(tiny)
    pix = torch.arange(0, 32400, 53).expand(2, -1)
    out = {}
    for kernel in ("sdpa", "math", "auto"):
        model = _small(max_samples=8, attention=kernel)
        with torch.no_grad():
            out[kernel] = model.render(model.prepare(b), pix)
    assert torch.allclose(out["sdpa"], out["math"], atol=1e-5) and torch.allclose(out["sdpa"], out["auto"], atol=1e-5)


def test_windowed_ray_attention(tiny):
    """ray_window W: full attention when a ray has at most W voxels; otherwise attention within windows of W
    voxels (each window's result equals the block applied to that window alone)."""
    b = _eval_batch(tiny)
    pix = torch.arange(0, 32400, 53).expand(2, -1)
    full, wide = _small(max_samples=8), _small(max_samples=8, ray_window=8)
    with torch.no_grad():
        assert torch.equal(full.render(full.prepare(b), pix), wide.render(wide.prepare(b), pix))
    model = _small(max_samples=8, ray_window=3)
    v = torch.randn(5, 8, model.d_model)
    with torch.no_grad():
        got = ray_transformer(model.ray_blocks, v, model.ray_window, fast=False)
        expect = v
        for blk in model.ray_blocks:
            expect = torch.cat([blk(expect[:, 0:3]), blk(expect[:, 3:6]), blk(expect[:, 6:8])], dim=1)
    assert torch.allclose(got, expect, atol=1e-6)
    with torch.no_grad():
        out = model.predict_spectra(b)
    assert torch.isfinite(out).all()
