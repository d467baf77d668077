"""One run, as plain functions of a composed config: what graf-train and graf-eval do, callable from Python or a
notebook without a Hydra app.

- :mod:`.build`: bands, scenes, neighbor selector, datamodules, model, loggers, callbacks and trainer from a config;
- :mod:`.evaluation`: validation, test, neighbor reliance and baselines of a built run;
- :mod:`.record`: the run record (``results.json``) and what a task returns; :mod:`.writer`: the record made,
  written and printed;
- :mod:`.finetune`, :mod:`.resume`: starting from a checkpoint's weights, resuming or stopping a training run;
- :mod:`.train` (graf-train), :mod:`.evaluate` (graf-eval): ``train(cfg) -> Results``, ``evaluate(cfg) -> Results``.

Where the configs are, what a config selects, the task wrapper and how a command ends are the command framework's
(:mod:`graf.app`); the tools that run many runs are in :mod:`graf.studies`, the reports over their records in
:mod:`graf.reports`, the case studies in :mod:`graf.case_studies` and the simulator's tasks in :mod:`graf.sim`.

Compose a config with Hydra's compose API and call a task::

    from hydra import compose, initialize_config_module
    from graf.run.train import train

    with initialize_config_module("graf.conf", version_base="1.3"):
        cfg = compose("train", overrides=["experiment=graf_rfid_s23", "paths.output_dir=/tmp/run"])
    metrics, run = train(cfg)  # run.record: the results.json written; run.built: model, datamodules, trainer
"""
