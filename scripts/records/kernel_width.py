"""The record sweeps/kernel_width/: GRaF's compiled kernel at 8 lanes (32-byte vectors, what an AVX2 CPU now builds)
against 16 lanes (64-byte vectors, as before), the same runs otherwise.  Each pair is a folder with bytes_64/ and
bytes_32/ (a graf-train run each, GRAF_KERNEL_VECTOR_BYTES=64 and =32); this writes the record's README.md, its
figures read from the runs' results.json and per_spectrum.csv.gz (``--check``: exit 1 if the README differs):

    python scripts/records/kernel_width.py [--check]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from graf.reports.statistics import paired_difference
from graf.run.per_spectrum import read_per_spectrum

ROOT = Path(__file__).resolve().parents[2]
RECORD = ROOT / "sweeps" / "kernel_width"
RUN = "GRAF_KERNEL_VECTOR_BYTES={w} graf-train "
PAIRS = {  # folder: (what it is, the command that made each run: {w} the vector bytes)
    "main_job": (
        "the main job (`rfid_s23`, 300 steps, 40 test spectra)",
        RUN + "experiment=graf_rfid_s23 hydra.run.dir=sweeps/kernel_width/main_job/bytes_{w}",
    ),
    "paper_cell": (
        "a 1,000-step cell at the paper's density (trained on conference_v1, 120 test spectra of conference_v2)",
        RUN + "experiment=cross_scene_matrix model=graf_cpu_scenes_ray_weights scene=conference_v1 seed=0 "
        "study_steps=1000 'eval_scene=[conference_v2]' torch_threads=2 reliance=false data_root=data hydra.mode=RUN "
        "hydra.run.dir=sweeps/kernel_width/paper_cell/bytes_{w}",
    ),
}
METRICS = ("psnr", "ssim", "lpips")


def _run(folder: Path) -> tuple[dict, dict]:
    result = json.loads((folder / "results.json").read_text())
    rows = [r for r in read_per_spectrum(folder / "per_spectrum.csv.gz") if r["method"] == result["method"]]
    return result, {m: {(r["eval_scene"], r["id"]): r[m] for r in rows} for m in METRICS}


def pair(name: str) -> str:
    """One pair's section: its command, the speed of each width and the paired difference, 8 lanes minus 16."""
    what, command = PAIRS[name]
    folder = RECORD / name
    lines = [f"## `{name}/`: {what}", "", "```bash", command.format(w=64), command.format(w=32), "```", ""]
    if not all((folder / f"bytes_{w}" / "results.json").is_file() for w in (64, 32)):
        return "\n".join(lines + ["Not run yet."])
    (old, old_rows), (new, new_rows) = _run(folder / "bytes_64"), _run(folder / "bytes_32")
    t_old, t_new = old["timing"], new["timing"]
    lines += [
        "| vector | s per training step | s per test spectrum | test PSNR (dB) | prediction hash |",
        "|---|---|---|---|---|",
    ]
    for label, r, t in (("16 lanes (64 bytes)", old, t_old), ("8 lanes (32 bytes)", new, t_new)):
        hashes = next(iter(r["prediction_sha256"].values()))[r["method"]][:12]
        lines.append(f"| {label} | {t['fit_s_per_step']:.3f} | {t['test_s_per_spectrum']:.3f} "
                     f"| {r['metrics']['test/psnr']:.4f} | `{hashes}` |")  # fmt: skip
    lines += [
        "",
        f"8 lanes train {t_old['fit_s_per_step'] / t_new['fit_s_per_step']:.2f}x and test "
        f"{t_old['test_s_per_spectrum'] / t_new['test_s_per_spectrum']:.2f}x faster here. Paired by test spectrum, "
        "8 lanes minus 16 (95% interval, graf.reports.statistics.paired_difference):",
        "",
    ]
    for m in METRICS:
        c = paired_difference([new_rows[m]], [old_rows[m]], m)
        lines.append(f"- {m.upper()}: {c['diff']:+.4f} [{c['low']:+.4f}, {c['high']:+.4f}] over "
                     f"{c['n_spectra']} spectra, {c['verdict']}")  # fmt: skip
    threads = new["config"].get("torch_threads")
    lines += ["", f"Torch threads: {threads or 'the default (the machine`s 2 cores)'}.".replace("`", "'")]
    return "\n".join(lines)


def readme() -> str:
    head = """# GRaF's compiled CPU kernel at the CPU's own vector width

GRaF's CPU kernels (`src/graf/models/graf/kernels/attention_cpu.cpp`) work on vectors of 16 floats. On a CPU with
AVX-512 a vector is one register. On one with AVX2 alone, such as this 2-core AMD EPYC, each vector is split into two
registers, and the arrays of vectors that the training step's attention backward keeps (queries, gradients, keys,
values) no longer fit the 16 registers: they spill to memory. The kernel now builds with 8-lane vectors where the CPU
has AVX2 but not AVX-512, and with 16 lanes elsewhere, as before. `GRAF_KERNEL_VECTOR_BYTES=64` builds the 16-lane
kernel anywhere, and `=32` the 8-lane one.

Each lane is one query, key or ray, and nothing is summed across lanes. So the width changes only which
multiply-adds the compiler fuses: the last bits of a prediction move (its hash changes), the figures do not. Each
pair below trains and tests twice from the same seed, once with each width, nothing else running, on the 2-core AMD
EPYC without AVX-512 of the development machine (2026-12-05, torch 2.13 on the CPU). The 16-lane run of
the main job gives the prediction hash the platform published before the change (`sweeps/newcomer_timing/`).
Generated by `python scripts/records/kernel_width.py` from the runs' `results.json` and `per_spectrum.csv.gz`."""
    return "\n\n".join([head, *(pair(name) for name in PAIRS)]) + "\n"


def main(argv: list[str]) -> int:
    text, path = readme(), RECORD / "README.md"
    if "--check" in argv:
        return 0 if path.is_file() and path.read_text() == text else 1
    path.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
