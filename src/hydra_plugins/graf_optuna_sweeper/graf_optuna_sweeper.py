"""``hydra/sweeper=graf_optuna``: Optuna >= 4 searches with persistent, resumable, failure-tolerant studies.

    graf-train -m hparams_search=neighbor_count            # conf/hparams_search/*.yaml select this sweeper

Settings (``hydra.sweeper.*``): :class:`graf.sweeper.settings.GrafOptunaSweeperConf`, their one home; behaviour:
:mod:`graf.sweeper.optuna_sweeper`.
"""

from typing import Any

from hydra.core.config_store import ConfigStore
from hydra.plugins.sweeper import Sweeper
from omegaconf import OmegaConf

from graf.sweeper.settings import GrafOptunaSweeperConf, HeartbeatConf, PrunerConf, sweeper_settings

__all__ = ["GrafOptunaSweeper", "GrafOptunaSweeperConf", "HeartbeatConf", "PrunerConf", "sweeper_settings"]


ConfigStore.instance().store(group="hydra/sweeper", name="graf_optuna", node=GrafOptunaSweeperConf, provider="graf")


class GrafOptunaSweeper(Sweeper):
    def __init__(self, **kwargs: Any) -> None:
        # lazy: Hydra imports every plugin module when any graf command starts; Optuna is imported only by a search
        from graf.sweeper.optuna_sweeper import OptunaSweep

        kwargs = {
            k: OmegaConf.to_container(v, resolve=True) if OmegaConf.is_config(v) else v for k, v in kwargs.items()
        }
        self.sweep_impl = OptunaSweep(**kwargs)

    def setup(self, *, hydra_context, task_function, config) -> None:
        self.sweep_impl.setup(hydra_context=hydra_context, task_function=task_function, config=config)

    def sweep(self, arguments: list[str]) -> Any:
        return self.sweep_impl.sweep(arguments)
