"""The study's sampler, by name: TPE, grid, NSGA-II or random, seeded so that a resumed or parallel sweep does not
replay the same proposals (:func:`make_sampler`)."""

from __future__ import annotations

import optuna

from graf.search.search_space import SearchSpace, SearchSpaceError


def make_sampler(
    name: str,
    space: SearchSpace,
    n_objectives: int,
    seed: int,
    population_size: int | None = None,
    grid_seed: int | None = None,
) -> optuna.samplers.BaseSampler:
    """``seed`` seeds a sampler of this process (varied per run and worker); a grid is shuffled by ``grid_seed``
    instead, the same in every process and run of a study: a trial stores its point as an index into the
    shuffled grid, so another shuffle (a resumed run, a second worker) would read those indices as other points,
    try some twice and leave others out."""
    name = (name or "auto").lower()
    if name == "auto":
        name = "nsga2" if n_objectives > 1 else ("grid" if space.all_categorical else "tpe")
    if name == "tpe":
        return optuna.samplers.TPESampler(seed=seed, multivariate=True)
    if name == "grid":
        if not space.all_categorical:
            raise SearchSpaceError(
                "sampler grid needs every parameter to be a choice(...): "
                f"{', '.join(k for k, d in space.distributions.items() if not hasattr(d, 'choices'))}"
            )
        return Grid(space.grid(), seed=seed if grid_seed is None else grid_seed)
    if name == "nsga2":
        if population_size is not None and int(population_size) < 2:
            raise SearchSpaceError(f"hydra.sweeper.population_size={population_size}: NSGA-II needs at least 2")
        return optuna.samplers.NSGAIISampler(seed=seed, population_size=int(population_size or 50))
    if name == "random":
        return optuna.samplers.RandomSampler(seed=seed)
    raise SearchSpaceError(f"hydra.sweeper.sampler={name}: one of auto, tpe, grid, nsga2, random")


class Grid(optuna.samplers.GridSampler):
    """Optuna's grid sampler without its ``study.stop()`` once the grid is covered (only allowed inside
    ``study.optimize``): this sweeper's loop ends the search itself (:meth:`OptunaSweep._next`)."""

    def after_trial(self, study, trial, state, values) -> None:
        return None
