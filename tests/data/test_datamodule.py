"""The datamodule: validation split, the step-indexed training stream, and per-item scene geometry."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from graf.bands import Band
from graf.data.datamodule import SpectrumDataModule
from graf.data.neighbors import NeighborSelector
from graf.data.scenes import NeRF2Scene
from graf.data.spectrum_set import DataFormatError
from graf.data.splits import carve_validation

S23 = NeRF2Scene("rfid_s23", "embedded:rfid_s23_200")
BAND = Band("915mhz", 915e6)


def _dm(scene=S23, band=BAND, **kw) -> SpectrumDataModule:
    kw.setdefault("batch_size", 8)
    dm = SpectrumDataModule(
        scene, band, kw.pop("neighbors", NeighborSelector(L=10, L_train=(3, 10), radius=10.0)), **kw
    )
    dm.setup()
    return dm


def test_validation_is_carved_from_training_and_never_meets_test():
    dm = _dm()
    fit, val, test, train = (set(dm.ids[r].tolist()) for r in (dm.fit_rows, dm.val_rows, dm.test_rows, dm.train_rows))
    assert len(val) == 16 and len(fit) == 144 and len(test) == 40  # 10% of the 160 training spectra
    assert val | fit == train and not val & fit
    assert not val & test and not fit & test
    # validation neighbors come from the fit spectra only; test neighbors from the whole training split
    for split, pool in (("val", fit), ("test", train)):
        rows, idx, mask = dm.split_neighbors(split)
        used = set(dm.ids[idx[mask]].tolist())
        assert used <= pool and not used & set(dm.ids[rows].tolist())
    # seeded by val_seed, not by the run's seed
    assert torch.equal(_dm(seed=5).val_rows, dm.val_rows)
    assert not torch.equal(_dm(val_seed=1).val_rows, dm.val_rows)


def test_training_targets_and_neighbors_are_fit_spectra_only():
    dm = _dm()
    fit = set(dm.fit_rows.tolist())
    for k in range(40):
        b = dm.train_batch(k)
        assert set(b["tgt_index"].tolist()) <= fit
        assert set(b["src_index"][b["src_mask"]].tolist()) <= fit
        assert not (b["src_index"] == b["tgt_index"][:, None])[b["src_mask"]].any()


def test_a_training_split_too_small_to_carve_is_refused(make_scene):
    with pytest.raises(DataFormatError, match="training split holds 1 spectrum"):
        carve_validation(np.array([3]), 0.1, 0, "scene")
    with pytest.raises(ValueError, match="val_fraction"):
        carve_validation(np.arange(10), 0.0, 0, "scene")
    fit, val = carve_validation(np.arange(2), 0.1, 0, "scene")
    assert len(fit) == 1 and len(val) == 1


def _stream(dm, start=0, n=None):
    dm._global_step = lambda: start  # what the trainer's global step would be
    out = []
    for b in dm.train_dataloader():
        out.append(b)
        if n is not None and len(out) == n:
            break
    return out


def test_training_batches_are_a_function_of_seed_and_batch_number():
    dm = _dm(batch_size=8)
    full = _stream(dm)
    assert len(full) == dm.batches_per_epoch == 18
    # an epoch visits every fit spectrum once
    assert sorted(torch.cat([b["tgt_index"] for b in full]).tolist()) == sorted(dm.fit_rows.tolist())
    # resuming at batch 7 gives exactly batches 7.. of the uninterrupted stream
    resumed = _stream(dm, start=7)
    assert len(resumed) == 11
    for a, b in zip(full[7:], resumed):
        assert all(torch.equal(a[k], b[k]) for k in a)
    # the next epoch has another order; another seed another stream
    nxt = _stream(dm, start=18, n=1)[0]
    assert not torch.equal(nxt["tgt_index"], full[0]["tgt_index"])
    other = _stream(_dm(batch_size=8, seed=1), n=1)[0]
    assert not torch.equal(other["tgt_index"], full[0]["tgt_index"])


def test_workers_build_the_same_stream_without_repeating_draws():
    dm0 = _dm(batch_size=4, num_workers=0)
    dm2 = _dm(batch_size=4, num_workers=2)
    a, b = _stream(dm0, n=12), _stream(dm2, n=12)
    for x, y in zip(a, b):
        assert torch.equal(x["tgt_index"], y["tgt_index"]) and torch.equal(x["src_index"], y["src_index"])
    # batches built by different workers draw different neighbor counts (no shared, copied generator)
    counts = [tuple(x["src_mask"].sum(1).tolist()) for x in b]
    assert len(set(counts)) > 6


def test_batches_carry_each_items_scene_geometry(make_scene):
    tiny = NeRF2Scene("tiny", str(make_scene(n=24, name="tiny")))
    dm = _dm(
        scene=[S23, tiny],
        band=[BAND, Band("2.4ghz", 2.412e9)],
        batch_size=6,
        neighbors=NeighborSelector(L=3, L_train=(2, 4), radius=None),
    )
    n_s23 = len(dm.sets[0].ids)
    assert dm.scene_name == "rfid_s23+tiny"
    seen = set()
    for k in range(2 * dm.batches_per_epoch):
        b = dm.train_batch(k)
        s = b["scene_index"]
        seen |= set(s.tolist())
        assert torch.equal(s, (b["tgt_index"] >= n_s23).long())
        assert torch.allclose(
            b["wavelength"], torch.where(s == 0, torch.tensor(BAND.wavelength), torch.tensor(299_792_458.0 / 2.412e9))
        )
        assert torch.equal(b["gw_pos"], dm.gw_pos[s]) and torch.equal(b["ray_length"], dm.ray_length[s])
        # neighbors never cross scenes
        src_scene = dm.row_scene[b["src_index"]]
        assert (src_scene == s[:, None])[b["src_mask"]].all()
    assert seen == {0, 1}
    rows, idx, mask = dm.split_neighbors("test")
    assert (dm.row_scene[idx] == dm.row_scene[rows][:, None])[mask].all()
    with pytest.raises(AttributeError, match="2 scenes"):
        _ = dm.data


def test_the_measured_spacing_is_the_median_nearest_neighbor_distance_and_grows_as_the_survey_thins():
    full, thin = _dm(), _dm(measured_fraction=0.2, measured_seed=0)
    full.setup("fit"), thin.setup("fit")
    pos = full.positions[full.measured_rows].double()
    d = torch.cdist(pos, pos) + torch.diag(torch.full((len(pos),), float("inf"), dtype=torch.float64))
    assert full.measured_spacing() == pytest.approx(float(d.min(dim=1).values.median()))
    assert thin.measured_spacing() > full.measured_spacing()
    assert full.split_summary()["measured_spacing_m"] == full.measured_spacing()


def test_the_record_states_the_nearest_neighbor_the_tested_targets_use():
    """results.json ``splits.nearest_neighbor_used``: the median over the tested targets of the distance to the
    nearest neighbor they read, in metres and wavelengths; with ``exclude_within`` it lies beyond the exclusion."""
    dense = _dm(neighbors=NeighborSelector(L=10, L_train=(3, 10), radius=None))
    sparse = _dm(neighbors=NeighborSelector(L=10, L_train=(3, 10), radius=None, exclude_within=0.5))
    rows, index, mask = dense.split_neighbors(dense.eval_split)
    d = (dense.positions[index] - dense.positions[rows][:, None]).double().norm(dim=-1).masked_fill(~mask, float("inf"))
    got = dense.nearest_neighbor_used()
    assert got["median_m"] == pytest.approx(float(d.min(dim=1).values.median()), abs=1e-6)
    assert got["median_wavelengths"] == pytest.approx(got["median_m"] / BAND.wavelength, abs=1e-3)
    assert got["n_targets"] == len(rows) and dense.split_summary()["nearest_neighbor_used"] == got
    far = sparse.nearest_neighbor_used()
    assert far["median_wavelengths"] >= 0.5 > got["median_wavelengths"]
