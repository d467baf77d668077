"""The run pipeline, as plain functions of a composed config: what every command does, callable from Python or a
notebook without a Hydra app.

- :mod:`.config`: where the configs are, the scenes and bands a config selects, held-out layouts, the task wrapper;
- :mod:`.build`: bands, scenes, neighbour selector, datamodules, model, loggers, callbacks and trainer from a config;
- :mod:`.testing`: validation, test, neighbour reliance and baselines of a built run; ``results.json``;
- :mod:`.train` (graf-train), :mod:`.evaluate` (graf-eval): ``train(cfg) -> Results``, ``evaluate(cfg) -> Results``;
- :mod:`.table`, :mod:`.report`, :mod:`.bench`, :mod:`.bench_sim`, :mod:`.pareto`, :mod:`.curves`, :mod:`.oracle`,
  :mod:`.simulate`, :mod:`.synthesize`, :mod:`.show_scenes`: the other commands' work.

Compose a config with Hydra's compose API and call a task::

    from hydra import compose, initialize_config_module
    from graf.pipeline.train import train

    with initialize_config_module("graf.conf", version_base="1.3"):
        cfg = compose("train", overrides=["experiment=graf_rfid_s23", "paths.output_dir=/tmp/run"])
    metrics, objects = train(cfg)
"""
