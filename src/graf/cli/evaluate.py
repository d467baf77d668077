"""graf-eval: validate and test a method (or a checkpoint, ckpt_path=...) on a scene; writes results.json.

The work is :func:`graf.run.evaluate.evaluate`.  With ``ckpt_path`` and a ``model.*`` override but no
``model=``, the checkpoint's model config is added to the command line
(:func:`graf.run.evaluate.checkpoint_model_choice`) so that the key exists when Hydra composes.
"""

from __future__ import annotations

import sys

from omegaconf import DictConfig

from graf.cli.entry import graf_command
from graf.run.evaluate import checkpoint_model_choice, evaluate
from graf.run.evaluation import sweep_value


@graf_command("eval")
def _hydra_main(cfg: DictConfig) -> float:
    metrics, run = evaluate(cfg)
    return sweep_value(cfg, metrics, run)


def main() -> None:
    """The ``graf-eval`` command."""
    choice = checkpoint_model_choice(sys.argv[1:])
    if choice is not None:
        sys.argv.append(f"model={choice}")
    _hydra_main()


if __name__ == "__main__":
    main()
