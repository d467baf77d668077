"""One run, as plain functions of a composed config: what graf-train and graf-eval do, callable from Python or a
notebook without a Hydra app.

- :mod:`.config`: where the configs are, the scenes and bands a config selects, held-out layouts, the task wrapper;
- :mod:`.build`: bands, scenes, neighbor selector, datamodules, model, loggers, callbacks and trainer from a config;
- :mod:`.evaluation`: validation, test, neighbor reliance and baselines of a built run;
- :mod:`.record`: the run record (``results.json``) and what a task returns; :mod:`.writer`: the record made,
  written and printed;
- :mod:`.finetune`, :mod:`.resume`: starting from a checkpoint's weights, resuming or stopping a training run;
- :mod:`.train` (graf-train), :mod:`.evaluate` (graf-eval): ``train(cfg) -> Results``, ``evaluate(cfg) -> Results``.
- :mod:`.overrides`, :mod:`.command`: a command line brought up to date and checked before Hydra composes, and
  how a command ends (a user error on one line, a multirun's failed jobs counted).

The tools over many runs are in :mod:`graf.studies`, the case studies in :mod:`graf.cases` and the simulator's
commands in :mod:`graf.sim_commands`.

Compose a config with Hydra's compose API and call a task::

    from hydra import compose, initialize_config_module
    from graf.run.train import train

    with initialize_config_module("graf.conf", version_base="1.3"):
        cfg = compose("train", overrides=["experiment=graf_rfid_s23", "paths.output_dir=/tmp/run"])
    metrics, run = train(cfg)  # run.record: the results.json written; run.built: model, datamodules, trainer
"""
