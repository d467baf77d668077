"""A search space written with Hydra's sweep grammar, as Optuna distributions.

    interval(a, b)             float, uniform            tag(log, interval(a, b))   float, log-uniform
    tag(int, interval(a, b))   integer, uniform          tag(int, log, interval(a, b))  integer, log-uniform
    range(a, b[, step])        integer a..b, b included (as hydra-optuna-sweeper reads it)
    choice(x, y, ...)          categorical: each value kept as its override text ([a,b] lists included)

Settings without a sweep (``key=value``) are fixed: passed to every trial as they are.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import ChoiceSweep, IntervalSweep, Override, RangeSweep
from optuna.distributions import BaseDistribution, CategoricalDistribution, FloatDistribution, IntDistribution


class SearchSpaceError(ValueError):
    """A search space the sweeper cannot use (a user error: reported without a traceback)."""


@dataclass
class SearchSpace:
    """A search's parameters: ``distributions`` (name -> Optuna distribution, from the sweeper's ``params``) and
    ``fixed`` (overrides every trial gets); a space of categorical choices only can be searched as a grid."""

    distributions: dict[str, BaseDistribution] = field(default_factory=dict)
    fixed: list[str] = field(default_factory=list)  # overrides every trial gets

    @property
    def all_categorical(self) -> bool:
        return bool(self.distributions) and all(
            isinstance(d, CategoricalDistribution) for d in self.distributions.values()
        )

    def grid(self) -> dict[str, list]:
        return {k: list(d.choices) for k, d in self.distributions.items()}  # type: ignore[attr-defined]

    def grid_size(self) -> int:
        n = 1
        for d in self.distributions.values():
            n *= len(d.choices)  # type: ignore[attr-defined]
        return n

    def overrides(self, params: dict) -> list[str]:
        """A trial's overrides: the fixed ones, then one ``key=value`` per parameter."""
        out = list(self.fixed)
        for k, v in params.items():
            out.append(f"{k}={format_value(v)}")
        return out

    def describe(self) -> dict:
        return {"params": {k: repr(d) for k, d in sorted(self.distributions.items())}, "fixed": sorted(self.fixed)}


def format_value(v) -> str:
    if isinstance(v, float):
        return repr(v)
    return str(v)


def distribution(override: Override) -> BaseDistribution:
    key = override.get_key_element()
    sweep = override.value()
    tags = set(getattr(sweep, "tags", set()) or set())
    if isinstance(sweep, ChoiceSweep) or override.is_choice_sweep():
        choices = list(override.sweep_string_iterator())
        if len(set(choices)) != len(choices):
            raise SearchSpaceError(f"{key}: choice(...) lists a value twice: {choices}")
        return CategoricalDistribution(choices)
    if isinstance(sweep, RangeSweep):
        start, stop, step = sweep.start, sweep.stop, sweep.step if sweep.step is not None else 1
        if all(isinstance(x, int) for x in (start, stop, step)):
            if stop < start:
                raise SearchSpaceError(f"{key}: range({start}, {stop}) is empty")
            return IntDistribution(int(start), int(stop), step=int(step))
        return FloatDistribution(float(start), float(stop), step=float(step))
    if isinstance(sweep, IntervalSweep):
        lo, hi = sweep.start, sweep.end
        if lo is None or hi is None or not lo < hi:
            raise SearchSpaceError(f"{key}: interval({lo}, {hi}) needs low < high")
        log = "log" in tags
        if log and lo <= 0:
            raise SearchSpaceError(f"{key}: tag(log, interval({lo}, {hi})) needs a positive low end")
        if "int" in tags:
            return IntDistribution(int(lo), int(hi), log=log)
        return FloatDistribution(float(lo), float(hi), log=log)
    raise SearchSpaceError(f"{key}: sweep {override.input_line!r} is not one of interval, range, choice")


def parse_search_space(params: dict | None, arguments: list[str], parser: OverridesParser) -> SearchSpace:
    """The space of ``hydra.sweeper.params`` (``{key: grammar}``) and the command line's arguments (which
    win over params on the same key)."""
    lines = [f"{k}={v}" for k, v in (params or {}).items()] + list(arguments)
    space = SearchSpace()
    by_key: dict[str, Override] = {}
    for o in parser.parse_overrides(lines):
        by_key[o.get_key_element()] = o  # the command line wins
    for key, o in by_key.items():
        if o.is_sweep_override():
            space.distributions[key] = distribution(o)
        else:
            space.fixed.append(o.input_line)
    return space
