"""The loaders' datasets: evaluation positions, and the training stream of batch numbers.

**Training batches are a pure function of (seed, batch number).**  Batch ``k`` belongs to epoch
``k // batches_per_epoch``, whose order is a permutation seeded by ``(seed, epoch)``; its neighbor
counts and draws come from a generator seeded by ``(seed, k)``
(:meth:`graf.data.datamodule.SpectrumDataModule.train_batch`).  The loader starts at the trainer's
``global_step``, so a run resumed from a checkpoint draws exactly the batches an uninterrupted run would,
and with ``num_workers > 0`` worker ``w`` builds batches ``k = w, w + W, ...`` (no shared generator, no
identical draws across workers, the same stream for every worker count).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

from torch.utils.data import DataLoader, Dataset, IterableDataset, get_worker_info


class Positions(Dataset):
    """Map-style dataset of positions 0..n-1 into a split's rows (evaluation)."""

    def __init__(self, n: int):
        self.n = int(n)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> int:
        return int(i)


class TrainBatchStream(IterableDataset):
    """Batch numbers ``start, start + 1, ...`` up to the end of ``start``'s epoch (``__len__``: one epoch).

    Each worker yields its share (``k % num_workers == worker id``); the DataLoader interleaves them back in
    order.  The batch itself is built by the loader's ``collate_fn`` from ``k`` alone."""

    def __init__(self, batches_per_epoch: int):
        self.batches_per_epoch = int(batches_per_epoch)
        self.start = 0

    def __len__(self) -> int:
        return self.batches_per_epoch

    def __iter__(self):
        info = get_worker_info()
        wid, nw = (0, 1) if info is None else (info.id, info.num_workers)
        end = (self.start // self.batches_per_epoch + 1) * self.batches_per_epoch
        return iter(range(self.start + wid, end, nw))


class StepLoader(DataLoader):
    """The training loader: sets the stream's first batch number from ``step_source()`` (the trainer's
    global step) every time it is iterated.  Its ``state_dict`` (saved in Lightning checkpoints) records the
    seed and batch number, and a resumed run with another seed is warned about."""

    def __init__(self, stream: TrainBatchStream, step_source: Callable[[], int], seed: int, **kwargs):
        super().__init__(stream, batch_size=None, shuffle=False, **kwargs)
        self.step_source, self.seed = step_source, int(seed)

    def __iter__(self):
        self.dataset.start = int(self.step_source())
        return super().__iter__()

    def state_dict(self) -> dict:
        return {"seed": self.seed, "next_batch": int(self.step_source()), "stream": "step-indexed"}

    def load_state_dict(self, state: dict) -> None:
        if int(state.get("seed", self.seed)) != self.seed:
            warnings.warn(
                f"resuming a run trained with data seed {state['seed']} with seed {self.seed}: the "
                "batches after the checkpoint differ from an uninterrupted run",
                stacklevel=2,
            )
