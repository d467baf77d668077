"""A trial's bookkeeping in the study: the attributes the sweeper stores with it, which failed trials count against
``max_failures``, which trials are finished, and its parameters written as Hydra overrides."""

from __future__ import annotations

from optuna.trial import FrozenTrial, TrialState

OWNER, ERROR, INTERRUPTED, REQUEUED, RESUME, DUPLICATE, SURPLUS, OUTPUT, WALL = (
    "graf.owner",
    "graf.error",
    "graf.interrupted",
    "graf.requeued_from",
    "graf.resume_from",
    "graf.duplicate_of",
    "graf.surplus",
    "graf.output_dir",
    "graf.wall_s",
)
POLL_S = 2.0  # seconds between looks at the study while others run its last trials
NOT_COUNTED = (INTERRUPTED, SURPLUS, DUPLICATE)  # FAIL trials that are not the configuration's failure


def retried(trials: list[FrozenTrial]) -> set[int]:
    """The numbers of trials failed by their heartbeat and queued again (Optuna's retry history)."""
    return {n for t in trials for n in t.system_attrs.get("retry_history", [])}


def counted_failures(trials: list[FrozenTrial]) -> list[FrozenTrial]:
    """Failed trials that count against ``max_failures``: not those interrupted, surplus or duplicate, nor those
    failed by a stale heartbeat and queued again (their worker died, the configuration did not fail)."""
    again = retried(trials)
    return [
        t
        for t in trials
        if t.state == TrialState.FAIL and not any(k in t.user_attrs for k in NOT_COUNTED) and t.number not in again
    ]


def finished(trials: list[FrozenTrial]) -> list[FrozenTrial]:
    return [t for t in trials if t.state in (TrialState.COMPLETE, TrialState.PRUNED)]


def quote(s: str) -> str:
    return "'" + s.replace("\\", "\\\\").replace("'", "\\'") + "'"


def grammar(v) -> str:
    """A value in Hydra's override grammar (strings quoted, dicts and lists nested)."""
    if isinstance(v, dict):
        return "{" + ",".join(f"{k}:{grammar(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(grammar(x) for x in v) + "]"
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    return quote(str(v))
