"""graf's Optuna sweeper for Hydra (``hydra/sweeper=graf_optuna``), discovered through the ``hydra_plugins``
namespace.  The work is in :mod:`graf.sweeper.optuna_sweeper`; this package only registers the plugin and its
config, importing nothing heavy (Hydra imports every plugin at start-up)."""
