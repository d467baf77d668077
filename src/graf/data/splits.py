"""The splits of each scene's spectra, and the seeds that cut them.

Each scene's training split (from its files) is cut, with a seeded permutation (``val_seed``, the same whatever
the run's ``seed``), into a *validation* part (``val_fraction`` of it, at least one spectrum) and the *fit* part
(the rest):

- training targets and their neighbors: fit spectra only (never the target itself);
- validation targets: the validation spectra, neighbors from the fit spectra only (so nothing a model is
  chosen on was trained on, and validation conditions match training);
- test targets: the test split, neighbors from the whole training split (fit + validation: at test time
  every measured spectrum is known).

The validation and test splits never share a spectrum; nothing is ever chosen on the test split.

**Measured fraction** (fine-tuning, ``conf/finetune``).  With ``measured_fraction`` (e.g. 0.2), only a seeded
part of each scene's training split counts as measured (``measured_seed``; at least 2 spectra, else an error):
the validation and fit parts are cut from it, and it is the pool test neighbors come from.  With
``test_pool="train_split"`` test neighbors come from the whole training split instead (the paper's zero-shot
protocol), while fitting still sees the measured part only.  The test split is never touched.
"""

from __future__ import annotations

import numpy as np

from graf.data.spectrum_set import DataFormatError
from graf.errors import ConfigError

# what an evaluation may select (data.eval_split): each a split's targets with their neighbor pool
EVAL_SPLITS = ("test", "val", "train")
TEST_POOLS = ("measured", "train_split")


def measured_part(train_rows: np.ndarray, fraction: float | None, seed: int, where: str) -> np.ndarray:
    """The seeded ``fraction`` of ``train_rows`` that is measured (rounded, at least 2: one to validate on, one
    to fit and take neighbors from); all of them when ``fraction`` is None."""
    n = len(train_rows)
    if fraction is None or fraction >= 1.0:
        return np.sort(train_rows)
    k = int(round(n * fraction))
    if k < 2:
        raise DataFormatError(
            where,
            f"a measured fraction of {fraction:g} of its {n} training spectra leaves {k}: at "
            "least 2 are needed (one to validate on, one to fit and take neighbors from); "
            "use a larger fraction or more spectra",
        )
    perm = np.random.default_rng(int(seed)).permutation(n)
    return np.sort(train_rows[perm[:k]])


def derangement(n: int, rng: np.random.Generator) -> np.ndarray:
    """A seeded permutation of ``range(n)`` with no fixed point (n >= 2): a uniform random n-cycle (Sattolo's
    algorithm)."""
    p = np.arange(n)
    for i in range(n - 1, 0, -1):
        j = int(rng.integers(0, i))  # j < i: never i itself
        p[i], p[j] = p[j], p[i]
    return p


def mixed_seed(*parts: int) -> int:
    """A 63-bit seed from integers (numpy's SeedSequence: well mixed, stable across versions)."""
    state = np.random.SeedSequence([int(p) & 0xFFFFFFFF for p in parts]).generate_state(1, np.uint64)[0]
    return int(state) & 0x7FFFFFFFFFFFFFFF


def carve_validation(train_rows: np.ndarray, fraction: float, seed: int, where: str) -> tuple[np.ndarray, np.ndarray]:
    """``(fit_rows, val_rows)``: a seeded ``fraction`` (rounded, at least 1) of ``train_rows`` for validation."""
    n = len(train_rows)
    if not 0.0 < fraction < 1.0:
        raise ConfigError(
            f"data.val_fraction must be in (0, 1), got {fraction}: validation is carved from each "
            "scene's training split (at least one spectrum), so 0 and 1 leave nothing to validate or fit on"
        )
    if n < 2:
        raise DataFormatError(
            where,
            f"the training split holds {n} spectrum(s): at least 2 are needed, one to "
            "validate on and one to train on and take neighbors from",
        )
    n_val = min(max(int(round(n * fraction)), 1), n - 1)
    perm = np.random.default_rng(int(seed)).permutation(n)
    return np.sort(train_rows[perm[n_val:]]), np.sort(train_rows[perm[:n_val]])
