"""The paper-density studies on one GPU machine, in one call with a deadline: learning curves, a choice made on them,
then the cross-scene matrix and the neighbor-count study at the chosen variant and budget.

    python scripts/paper_studies_gpu.py --pack .paper_gpu --out "$OUT" --deadline 520      (on the GPU machine)
    python scripts/paper_studies_gpu.py --pack .paper_gpu --out /tmp/o --tiny             (a smoke run on a CPU)

The pack folder comes from ``scripts/prepare_paper_gpu.sh`` (wheels of what such a machine lacks, the LPIPS weights,
and the six conference/office layouts' catalog files without their spectra: ``graf.sim.slim``).  Stages, each
started only if the deadline leaves it time, each stopped (SIGTERM: state saved) when the deadline comes:

1. **data**: the spectra rebuilt from the channels (their sha256 checked against the traced originals).
2. **curves** (validation only): ``graf-curves`` regime ``cross_family_paper`` (trained on conference_v1 +
   office_v1 at full density, validated zero-shot on their v2 layouts), the GRaF modes pooled, ray, ray_knn,
   ray_weights and KNN-DL, one process each, at once, until ``--curves-until`` or ``--curves-deadline``.
3. **choice**, fixed before any curve was seen: the mode by :func:`graf.reports.choices.choose` (the best
   mean rank of validation PSNR, SSIM and LPIPS at the largest step every mode reached); each trained method's
   budget is the point of its own curve with the highest validation PSNR (the smaller on a tie), lowered to the
   largest point whose predicted training time (the curve's measured seconds per step) fits the time left.
   Written to ``choice.json``.
4. **studies**: a queue of jobs run ``--workers`` at a time, in this order: the cross-scene matrix at seed 0
   (GRaF, KNN-DL, NeRF2 on conference_v1 and on office_v1), its seeds 1 and 2 (GRaF, KNN-DL), then the
   neighbor-count groups (one process per method, training scene and seed: its base model, then L = 2, 4, 10 on
   the two other layouts of its family, then L = 1, 6, 8, 16; ``--nc-ls`` other groups; ``--nc-from-matrix``: no
   base of its own, each group tests the matrix job's model of its method, scene and seed zero-shot once that job
   has finished).  A job not finished by the deadline is stopped; graf-report then writes each study's tables and
   intervals from the jobs that finished.  ``--no-curves --steps graf=1000 knn_dl=3000``: the budgets fixed before
   the run instead of curves and a choice.
5. **out**: ``curves.tar.gz``, ``cross_scene_matrix_paper.tar.gz``, ``neighbor_count_paper.tar.gz`` (no
   checkpoints), ``summary.json`` (each stage's seconds, the choice, the jobs' outcomes) and ``log.txt``; with
   ``--weights-back`` also the finished matrix jobs' weights without optimiser state (``weights_*.tar``, each under
   the 16 MiB a file may come back with), for the neighbor count or a resumed study on the CPU.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import signal
import subprocess
import sys
import tarfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PY = sys.executable
T0 = time.time()
MODES = ["pooled", "ray", "ray_knn", "ray_weights"]
GRAF_MODELS = {  # the studies' model of each mode (graf_cpu_ray_weights + 4-D positions: the curves' configuration)
    "pooled": "graf_cpu_scenes_pooled",
    "ray": "graf_cpu_scenes_ray_plain",
    "ray_knn": "graf_cpu_scenes_ray_knn",
    "ray_weights": "graf_cpu_scenes_ray_weights",
}
LOG: list[str] = []


def log(msg: str) -> None:
    line = f"[{time.time() - T0:6.1f} s] {msg}"
    LOG.append(line)
    print(line, flush=True)


def left(deadline: float) -> float:
    return deadline - (time.time() - T0)


def stop(procs: list[subprocess.Popen], grace: float = 20.0) -> None:
    """SIGTERM (graf-train saves its state), then SIGKILL after ``grace`` seconds."""
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    end = time.time() + grace
    for p in procs:
        try:
            p.wait(timeout=max(0.1, end - time.time()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def _restore_one(f: Path, data: Path) -> dict:
    from graf.sim.slim import restore as restore_one

    scene, band = f.name.split(".slim.h5")[0].split("__")
    dst = data / "sim" / scene / f"{band}.h5"
    r = restore_one(f, dst) if not dst.exists() else {"n": None, "match": None, "existing": True}
    return {"scene": scene, "band": band, "file": str(dst), **r}


def restore(pack: Path, data: Path) -> list[dict]:
    """Every catalog file of ``pack`` rebuilt under ``data`` (one process per file)."""
    from concurrent.futures import ProcessPoolExecutor

    files = sorted((pack / "catalog").glob("*.slim.h5"))
    with ProcessPoolExecutor(max(1, min(len(files), os.cpu_count() or 1))) as ex:
        out = list(ex.map(_restore_one, files, [data] * len(files)))
    for r in out:
        state = "kept" if r.get("existing") else ("sha256 matches" if r["match"] else "sha256 DIFFERS")
        log(f"data: {r['file']} ({state})")
    return out


def curves(args, data: Path, work: Path, extra: list[str]) -> dict:
    base = [
        PY,
        "-m",
        "graf.cli.studies.curves",
        f"out={work / 'curves'}",
        f"data_root={data}",
        "only_regimes=[cross_family_paper]",
        f"extra_overrides=[{','.join(repr(e) for e in extra)}]",
        f"threads={args.threads}",
        f"until={args.curves_until}",
        f"run_timeout_s={int(args.deadline)}",
    ]
    if not args.tiny:
        base += [f"steps={args.curves_steps}"]
    else:
        base = [b.replace("extra_overrides=[", "extra_overrides=['data.val_fraction=0.001',") for b in base]
        base += ["regimes.cross_family_paper.max_steps=4", "steps=[2,4]", "checkpoint_every=2"]
    (work / "logs").mkdir(parents=True, exist_ok=True)
    t = time.time()
    subprocess.run(
        [*base, "only_methods=[]"],
        stdout=open(work / "logs" / "curves_knn.log", "w"),
        stderr=subprocess.STDOUT,
        timeout=max(10, left(args.curves_deadline)),
    )
    procs = [
        subprocess.Popen(
            [*base, f"only_methods=[{m}]"],
            stdout=open(work / "logs" / f"curves_{m}.log", "w"),
            stderr=subprocess.STDOUT,
        )
        for m in [*MODES, "knn_dl"]
    ]
    while any(p.poll() is None for p in procs) and left(args.curves_deadline) > 0:
        time.sleep(2)
    stopped = any(p.poll() is None for p in procs)
    stop(procs)
    subprocess.run(
        [*base, "only_methods=[]", "until=0"],
        stdout=open(work / "logs" / "curves_tables.log", "w"),
        stderr=subprocess.STDOUT,
    )
    log(f"curves: {time.time() - t:.0f} s{' (stopped at the deadline)' if stopped else ''}")
    f = work / "curves" / "curves.csv"
    rows = [r for r in csv.DictReader(f.open())] if f.exists() else []
    return {"rows": [r for r in rows if r["regime"] == "cross_family_paper"], "stopped": stopped}


def budget(rows: list[dict], method: str, seconds: float, fallback: int) -> dict:
    """A method's budget: its curve's best validation-PSNR point (the smaller on a tie), lowered to the largest
    point whose predicted seconds (steps x the curve's measured s/step) fit ``seconds``."""
    from graf.reports.choices import best_step

    pts = sorted(
        (int(r["step"]), float(r["val_psnr"]), float(r["s_per_step"] or 0))
        for r in rows
        if r["method"] == method and r["val_psnr"] not in ("", None)
    )
    if not pts:
        return {"steps": fallback, "why": "no curve point: the fallback"}
    best = best_step(rows, method)
    s_step = max(p[2] for p in pts)  # the slowest point's (contention with the other curves included)
    fits = [p[0] for p in pts if p[0] <= best and p[0] * s_step <= seconds]
    steps = max(fits) if fits else min(p[0] for p in pts)
    why = f"best validation PSNR at step {best}" + (
        "" if steps == best else f"; lowered to {steps} to fit {seconds:.0f} s at {s_step:.3f} s/step"
    )
    return {"steps": steps, "best_step": best, "s_per_step": s_step, "why": why}


def choose_all(args, rows: list[dict]) -> dict:
    from graf.reports.choices import choose

    modes = [m for m in MODES if any(r["method"] == m for r in rows)]
    if modes:
        mode, table = choose(rows, modes)
    else:
        mode, table = "ray_weights", []
    # the studies' trainings run --workers at a time; a third of what is left goes to each round of them
    per_round = max(30.0, (left(args.deadline) - 40) / 3)
    return {
        "mode": mode,
        "modes_compared": modes,
        "table": table,
        "graf": budget(rows, mode, per_round, args.fallback_steps),
        "knn_dl": budget(rows, "knn_dl", per_round, args.fallback_steps),
        "seconds_per_round": round(per_round),
    }


def study_jobs(args, choice: dict, data: Path, work: Path, extra: list[str]) -> list[dict]:
    """The queue: ``{"name", "cmd" (a list, or a callable giving it at start), "after" (a job to wait for)}``."""
    graf_model = [f"model={GRAF_MODELS[choice['mode']]}"]
    steps = {"graf": choice["graf"]["steps"], "knn_dl": choice["knn_dl"]["steps"], "nerf2": choice["graf"]["steps"]}
    models = {"graf": graf_model, "knn_dl": ["model=knn_dl"], "nerf2": ["model=nerf2_study"]}
    threads = {m: args.threads for m in models} | {"graf": args.graf_threads or args.threads}
    common = [f"data_root={data}", "reliance=false", *extra]
    if args.tiny:
        common += ["data.test_subset=4"]
    jobs = []

    def train(*overrides):
        return [PY, "-m", "graf.cli.train", *overrides]

    def matrix(method, scene, seed):
        return {
            "name": f"matrix {method} {scene} seed {seed}",
            "cmd": train(
                "experiment=cross_scene_matrix",
                *models[method],
                f"scene={scene}",
                f"seed={seed}",
                f"study_steps={steps[method]}",
                f"torch_threads={threads[method]}",
                *common,
                f"hydra.sweep.dir={work / 'cross_scene_matrix_paper'}",
            ),
            "after": None,
        }

    def nc(method, scene, seed, L):
        same = {"conference_v1": "conference_v2,conference_v3", "office_v1": "office_v2,office_v3"}[scene]
        overrides = [
            "experiment=neighbor_count",
            *models[method],
            f"scene={scene}",
            f"seed={seed}",
            f"study_steps={steps[method]}",
            f"eval_scene={same}",
            f"neighbors.L={L}",
            f"torch_threads={threads[method]}",
            *common,
            f"hydra.sweep.dir={work / 'neighbor_count_paper'}",
        ]
        job = {"name": f"neighbor_count {method} {scene} seed {seed} L {L}", "cmd": train(*overrides), "after": None}
        if args.nc_from_matrix:  # zero-shot from the matrix job's checkpoint (the same weights as a base of its own)
            job["after"] = f"matrix {method} {scene} seed {seed}"
            job["cmd"] = lambda: train(*overrides, *zero_shot(work, models[method][0], scene, seed))
        return job

    scenes = ["conference_v1", "office_v1"]
    for m in ("graf", "knn_dl", "nerf2"):
        jobs += [matrix(m, s, 0) for s in scenes]
    for seed in (1, 2):
        jobs += [matrix(m, s, seed) for m in ("graf", "knn_dl") for s in scenes]
    for Ls in args.nc_ls:
        jobs += [nc(m, s, seed, Ls) for seed in (0, 1, 2) for m in ("graf", "knn_dl") for s in scenes]
    jobs = [j for j in jobs if j["name"].split()[0] in args.studies and j["name"].split()[1] in args.methods]
    if args.tiny:  # one job of each kind
        keep = (
            "matrix graf conference_v1 seed 0",
            "matrix knn_dl conference_v1 seed 0",
            "matrix nerf2 conference_v1 seed 0",
            f"neighbor_count graf conference_v1 seed 0 L {args.nc_ls[0]}",
        )
        jobs = [j for j in jobs if j["name"] in keep]
    return jobs


def matrix_checkpoint(work: Path, model: str, scene: str, seed: int) -> Path:
    """The finished matrix job's checkpoint of ``model`` (``model=...``), ``scene`` and ``seed``."""
    want = {model, f"scene={scene}", f"seed={seed}"}
    found = [
        d / "checkpoints" / "last.ckpt"
        for d in (work / "cross_scene_matrix_paper").glob("*model=*")
        if want <= set(d.name.split(",")) and (d / "results.json").exists()
    ]
    if len(found) != 1:
        raise FileNotFoundError(f"{len(found)} finished matrix jobs of {model} {scene} seed {seed}")
    return found[0]


def zero_shot(work: Path, model: str, scene: str, seed: int) -> list[str]:
    ckpt = matrix_checkpoint(work, model, scene, seed)
    keys = "experiment,data_root,study_size,finetune.base,finetune.init_from"
    return [
        "finetune.base=null",
        f'finetune.init_from="{ckpt}"',
        f"hydra.job.config.override_dirname.exclude_keys=[{keys}]",
    ]


def run_queue(args, jobs: list[dict], work: Path) -> list[dict]:
    """Run ``jobs`` ``--workers`` at a time, in order; a neighbor-count group waits for the one before it with the
    same base model (its first part trains the base), a job with ``after`` for that job (and is dropped if it
    failed); stop everything at the deadline."""
    running: dict[str, tuple[subprocess.Popen, float]] = {}
    outcomes, queue, exits = [], list(jobs), {}
    (work / "logs").mkdir(parents=True, exist_ok=True)
    while (queue or running) and left(args.deadline) > 0:
        for name, (p, t) in list(running.items()):
            if p.poll() is not None:
                outcomes.append({"job": name, "exit": p.returncode, "seconds": round(time.time() - t)})
                exits[name] = p.returncode
                log(f"done ({p.returncode}): {name} in {time.time() - t:.0f} s")
                del running[name]
        for j in [j for j in queue if j["after"] is not None and exits.get(j["after"], 0) != 0]:
            queue.remove(j)
            outcomes.append({"job": j["name"], "exit": f"not started: {j['after']} failed"})
        busy_bases = {n.rsplit(" L ", 1)[0] for n in running}
        while len(running) < args.workers and left(args.deadline) > args.min_job_s:
            ready = [
                j
                for j in queue
                if j["name"].rsplit(" L ", 1)[0] not in busy_bases and (j["after"] is None or j["after"] in exits)
            ]
            if not ready:
                break
            job = ready[0]
            queue.remove(job)
            try:
                cmd = job["cmd"]() if callable(job["cmd"]) else job["cmd"]
            except FileNotFoundError as e:
                outcomes.append({"job": job["name"], "exit": f"not started: {e}"})
                log(f"not started: {job['name']}: {e}")
                continue
            slug = job["name"].replace(" ", "_").replace(",", "-")
            running[job["name"]] = (
                subprocess.Popen(
                    cmd, stdout=open(work / "logs" / f"{slug}.log", "w"), stderr=subprocess.STDOUT, cwd=ROOT
                ),
                time.time(),
            )
            busy_bases.add(job["name"].rsplit(" L ", 1)[0])
            log(f"start: {job['name']}")
        time.sleep(2)
    if running:
        log(f"deadline: stopping {sorted(running)}")
        stop([p for p, _ in running.values()])
        outcomes += [{"job": n, "exit": "stopped at the deadline"} for n in running]
    outcomes += [{"job": j["name"], "exit": "not started (deadline)"} for j in queue]
    return outcomes


def weights_back(work: Path, out: Path) -> None:
    """The finished matrix jobs' weights (their checkpoints without the optimiser's state: what
    ``finetune.init_from`` reads), one tarball per GRaF training scene and one for the other methods, each under the
    16 MiB a file may come back with."""
    groups: dict[str, list[Path]] = {}
    slim = work / "weights"
    for ckpt in sorted((work / "cross_scene_matrix_paper").glob("*/checkpoints/last.ckpt")):
        run = ckpt.parent.parent
        if not (run / "results.json").exists():
            continue
        import torch

        state = torch.load(ckpt, map_location="cpu", weights_only=True)
        for k in ("optimizer_states", "lr_schedulers", "loops", "callbacks"):
            state.pop(k, None)
        dst = slim / run.name / "checkpoints" / "last.ckpt"
        dst.parent.mkdir(parents=True, exist_ok=True)
        torch.save(state, dst)
        parts = dict(p.split("=", 1) for p in run.name.split(","))
        key = f"graf_{parts['scene']}" if parts["model"].startswith("graf") else "others"
        groups.setdefault(key, []).append(dst)
    for key, files in groups.items():
        with tarfile.open(out / f"weights_{key}.tar", "w") as tar:
            for f in files:
                tar.add(f, arcname=str(f.relative_to(slim)))


def pack_out(work: Path, out: Path, summary: dict, weights: bool = False) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name in ("curves", "cross_scene_matrix_paper", "neighbor_count_paper", "logs"):
        src = work / name
        if not src.exists():
            continue
        with tarfile.open(out / f"{name}.tar.gz", "w:gz") as tar:
            tar.add(src, arcname=name, filter=lambda ti: None if ti.name.endswith(".ckpt") else ti)
    if weights:
        try:
            weights_back(work, out)
        except Exception as e:  # noqa: BLE001  (the records still go back)
            log(f"weights: {type(e).__name__}: {e}")
    (out / "summary.json").write_text(json.dumps(summary, indent=1, default=str))
    (out / "log.txt").write_text("\n".join(LOG) + "\n")


def report(args) -> None:
    """graf-report over each study's folder (the tables and intervals of the jobs that finished)."""
    for study in ("cross_scene_matrix_paper", "neighbor_count_paper"):
        if (args.work / study).exists():
            r = subprocess.run(
                [PY, "-m", "graf.cli.report", f"runs={args.work / study}"],
                capture_output=True,
                text=True,
                timeout=args.report_timeout,
            )
            log(f"report {study}: exit {r.returncode}")
            (args.work / "logs" / f"report_{study}.log").write_text(r.stdout + r.stderr)


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pack", type=Path, default=ROOT / ".paper_gpu")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--work", type=Path, default=Path("/tmp/paper_gpu"))
    ap.add_argument("--deadline", type=float, default=520.0, help="seconds from the start: everything stops")
    ap.add_argument("--curves-deadline", type=float, default=240.0)
    ap.add_argument("--curves-until", type=int, default=3000)
    ap.add_argument("--curves-steps", default="[300,1000,3000]", help="the curves' evaluation points")
    ap.add_argument("--workers", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--graf-threads", type=int, default=None, help="GRaF's jobs' torch threads (default --threads)")
    ap.add_argument("--min-job-s", type=float, default=45.0, help="no job starts with less time left")
    ap.add_argument("--fallback-steps", type=int, default=1000)
    ap.add_argument("--steps", nargs="*", default=[], help="with --no-curves: METHOD=STEPS (graf, knn_dl) budgets")
    ap.add_argument("--nc-ls", nargs="+", default=["2,4,10", "1,6,8,16"], help="the neighbor-count L groups")
    ap.add_argument("--nc-from-matrix", action="store_true", help="neighbor count zero-shot from the matrix's models")
    ap.add_argument("--weights-back", action="store_true", help="the matrix jobs' weights come back (no optimiser)")
    ap.add_argument("--no-curves", action="store_true", help="no curves: --mode and --fallback-steps decide")
    ap.add_argument("--mode", default="ray_weights", choices=MODES, help="GRaF's mode with --no-curves")
    ap.add_argument("--studies", nargs="+", default=["matrix", "neighbor_count"], choices=["matrix", "neighbor_count"])
    ap.add_argument("--methods", nargs="+", default=["graf", "knn_dl", "nerf2"], choices=["graf", "knn_dl", "nerf2"])
    ap.add_argument("--report-timeout", type=float, default=120.0)
    ap.add_argument("--tiny", action="store_true", help="toy sizes on whatever device there is (a smoke run)")
    return ap.parse_args()


def main() -> int:
    args = parse_args()
    sys.path.insert(0, str(ROOT / "src"))
    import torch

    device = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"
    extra = ["trainer=gpu"] if device != "cpu" else ["trainer=cpu"]
    data = args.work / "data"
    summary: dict = {"device": device, "args": vars(args), "stages": {}}
    try:
        t = time.time()
        summary["catalog"] = restore(args.pack, data)
        summary["stages"]["data_s"] = round(time.time() - t, 1)
        t = time.time()
        if args.no_curves:  # the mode and budget fixed before the run (--mode, --fallback-steps)
            fixed = {m: int(v) for m, v in (kv.split("=", 1) for kv in args.steps)}
            choice = {"mode": args.mode, "modes_compared": [], "table": []} | {
                m: {"steps": fixed.get(m, args.fallback_steps), "why": "fixed before the run (--no-curves)"}
                for m in ("graf", "knn_dl")
            }
        else:
            cur = curves(args, data, args.work, extra)
            summary["stages"]["curves_s"] = round(time.time() - t, 1)
            summary["curves_stopped"] = cur["stopped"]
            choice = choose_all(args, cur["rows"])
        summary["choice"] = choice
        (args.work / "choice.json").write_text(json.dumps(choice, indent=1))
        log(
            f"choice: {choice['mode']}, GRaF {choice['graf']['steps']} steps ({choice['graf']['why']}), "
            f"KNN-DL {choice['knn_dl']['steps']} ({choice['knn_dl']['why']})"
        )
        t = time.time()
        summary["jobs"] = run_queue(args, study_jobs(args, choice, data, args.work, extra), args.work)
        summary["stages"]["studies_s"] = round(time.time() - t, 1)
        report(args)
    except Exception as e:  # noqa: BLE001  (whatever finished still goes back)
        log(f"error: {type(e).__name__}: {e}")
        summary["error"] = f"{type(e).__name__}: {e}"
    summary["total_s"] = round(time.time() - T0, 1)
    pack_out(args.work, args.out, summary, args.weights_back)
    log(f"total {summary['total_s']} s")
    return 1 if "error" in summary else 0


if __name__ == "__main__":
    sys.exit(main())
