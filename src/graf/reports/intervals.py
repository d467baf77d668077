"""graf-report's paired comparisons: every cell of a study whose jobs wrote per-spectrum records
(``per_spectrum.csv.gz``), each trained method against KNN and against KNN-DL on the same test spectra, with the
interval and verdict of :mod:`graf.reports.statistics`.  Writes ``intervals.json``, ``intervals.csv`` and
``intervals.md`` (PSNR; the JSON has every metric).

A *cell* is a test scene at one test band under one setting of the study's other axes (trained on, training band,
fine-tuning, L).  A trained method's seeds are its jobs in the cell (``config.seed``); KNN is the baseline tested
beside them (the same in every seed's job: nothing is trained, checked); KNN-DL is the ``knn-dl`` jobs of the same
cell.  Where the training band varies (the bands study), each model trained at another band is also compared with
the model trained at the test band, on the same spectra (:func:`band_transfers`).
"""

from __future__ import annotations

import csv
import io
import math
from collections import defaultdict
from pathlib import Path

from graf.io import atomic_write_bytes, atomic_write_json
from graf.reports.axes import AXES, AXIS_NAMES
from graf.reports.rows import evaluations, job_settings, label_hz, result_files
from graf.reports.statistics import HIGHER_IS_BETTER, paired_difference, summary
from graf.reports.table import read_run_result
from graf.run.per_spectrum import read_per_spectrum

CELL = AXIS_NAMES  # a cell: one value of every study axis (graf.reports.axes)
REFERENCES = ("knn", "knn-dl")
PAIRED_METRICS = tuple(HIGHER_IS_BETTER)


BASELINE_TOLERANCE = 1e-4  # a baseline tested in two jobs: equal up to float rounding (another device, another BLAS)


def same_baseline(a: dict, b: dict) -> bool:
    """Two jobs' records of one baseline ``{metric: {id: value}}``: the same spectra, every value within
    ``BASELINE_TOLERANCE`` (KNN tested on a GPU and on a CPU differs by about 4e-6 dB of PSNR, measured)."""
    if a.keys() != b.keys() or any(a[m].keys() != b[m].keys() for m in a):
        return False
    return all(abs(float(a[m][i]) - float(b[m][i])) <= BASELINE_TOLERANCE for m in a for i in a[m])


def collect_spectra(runs: Path) -> tuple[dict, list]:
    """``{cell key: {method: {seed: {metric: {id: value}}}}}`` of every job under ``runs`` with per-spectrum
    records (baselines keyed under the cell of the job that tested them, seed ``None``), and the jobs'
    ``sim_num_tx`` values (None: the catalog's full datasets)."""
    out: dict = defaultdict(lambda: defaultdict(dict))
    densities: set = set()
    for f in result_files(runs):
        result = read_run_result(f)
        if result is None or not result.get("per_spectrum"):
            continue
        settings = job_settings(result, str(f.parent))
        seed = (result.get("config") or {}).get("seed")
        densities.add((result.get("config") or {}).get("sim_num_tx"))
        trained = result.get("method")
        by_eval: dict = defaultdict(lambda: {m: {} for m in PAIRED_METRICS})
        for row in read_per_spectrum(f.parent / result["per_spectrum"]):
            for m in PAIRED_METRICS:
                if not math.isnan(row[m]):  # NaN: an empty target, left out of every figure (its id of every method)
                    by_eval[(row["eval_scene"], row["method"])][m][row["id"]] = row[m]
        tested = {ev["eval_scene"]: ev for ev in evaluations(result)}  # a cross-band job tests at another band
        for (eval_scene, method), values in by_eval.items():
            ev = tested.get(eval_scene, {"eval_scene": eval_scene})
            at = {a.name: a.evaluation_value(result, ev) for a in AXES if a.of_evaluation is not None}
            key = tuple(at[c] if c in at else str(settings.get(c)) for c in CELL)
            runs_of = out[key][method]
            if method != trained:  # a baseline: the same in every job of the cell (nothing trained)
                if None in runs_of and not same_baseline(runs_of[None], values):
                    raise ValueError(f"{f}: {method} on {eval_scene} differs from its run in another job of the cell")
                runs_of[None] = values
            else:
                runs_of[seed] = values
    return out, sorted(densities, key=str)


def natural(value: str) -> tuple:
    """A cell setting's place in a table: L in numeric order (2, 4, 10, not "10", "2", "4"), fine-tuning
    fractions in theirs (zero-shot, f05, f10, f20, f50, f100), bands by frequency, anything else by name.  The
    bootstrap is seeded per comparison, so the order changes no figure."""
    if value.isdigit():
        return (0, int(value), "")
    hz = label_hz(value)  # a band: 915 MHz before 1.8 GHz
    if hz:
        return (0, hz, "")
    if value == "zero-shot":
        return (1, -1, "")
    if value[:1] == "f" and value[1:].isdigit():
        return (1, int(value[1:]), "")
    return (2, 0, value)


def _cell_order(item: tuple) -> tuple:
    """A ``cells`` item's place: its key's settings in :func:`natural` order."""
    return tuple(map(natural, item[0]))


