"""KNN-DL: IDW KNN at initialisation, masking, edge cases, upsampling, and training through the real configs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from torch import nn

from graf.models.knn import KNNModule
from graf.models.knn_dl import KNNDLModule, upsample_maps
from graf.run.build import build_datamodule
from graf.run.train import train


@pytest.fixture
def batches(compose_cfg):
    """A test batch (L = 10, no padding) and a training batch (L drawn from 3..10, padded) of rfid_s23."""
    cfg = compose_cfg("eval", ("scene=rfid_s23", "neighbors=random_3_10", "data.batch_size=4"))
    _, _, _, dm = build_datamodule(cfg)
    dm.setup()
    test, trn = next(iter(dm.test_dataloader())), next(iter(dm.train_dataloader()))
    trn["src_mask"][0, 2:] = False  # make sure some neighbors are padded
    return test, trn


def _randomised(**kwargs) -> KNNDLModule:
    """A model whose maps are not zero (as after training): random last layer."""
    torch.manual_seed(0)
    m = KNNDLModule(**{"max_rank": 10, **kwargs})
    nn.init.normal_(m.net.decoder[-1].weight, std=1.0)
    nn.init.normal_(m.net.decoder[-1].bias, std=1.0)
    return m


def test_initial_model_is_idw_knn(batches):
    for batch in batches:
        with torch.no_grad():
            pred = KNNDLModule(max_rank=10).predict_spectra(batch)
            knn = KNNModule().predict_spectra(batch)
        assert pred.shape == (4, 90, 360) and torch.isfinite(pred).all()
        assert torch.allclose(pred, knn, atol=1e-5)


def test_padded_neighbors_get_zero_weight_and_weights_sum_to_one(batches):
    _, batch = batches
    m = _randomised()
    with torch.no_grad():
        w = m.fusion_weights(batch)
        pred = m.predict_spectra(batch)
        batch["src_spectra"][~batch["src_mask"]] = float("nan")  # what a padded slot holds must not matter
        again = m.predict_spectra(batch)
    pad = ~batch["src_mask"]
    assert pad.any() and (w[pad] == 0).all()
    assert torch.allclose(w.sum(dim=1), torch.ones(4, 90, 360), atol=1e-5)
    assert (w < 0).any()  # the signed correction is active
    assert torch.equal(pred, again)
    convex = _randomised(signed_scale=0.0)
    with torch.no_grad():
        assert (convex.fusion_weights(batch) >= 0).all()


def test_one_neighbor_and_a_co_located_neighbor(batches):
    test, _ = batches
    m = _randomised()
    one = dict(test, src_mask=torch.zeros_like(test["src_mask"]))
    one["src_mask"][:, 0] = True
    with torch.no_grad():
        w = m.fusion_weights(one)
    assert torch.allclose(w[:, 0], torch.ones(4, 90, 360)) and (w[:, 1:] == 0).all()
    same = dict(test, src_pos=test["src_pos"].clone())
    same["src_pos"][:, 1] = same["tgt_pos"]
    pred = m.predict_spectra(same)
    pred.mean().backward()
    assert torch.isfinite(pred).all()
    assert all(torch.isfinite(p.grad).all() for p in m.parameters() if p.grad is not None)
    with torch.no_grad():  # at initialisation the co-located neighbor takes all the weight, as IDW
        assert torch.allclose(KNNDLModule(max_rank=10).predict_spectra(same), same["src_spectra"][:, 1], atol=1e-6)


def test_upsampling_is_circular_in_azimuth_and_aligned():
    az = (torch.arange(72) + 0.5) * 5 - 0.5 + 1  # cell centres in degrees
    el = (torch.arange(18) + 0.5) * 5 - 0.5 + 1
    coarse = torch.sin(torch.deg2rad(az))[None, :] + el[:, None] / 90
    fine = upsample_maps(coarse[None])[0]
    true = torch.sin(torch.deg2rad(torch.arange(1, 361.0)))[None, :] + torch.arange(1, 91.0)[:, None] / 90
    inner = slice(3, 87)  # elevation is edge-clamped beyond the outer cell centres
    assert (fine[inner] - true[inner]).abs().max() < 2e-3  # including azimuth 1 deg and 360 deg


def test_bad_config_values_name_the_key():
    with pytest.raises(ValueError, match="model.map_size"):
        KNNDLModule(max_rank=10, map_size=(7, 72))
    with pytest.raises(ValueError, match="model.signed_scale"):
        KNNDLModule(max_rank=10, signed_scale=-1)
    with pytest.raises(ValueError, match="model.lr"):
        KNNDLModule(max_rank=10, lr=0)


def test_twenty_steps_on_one_batch_lower_the_loss(batches):
    batch = {k: v[:2] for k, v in batches[1].items()}  # two targets, one with padded neighbors
    torch.manual_seed(0)
    m = KNNDLModule(max_rank=10, lr=1e-2)
    opt = torch.optim.Adam(m.parameters(), lr=m.lr)
    losses = []
    for _ in range(20):
        loss = nn.functional.mse_loss(m.predict_spectra(batch), batch["tgt_spectrum"])
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.9 * losses[0]


def test_two_training_steps_through_the_real_configs(compose_cfg):
    cfg = compose_cfg(
        "train",
        (
            "scene=rfid_s23",
            "model=knn_dl",
            "trainer.max_steps=2",
            "data.batch_size=2",
            "baselines={}",
            "plot_count=1",
            "data.test_subset=2",
        ),
    )
    metrics, _ = train(cfg)
    r = json.loads((Path(cfg.paths.output_dir) / "results.json").read_text())
    assert r["method"] == "knn-dl" and r["global_step"] == 2
    assert 10_000 < r["trainable_parameters"] < 100_000
    assert all(torch.isfinite(torch.tensor(v)) for v in metrics.values())
