"""Each setting's default lives in one place: the config file (``conf/``), as the Lightning-Hydra template keeps it.

A class configured from ``conf/`` names its *home* file with :func:`defaults_from`: the file states every setting
with its value and its comment, the constructor states the same settings without a default, and a construction
from Python (a test, a notebook: ``GRaFModule(d_model=8)``) takes what it leaves out from the home file.  So the
value a run gets and the value a script gets cannot drift apart (``chunk_rays`` had 4096 in the constructor and
1024 in ``conf/model/graf.yaml``).  Other files targeting the class (presets: ``model/graf_cpu.yaml``) derive from
the home through their defaults list and state only what they change; ``tests/app/test_config_home.py`` fails on a
setting stated in two places.

A value that is an interpolation (``seed: ${seed}``) is wiring, not a default: the constructor keeps its own
default for it, and ``???`` (a setting the user must give) is no default either.
"""

from __future__ import annotations

import functools
import inspect
from pathlib import Path

CONF_DIR = Path(__file__).resolve().parent / "conf"
SKIP = ("defaults",)  # keys of a config file that are Hydra's, not the class's settings


def is_wiring(value) -> bool:
    """An interpolation or a mandatory value (``???``): no default."""
    return isinstance(value, str) and ("${" in value or value == "???")


@functools.cache
def _home(rel: str) -> dict:
    from omegaconf import OmegaConf

    path = CONF_DIR / rel
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such config file (the home of a class's defaults)")
    raw = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    return {k: v for k, v in raw.items() if not k.startswith("_") and k not in SKIP}


def home_values(rel: str) -> dict:
    """The settings the home file ``rel`` (relative to ``conf/``) gives a class: every key but Hydra's own
    (``_target_``, ``defaults``, ...) and those whose value is wiring (:func:`is_wiring`).  A fresh copy."""
    import copy

    return {k: copy.deepcopy(v) for k, v in _home(rel).items() if not is_wiring(v)}


def defaults_from(rel: str):
    """Class decorator: the constructor's missing keyword arguments are taken from the home config file ``rel``.

    Refuses (at import) a constructor that also gives one of those settings a default of its own (two homes), or a
    home file stating a setting the constructor does not take."""

    def decorate(cls):
        init = cls.__init__
        signature = inspect.signature(init)  # once, not per construction
        params = signature.parameters
        values = home_values(rel)
        unknown = [k for k in values if k not in params and not any(p.kind == p.VAR_KEYWORD for p in params.values())]
        if unknown:
            raise TypeError(f"{CONF_DIR / rel}: {cls.__name__} takes no setting(s) {unknown}")
        twice = [k for k in values if k in params and params[k].default is not inspect.Parameter.empty]
        if twice:
            raise TypeError(
                f"{cls.__qualname__}: the default of {twice} is stated both in the constructor and in {rel}; "
                "keep it in the config file only"
            )

        @functools.wraps(init)
        def __init__(self, *args, **kwargs):
            bound = signature.bind_partial(self, *args, **kwargs).arguments
            for k, v in home_values(rel).items():
                if k not in bound:
                    kwargs[k] = v
            init(self, *args, **kwargs)

        cls.__init__ = __init__
        cls.config_home = rel
        return cls

    return decorate


def class_defaults(cls, skip=("self",)) -> dict:
    """Every setting ``cls`` takes that has a default, and that default: its home file's value
    (:func:`defaults_from`) or its constructor's.  What a checkpoint records of a component built by name."""
    params = inspect.signature(cls.__init__).parameters
    out = {k: p.default for k, p in params.items() if p.default is not inspect.Parameter.empty and k not in skip}
    home = getattr(cls, "config_home", None)
    if home:
        out.update({k: v for k, v in home_values(home).items() if k in params and k not in skip})
    return {k: out[k] for k in params if k in out}  # in the constructor's order