def comparisons(
    cells: dict,
    metrics: tuple[str, ...] = PAIRED_METRICS,
    references: tuple[str, ...] = REFERENCES,
    imported: tuple = (),
) -> list[dict]:
    """One row per (cell, trained method, metric): its summary and its paired differences to the references.
    ``imported``: methods taken from another record (:func:`import_references`), compared with, never given rows
    of their own."""
    rows = []
    for key, methods in sorted(cells.items(), key=_cell_order):
        cell = dict(zip(CELL, key))
        for method, seeds in sorted(methods.items()):
            if method == "knn" or method in imported:
                continue
            for m in metrics:
                runs = [seeds[s][m] for s in sorted(seeds, key=str)]
                row = {**cell, "method": method, "metric": m, **summary(runs)}
                for ref in references:
                    if ref == method or ref not in methods:
                        continue
                    ref_runs = [methods[ref][s][m] for s in sorted(methods[ref], key=str)]
                    row[f"vs_{ref}"] = paired_difference(runs, ref_runs, m)
                rows.append(row)
    return rows


def l_changes(cells: dict, base_l: int = 2, metrics: tuple[str, ...] = PAIRED_METRICS) -> list[dict]:
    """The neighbor-count study's question: each trained method's change from ``L = base_l`` to every other L,
    pooled over the cells' (trained on, test scene) pairs (the paper averages its four same-family pairs),
    paired by (pair, spectrum id), with the interval of :func:`paired_difference`."""
    pools: dict = defaultdict(lambda: defaultdict(lambda: defaultdict(dict)))  # (method, band, ft) -> L -> seed
    for key, methods in cells.items():
        cell = dict(zip(CELL, key))
        for method, seeds in methods.items():
            if method == "knn" or cell["L"] in ("None", ""):
                continue
            group = pools[(method, cell["train_band"], cell["finetune"])]
            for seed, values in seeds.items():
                run = group[int(cell["L"])].setdefault(seed, {m: {} for m in metrics})
                for m in metrics:
                    pair = (cell["trained_on"], cell["eval_scene"], cell["eval_band"])
                    run[m].update({(*pair, i): v for i, v in values[m].items()})
    rows = []
    for (method, band, ft), by_l in sorted(pools.items()):
        if base_l not in by_l:
            continue
        for L in sorted(by_l):
            if L == base_l:
                continue
            for m in metrics:
                runs = [by_l[L][s][m] for s in sorted(by_l[L], key=str)]
                base = [by_l[base_l][s][m] for s in sorted(by_l[base_l], key=str)]
                c = paired_difference(runs, base, m)
                rows.append(
                    {
                        "method": method,
                        "train_band": band,
                        "finetune": ft,
                        "L_from": base_l,
                        "L_to": L,
                        "metric": m,
                        **c,
                    }
                )
    return rows


def band_transfers(cells: dict, metrics: tuple[str, ...] = PAIRED_METRICS) -> list[dict]:
    """Seed E.5's question: each trained method's model trained at another band than the test band, minus the
    model trained at the test band (the same method, scenes, fine-tuning and L), on the same test spectra, with the
    interval of :func:`paired_difference`.  Empty unless the study varies the training band."""
    rows = []
    for key, methods in sorted(cells.items(), key=_cell_order):
        cell = dict(zip(CELL, key))
        if cell["train_band"] == cell["eval_band"]:
            continue
        home = tuple(cell["eval_band"] if c == "train_band" else cell[c] for c in CELL)
        for method, seeds in sorted(methods.items()):
            if method == "knn" or method not in cells.get(home, {}):
                continue
            for m in metrics:
                runs = [seeds[s][m] for s in sorted(seeds, key=str)]
                ref = [cells[home][method][s][m] for s in sorted(cells[home][method], key=str)]
                rows.append({**cell, "method": method, "metric": m, **paired_difference(runs, ref, m)})
    return rows


def _interval(c: dict | None) -> str:
    if not c:
        return "-"
    return f"{c['diff']:+.2f} [{c['low']:+.2f}, {c['high']:+.2f}] {c['verdict'].split(' ')[0]}"


def _change_tables(record: dict) -> list[str]:
    """The markdown of a record's L changes from L = 2 and its band transfers (PSNR), where the study has them."""
    md: list[str] = []
    changes = [c for c in record["L_changes"] if c["metric"] == "psnr" and c["L_from"] == 2]
    if changes:
        md += ["", "PSNR change from L = 2, pooled over the trained-on / test-scene pairs (paired by spectrum):", ""]
        md += ["| method | L | change (dB) | 95% interval | verdict |", "|---|---|---|---|---|"]
        word = {"ahead": "rises", "behind": "falls"}  # an L change: the verdict as a direction
        md += [
            f"| {c['method']} | 2 -> {c['L_to']} | {c['diff']:+.2f} | [{c['low']:+.2f}, {c['high']:+.2f}] | "
            f"{word.get(c['verdict'], c['verdict'])} |"
            for c in changes
        ]
    transfers = [c for c in record["band_transfers"] if c["metric"] == "psnr"]
    if transfers:
        md += [
            "",
            "PSNR of a model trained at another band, minus the model trained at the test band (paired by spectrum):",
            "",
        ]
        md += [
            "| method | trained at | tested at | difference (dB) | 95% interval | verdict |",
            "|---|---|---|---|---|---|",
        ]
        md += [
            f"| {c['method']} | {c['train_band']} | {c['eval_band']} | {c['diff']:+.2f} | "
            f"[{c['low']:+.2f}, {c['high']:+.2f}] | {c['verdict'].split(' ')[0]} |"
            for c in transfers
        ]
    return md


