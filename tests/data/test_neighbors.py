"""The one neighbor selector every method uses."""

from __future__ import annotations

import pytest
import torch

from graf.data.neighbors import NeighborSelector, NoNeighborsError, select_neighbors


def _brute(tp, cp, L, tid=None, cid=None):
    out = []
    for t in range(len(tp)):
        d = [((tp[t] - cp[m]).norm().item(), m) for m in range(len(cp)) if tid is None or cid[m] != tid[t]]
        out.append([m for _, m in sorted(d)[:L]])
    return out


def test_matches_brute_force_and_is_sorted():
    g = torch.Generator().manual_seed(0)
    cp = torch.rand(50, 3, generator=g, dtype=torch.float64)
    tp = torch.rand(7, 3, generator=g, dtype=torch.float64)
    nb = select_neighbors(tp, cp, 5)
    assert nb.index.tolist() == _brute(tp, cp, 5)
    assert bool((nb.distance[:, 1:] >= nb.distance[:, :-1]).all())
    assert bool(nb.mask.all())


def test_never_returns_target_itself_even_when_colocated():
    cp = torch.tensor([[0.0, 0, 0], [0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]], dtype=torch.float64)
    ids = torch.tensor([10, 11, 12, 13])
    nb = select_neighbors(cp, cp, 2, target_ids=ids, cand_ids=ids)
    for t in range(4):
        assert int(ids[t]) not in ids[nb.index[t]].tolist()
    # id 10's co-located twin (id 11) is a valid neighbor at distance 0
    assert nb.index[0, 0] == 1 and float(nb.distance[0, 0]) == 0.0


def test_L_one_and_L_larger_than_available():
    cp = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0]])
    tp = torch.tensor([[0.9, 0, 0]])
    assert select_neighbors(tp, cp, 1).index.tolist() == [[1]]
    nb = select_neighbors(tp, cp, 10)
    assert nb.mask.tolist() == [[True, True, True]] and bool(nb.short.all())
    assert nb.index.tolist() == [[1, 0, 2]]


def test_radius_is_widened_when_too_few_inside():
    cp = torch.tensor([[0.1, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [5.0, 0, 0]])
    tp = torch.zeros(1, 3)
    nb = select_neighbors(tp, cp, 3, radius=0.5)
    assert nb.index.tolist() == [[0, 1, 2]] and bool(nb.widened.all())
    nb = select_neighbors(tp, cp, 1, radius=0.5)
    assert nb.index.tolist() == [[0]] and not bool(nb.widened.any())


def test_exclude_within_and_no_candidates_error():
    cp = torch.tensor([[0.01, 0, 0], [0.2, 0, 0], [0.5, 0, 0]])
    tp = torch.zeros(1, 3)
    nb = select_neighbors(tp, cp, 3, exclude_within=0.1)
    assert nb.index[0][nb.mask[0]].tolist() == [1, 2]
    with pytest.raises(NoNeighborsError, match="no candidate neighbor"):
        select_neighbors(tp, cp, 3, exclude_within=10.0)


def test_ties_are_deterministic_in_candidate_order():
    cp = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]])
    nb = select_neighbors(torch.zeros(1, 3), cp, 3)
    assert nb.index.tolist() == [[0, 1, 2]]


def test_per_target_L_with_mask():
    cp = torch.arange(10, dtype=torch.float64).view(-1, 1).repeat(1, 3)
    tp = torch.zeros(3, 3, dtype=torch.float64)
    nb = select_neighbors(tp, cp, torch.tensor([1, 3, 2]))
    assert nb.mask.sum(1).tolist() == [1, 3, 2]
    assert nb.index.shape == (3, 3) and nb.index[0, 1:].tolist() == [0, 0]


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(ValueError, match=r"target_pos must be \[T, 3\]"):
        select_neighbors(torch.zeros(3), torch.zeros(4, 3), 2)
    with pytest.raises(ValueError, match="finite"):
        select_neighbors(torch.full((1, 3), float("nan")), torch.zeros(4, 3), 2)
    with pytest.raises(ValueError, match="L must be >= 1"):
        select_neighbors(torch.zeros(1, 3), torch.zeros(4, 3), 0)
    with pytest.raises(ValueError, match="L_train"):
        NeighborSelector(L=4, L_train=(5, 3), radius=10.0)


def test_selector_units_are_wavelengths_and_training_draws_L_in_range():
    lam = 0.5
    cp = torch.linspace(0, 10, 101, dtype=torch.float64).view(-1, 1) * torch.tensor([[1.0, 0, 0]], dtype=torch.float64)
    sel = NeighborSelector(L=4, L_train=(3, 6), radius=None, exclude_within=0.5)
    tp = torch.tensor([[5.0, 0, 0]], dtype=torch.float64)
    nb = sel.select(tp, cp, lam)
    assert float(nb.distance[0].min()) >= 0.25 - 1e-9  # 0.5 wavelengths = 0.25 m
    g = torch.Generator().manual_seed(0)
    counts = sel.select(tp.repeat(200, 1), cp, lam, train=True, generator=g).counts
    assert set(counts.tolist()) == {3, 4, 5, 6}


def test_selector_warns_when_widening_or_short():
    sel = NeighborSelector(L=3, L_train=(3, 3), radius=1.0)
    cp = torch.tensor([[0.1, 0, 0], [5.0, 0, 0], [9.0, 0, 0]])
    with pytest.warns(UserWarning, match="widened"):
        sel.select(torch.zeros(1, 3), cp, wavelength=1.0)
    with pytest.warns(UserWarning, match="only 2 candidates"):
        NeighborSelector(L=5, L_train=(3, 10), radius=None).select(torch.zeros(1, 3), cp[:2], wavelength=1.0)
