"""The 2-process speed-ups of the scaling-out engines on this machine, each next to one process.

    python scripts/scaling_speedups.py [--out sweeps/scaling] [--num-tx 256] [--steps 150]

1. Simulation in shards: ``graf-simulate scene=conference_v1 band=2.4ghz sim.num_tx=N`` in one process, then the
   same positions as two shard processes started together (``sim.shard.count=2``); the two files must be equal
   byte for byte.
2. A 2-job multirun: two KNN-DL trainings (``seed=0,1``, ``trainer.max_steps=S``) with Hydra's basic launcher
   (one job after the other, each with every core) and with ``submitit_local`` (the two at once, a core each).

Run it alone on the machine.  Prints a table and writes ``scaling.json`` and ``scaling.md`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BIN = Path(sys.executable).parent


def _timed(cmds: list[list[str]], env: dict) -> float:
    """Wall seconds from starting every command (at once) until the last ends; each must succeed."""
    t0 = time.perf_counter()
    procs = [subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env) for c in cmds]
    for p, c in zip(procs, cmds):
        out, _ = p.communicate()
        if p.returncode != 0:
            raise SystemExit(f"{' '.join(c)} failed:\n{out[-3000:]}")
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="sweeps/scaling")
    ap.add_argument("--num-tx", type=int, default=256)
    ap.add_argument("--steps", type=int, default=150)
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="graf-scaling-"))
    cores = os.cpu_count() or 1
    env = dict(os.environ, WANDB_MODE="offline")
    rows = []
    try:
        sim = [str(BIN / "graf-simulate"), "scene=conference_v1", "band=2.4ghz", f"sim.num_tx={args.num_tx}",
               "sim.chunk_size=32", "sim.progress=false"]  # fmt: skip
        one = _timed([[*sim, f"data_root={work / 'sim1'}", f"hydra.run.dir={work / 'sim1_run'}"]], env)
        two = _timed(
            [[*sim, f"data_root={work / 'sim2'}", f"hydra.run.dir={work / f'sim2_run{i}'}", f"sim.shard.index={i}",
              "sim.shard.count=2"] for i in (0, 1)],
            env,
        )  # fmt: skip
        f1, f2 = (next((work / d).rglob("*.h5")) for d in ("sim1", "sim2"))
        same = f1.read_bytes() == f2.read_bytes()
        what = f"graf-simulate, conference_v1, {args.num_tx} positions"
        rows.append({"what": what, "one_process_s": round(one, 1), "two_processes_s": round(two, 1),
                     "speedup": round(one / two, 2), "identical_output": same})  # fmt: skip

        train = [str(BIN / "graf-train"), "-m", "model=knn_dl", f"trainer.max_steps={args.steps}", "seed=0,1",
                 "logger=none", "plot_count=0", "reliance=false", "trainer.enable_progress_bar=false",
                 f"data_root={work / 'data'}"]  # fmt: skip
        basic = _timed([[*train, f"hydra.sweep.dir={work / 'basic'}", f"torch_threads={cores}"]], env)
        local = _timed(
            [[*train, f"hydra.sweep.dir={work / 'local'}", "hydra/launcher=submitit_local",
              f"torch_threads={max(1, cores // 2)}"]],
            dict(env, OMP_NUM_THREADS=str(max(1, cores // 2))),
        )  # fmt: skip
        psnr = {
            k: sorted(json.loads(f.read_text())["metrics"]["test/psnr"] for f in (work / k).glob("*/results.json"))
            for k in ("basic", "local")
        }
        rows.append({"what": f"2-job multirun (KNN-DL, {args.steps} steps, seeds 0 and 1)",
                     "one_process_s": round(basic, 1), "two_processes_s": round(local, 1),
                     "speedup": round(basic / local, 2), "test_psnr": psnr})  # fmt: skip
    finally:
        shutil.rmtree(work, ignore_errors=True)
    record = {"machine": f"{platform.node()}: {cores} cores, {platform.processor() or platform.machine()}",
              "python": platform.python_version(), "rows": rows,
              "command": "python scripts/scaling_speedups.py " + " ".join(sys.argv[1:])}  # fmt: skip
    (out / "scaling.json").write_text(json.dumps(record, indent=2) + "\n")
    lines = ["| run | one process (s) | two processes (s) | speed-up |", "|---|---|---|---|"]
    lines += [f"| {r['what']} | {r['one_process_s']} | {r['two_processes_s']} | {r['speedup']}x |" for r in rows]
    (out / "scaling.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