def import_references(cells: dict, others: list[Path]) -> tuple[str, ...]:
    """Add to ``cells`` the trained methods of other studies' records (``others``: folders of finished jobs with
    per-spectrum records) in the cells this study shares with them, as references for its own methods (a
    per-scene method against GRaF's record of the same scene, say).  A method this study trains itself is not
    taken; KNN, tested in both, must be the same on the same spectra (checked: the two studies then tested the
    same spectra).  Returns the methods taken, in name order."""
    taken: set[str] = set()
    for other in others:
        if not Path(other).is_dir():
            raise FileNotFoundError(f"{other}: no such study record to compare with (graf-report compare_with)")
        theirs, _ = collect_spectra(Path(other))
        for key, methods in theirs.items():
            if key not in cells:
                continue
            ours = cells[key]
            if "knn" in ours and "knn" in methods and not same_baseline(ours["knn"][None], methods["knn"][None]):
                cell = dict(zip(CELL, key))
                raise ValueError(f"{other}: KNN on {cell} differs from this study's: not the same spectra")
            for method, seeds in methods.items():
                if method != "knn" and method not in ours:
                    ours[method] = seeds
                    taken.add(method)
    return tuple(sorted(taken))


def write_intervals(runs: Path, out: Path, compare_with: list[Path] = ()) -> list[dict] | None:
    """intervals.json / .csv / .md of the study under ``runs`` into ``out``; None when no job wrote per-spectrum
    records.  ``compare_with``: other study records whose trained methods are references too
    (:func:`import_references`)."""
    cells, densities = collect_spectra(runs)
    if not cells:
        return None
    compared = {key: dict(methods) for key, methods in cells.items()}  # the L changes stay the study's own
    imported = import_references(compared, list(compare_with))
    extra = tuple(m for m in imported if m not in REFERENCES)
    rows = comparisons(compared, references=REFERENCES + extra, imported=imported)
    record = {"rows": rows, "confidence": 0.95, "rule": "graf.reports.statistics", "sim_num_tx": densities}
    record["compared_with"] = {"records": [str(p) for p in compare_with], "methods": list(imported)}
    record["L_changes"] = l_changes(cells, 2) + l_changes(cells, 4)  # from L = 2 (Table 5's drop), from 4 (plateau)
    record["band_transfers"] = band_transfers(cells)
    atomic_write_json(out / "intervals.json", record)
    refs = ["knn", "knn-dl", *extra]
    head = [*CELL, "method", "seeds", "spectra", "mean", "median", "seed spread", "- KNN", "- KNN-DL"]
    head += [f"- {ref}" for ref in extra]
    body = [
        [
            *(r[c] for c in CELL),
            r["method"],
            r["n_seeds"],
            r["n_spectra"],
            f"{r['mean']:.2f}",
            f"{r['median']:.2f}",
            f"{r['seed_spread']:.2f}",
            *(_interval(r.get(f"vs_{ref}")) for ref in refs),
        ]
        for r in rows
        if r["metric"] == "psnr"
    ]
    text = io.StringIO()
    csv.writer(text, lineterminator="\n").writerows([head, *body])
    atomic_write_bytes(out / "intervals.csv", text.getvalue().encode())
    # the markdown (a docs page includes it) leaves out the columns with one value in every row and says them once
    same = [i for i, h in enumerate(head) if i < len(CELL) + 3 and len({str(b[i]) for b in body}) == 1 and body]
    keep = [i for i in range(len(head)) if i not in same]
    md = ["| " + " | ".join(head[i] for i in keep) + " |", "|" + "---|" * len(keep)] + [
        "| " + " | ".join(str(b[i]) for i in keep) + " |" for b in body
    ]
    note = (
        "PSNR (dB) per cell: mean and median over the test spectra (seed-averaged), the range of the seeds' means, "
        "and each difference to KNN and to KNN-DL with its 95% interval (paired bootstrap over spectra, widened to "
        "include every seed's difference) and verdict (graf.reports.statistics)."
    )
    if imported:
        note += f" {', '.join(imported)}: from {', '.join(map(str, compare_with))}, on the same test spectra."
    if same:
        note += " Every row: " + ", ".join(f"{head[i]} {body[0][i]}" for i in same) + "."
    md += _change_tables(record)
    atomic_write_bytes(out / "intervals.md", (note + "\n\n" + "\n".join(md) + "\n").encode())
    return rows
