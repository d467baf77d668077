"""Optuna studies shared across machines (issue 25, part 3): the sweeper on a real PostgreSQL server, two worker
processes filling one study, and a worker killed mid-trial whose trial Optuna's heartbeats fail and queue again.
The trials are the tiny sweep app's (tests/fixtures/sweep_app: milliseconds each)."""

from __future__ import annotations

import os
import signal
import time

import optuna
import pytest
from optuna.trial import TrialState

from tests.sweeper.test_optuna_sweeper import load, run_app, trained

pytest.importorskip("psycopg2")

SIX = ["hydra.sweeper.n_trials=6", "hydra.sweeper.threads_per_job=1"]
BEAT = ["hydra.sweeper.heartbeat.interval=1", "hydra.sweeper.heartbeat.grace_period=3"]


def _logs(tmp) -> str:
    return "".join(f.read_text() for f in sorted(tmp.glob("app_*.log")))[-4000:]


@pytest.mark.slow  # a PostgreSQL server and two sweep processes: about 20 s here
def test_two_workers_fill_a_six_trial_study_on_postgresql_with_no_trial_lost_or_run_twice(tmp_path, postgres):
    url = postgres.create_database("two_workers")
    procs = [run_app(tmp_path, "work_s=0.5", f"hydra.sweeper.storage={url}", *SIX, *BEAT, wait=False) for _ in range(2)]
    for p in procs:
        assert p.wait(timeout=300) == 0, _logs(tmp_path)
    study = optuna.load_study(study_name="study", storage=url)
    complete = [t for t in study.trials if t.state == TrialState.COMPLETE]
    assert len(complete) == 6 and len({t.params["x"] for t in complete}) == 6
    assert set(trained(tmp_path).values()) == {1} and len(trained(tmp_path)) == 6  # none lost, none run twice
    pids = {p.name.rsplit("_", 1)[1] for p in (tmp_path / "marks").glob("started_*")}
    assert len(pids) == 2, "both workers ran trials"


@pytest.mark.slow  # three sweep processes and a 3 s grace period: about 30 s here
def test_a_worker_killed_mid_trial_has_its_trial_failed_by_heartbeat_and_queued_again(tmp_path, postgres):
    # the grid order is seeded, the same on any storage: the first trial's x, from a dry run on SQLite
    probe = tmp_path / "probe"
    probe.mkdir()
    assert run_app(probe, "hydra.sweeper.n_trials=1").returncode == 0
    first = load(probe).trials[0].params["x"]

    url = postgres.create_database("killed_worker")
    a = run_app(tmp_path, f"hydra.sweeper.storage={url}", *SIX, *BEAT, wait=False, env={"SWEEP_APP_SLOW_AT": first})
    deadline = time.time() + 120
    while not list((tmp_path / "marks").glob(f"started_x{first}_*")):
        assert a.poll() is None and time.time() < deadline, "worker A ended before its first trial: " + _logs(tmp_path)
        time.sleep(0.2)
    time.sleep(2.0)  # a heartbeat or two recorded
    os.killpg(a.pid, signal.SIGKILL)  # the worker dies mid-trial: no tell, no cleanup
    a.wait()
    study = optuna.load_study(study_name="study", storage=url)
    assert [t.state for t in study.trials] == [TrialState.RUNNING]

    b = run_app(tmp_path, f"hydra.sweeper.storage={url}", *SIX, *BEAT, timeout=300)  # another worker, later
    assert b.returncode == 0, b.stderr[-3000:]
    assert "sent no heartbeat" in b.stderr + b.stdout
    study = optuna.load_study(study_name="study", storage=url)
    complete = [t for t in study.trials if t.state == TrialState.COMPLETE]
    assert len(complete) == 6 and len({t.params["x"] for t in complete}) == 6
    dead = study.trials[0]
    assert dead.state == TrialState.FAIL and dead.params["x"] == first
    retry = [t for t in study.trials if t.system_attrs.get("failed_trial") == 0]
    assert len(retry) == 1 and retry[0].state == TrialState.COMPLETE and retry[0].params == dead.params
    # every configuration ran to its end exactly once (the killed one never ended), and the dead worker's trial
    # is not counted as a failure of its configuration
    assert set(trained(tmp_path).values()) == {1} and len(trained(tmp_path)) == 6
    from graf.sweeper.trials import counted_failures

    assert counted_failures(study.trials) == []
