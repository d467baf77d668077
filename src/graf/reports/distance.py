"""The neighbour-distance study (``conf/experiment/neighbor_distance.yaml``): what each learned method gains over KNN
and over KNN-DL as the nearest neighbour it may use moves away from the target, in wavelengths of the scene's band.

From a study folder's per-spectrum records (:func:`graf.reports.intervals.collect_spectra`), per family (the
training scene's, its test layouts pooled: 240 paired spectra for two layouts of 120) and per distance
(``neighbors.exclude_within``):

- each trained method minus KNN and minus KNN-DL, with the paired interval of :mod:`graf.reports.statistics`;
- GRaF's mode chosen on validation at that distance (:func:`validation_choice`, from the study's ``validation/``
  jobs: each GRaF mode validated zero-shot on its family's validation layout), and the chosen mode's figures as
  "GRaF"; a study of one GRaF mode and no validation jobs (``experiment=neighbor_distance_rfid``: the mode fixed
  before the runs) shows that mode;
- the geometry each cell's methods saw: the median over its targets of the distance to the nearest neighbour
  actually used, in wavelengths and centimetres (``splits.nearest_neighbor_used`` of each evaluation);
- the distance from which a learned method leads KNN with an interval above 0 at that distance and every larger one
  (:func:`leads_from`), per family and for both families at once; and the sentence that turns a survey's spacing
  into a choice (:func:`advice`).

Writes ``distance.json`` and ``vs_distance.png``; graf-report's README block shows :func:`markdown`.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np

from graf.bands import SPEED_OF_LIGHT
from graf.io import atomic_write_json
from graf.reports.intervals import CELL, collect_spectra
from graf.reports.rows import VALIDATION_DIR, evaluations, result_files
from graf.reports.statistics import paired_difference
from graf.reports.table import read_run_result

AXIS = "exclude_within"
GRAF = "graf"  # the chosen GRaF mode's label in the figures and tables
NAMES = {GRAF: "GRaF (the mode of each distance)", "knn": "KNN", "knn-dl": "KNN-DL"}
CHOSEN = {"fixed": " (fixed before the runs)", "validation": " (chosen on validation)"}  # how the GRaF mode was chosen


def is_graf(method: str) -> bool:
    return method.startswith("graf")


def _val_psnr(result: dict) -> list[float]:
    """A validation job's PSNR on each layout it validated on (its evaluations'; else its headline figure)."""
    values = [(ev.get("metrics") or {}).get("val/psnr") for ev in evaluations(result)]
    values = [float(v) for v in values if v is not None]
    headline = (result.get("metrics") or {}).get("val/psnr")
    return values or ([float(headline)] if headline is not None else [])


def validation_choice(runs: Path) -> dict[str, dict]:
    """``{distance: {"mode", "val_psnr": {mode: mean}}}``: at each distance, the GRaF mode with the higher mean
    validation PSNR over the study's validation jobs (``<runs>/validation/``, ``test=false``: trained as a study job
    and validated zero-shot on the validation layouts conference_v4 and office_v4, which no study tests on; the
    mean over the jobs and their layouts); a tie goes to the mode first by name.  Empty without validation jobs."""
    psnr: dict = defaultdict(lambda: defaultdict(list))
    folder = Path(runs) / VALIDATION_DIR
    for f in sorted(folder.rglob("results.json")) if folder.is_dir() else []:
        result = read_run_result(f)
        if result is None or not is_graf(str(result.get("method"))):
            continue
        distance = str(((result.get("config") or {}).get("neighbors") or {}).get(AXIS))
        psnr[distance][result["method"]] += _val_psnr(result)
    out = {}
    for distance, modes in psnr.items():
        means = {m: float(np.mean(v)) for m, v in sorted(modes.items()) if v}
        out[distance] = {"mode": sorted(means, key=lambda m: (-means[m], m))[0], "val_psnr": means}
    return out


def geometry(runs: Path) -> dict[tuple[str, str, str], dict]:
    """``{(trained on, distance, test layout): nearest neighbour used}`` (median metres and wavelengths over the
    layout's targets) from the study's jobs: the test neighbours depend on the layout and the distance alone, so any
    job of the cell gives them."""
    out = {}
    for f in result_files(Path(runs)):
        result = read_run_result(f)
        if result is None:
            continue
        distance = str(((result.get("config") or {}).get("neighbors") or {}).get(AXIS))
        trained = "+".join(result.get("train_scenes") or [result.get("scene")])
        for ev in evaluations(result):
            used = (ev.get("splits") or {}).get("nearest_neighbor_used")
            if used and ev.get("band_hz"):
                wavelength = SPEED_OF_LIGHT / float(ev["band_hz"])
                out.setdefault((trained, distance, ev["eval_scene"]), {**used, "wavelength_m": wavelength})
    return out


def _pooled(cell_runs: list[dict], method: str) -> list[dict] | None:
    """One method's runs over the family's test layouts: ``[{(layout, id): psnr}]`` per seed (baselines: one run);
    None when a layout lacks the method or its seeds differ between layouts."""
    per_layout = [(layout, methods.get(method)) for layout, methods in cell_runs]
    if any(seeds is None for _, seeds in per_layout):
        return None
    seeds = sorted(per_layout[0][1], key=str)
    if any(sorted(s, key=str) != seeds for _, s in per_layout):
        return None
    return [{(layout, i): v for layout, s in per_layout for i, v in s[seed]["psnr"].items()} for seed in seeds]


def differences(cells: dict, choice: dict[str, dict]) -> dict[str, dict[str, dict]]:
    """``{family (trained on): {distance: {method: {"vs_knn", "vs_knn-dl"}}}}``: each trained method (and ``graf``,
    the mode chosen at that distance) minus KNN and KNN-DL on the family's pooled test spectra."""
    at = {name: CELL.index(name) for name in ("trained_on", "eval_scene", AXIS)}
    groups: dict = defaultdict(list)
    for key, methods in cells.items():
        if key[at["trained_on"]] in ("-", "None", ""):
            continue
        groups[(key[at["trained_on"]], key[at[AXIS]])].append((key[at["eval_scene"]], methods))
    out: dict = defaultdict(dict)
    for (family, distance), cell_runs in sorted(groups.items()):
        cell_runs.sort(key=lambda x: x[0])
        methods = sorted({m for _, ms in cell_runs for m in ms} - {"knn"})
        refs = {r: _pooled(cell_runs, r) for r in ("knn", "knn-dl")}
        row = {}
        for method in methods:
            runs = _pooled(cell_runs, method)
            if runs is None:
                continue
            row[method] = {
                f"vs_{r}": paired_difference(runs, ref, "psnr")
                for r, ref in refs.items()
                if ref is not None and r != method
            }
        chosen, how = (choice.get(distance) or {}).get("mode"), "validation"
        grafs = [m for m in row if is_graf(m)]
        if chosen is None and len(grafs) == 1:  # one GRaF mode, no validation jobs: the mode fixed before the runs
            chosen, how = grafs[0], "fixed"
        if chosen in row:
            row[GRAF] = {**row[chosen], "mode": chosen, "chosen_on": how}
        out[family][distance] = row
    return dict(out)


def leads_from(points: dict[str, dict], method: str, reference: str = "knn") -> float | None:
    """The smallest distance from which ``method`` leads ``reference`` (interval above 0) at that distance and at
    every larger one of ``points`` (``{distance: {method: {"vs_<reference>"}}}``); None when it does not lead at
    the largest."""
    found = None
    for distance in sorted(points, key=float, reverse=True):
        c = (points[distance].get(method) or {}).get(f"vs_{reference}")
        if c is None or c["verdict"] != "ahead":
            break
        found = float(distance)
    return found


def thresholds(diffs: dict) -> dict[str, dict]:
    """``{method: {"vs_knn": {family: distance or None, "all": ...}, "vs_knn-dl": ...}}`` (:func:`leads_from`): the
    distance from which the method leads, per family and in every family at once (the largest of theirs)."""
    methods = sorted({m for fam in diffs.values() for row in fam.values() for m in row})
    out = {}
    for m in methods:
        out[m] = {}
        for ref in ("knn", "knn-dl"):
            if m == ref:
                continue
            per = {fam: leads_from(points, m, ref) for fam, points in sorted(diffs.items())}
            per["all"] = None if any(v is None for v in per.values()) or not per else max(per.values())
            out[m][f"vs_{ref}"] = per
    return out


def _wl(distance: float) -> str:
    return f"{distance:g} wavelength{'' if distance == 1 else 's'}"


def _everywhere(record: dict) -> str:
    """Where a threshold holds: in every family of the rooms, or within the one scene a record tests itself on."""
    return "within the scene" if record.get("within_scene") else "in every family"


def fixed_mode(record: dict) -> str | None:
    """The GRaF mode fixed before the runs when that one mode stands at every point of the record, else None (the
    mode of each distance is chosen on validation)."""
    rows = [p.get(GRAF) or {} for points in record["differences"].values() for p in points.values()]
    ways = {(r.get("mode"), r.get("chosen_on")) for r in rows if r}
    mode, how = next(iter(ways)) if len(ways) == 1 else (None, None)
    return mode if how == "fixed" else None


def method_label(record: dict, method: str) -> str:
    """A method's name in the figure and the thresholds; GRaF's names its mode where :func:`fixed_mode` has one."""
    if method != GRAF:
        return NAMES.get(method, method)
    mode = fixed_mode(record)
    return NAMES[GRAF] if mode is None else f"GRaF ({mode}, fixed before the runs)"


def _cm(distance: float, wavelength_m: float | None, within: bool = False) -> str:
    band = "this scene's band" if within else "these layouts' band"
    return "" if wavelength_m is None else f" ({100 * distance * wavelength_m:.0f} cm at {band})"


def between_learned(record: dict) -> str:
    """Where GRaF and KNN-DL both lead KNN but GRaF does not lead KNN-DL in every family: which of the two to take,
    from GRaF - KNN-DL in each (family, distance) cell of the record ("" when no cell compares them)."""
    verdicts: dict = defaultdict(dict)
    for family, points in record["differences"].items():
        for distance, row in points.items():
            c = (row.get(GRAF) or {}).get("vs_knn-dl")
            if c is not None:
                verdicts[family][float(distance)] = c["verdict"].split(" ")[0]
    cells = [v for per in verdicts.values() for v in per.values()]
    if not cells:
        return ""
    families = []
    for family, per in sorted(verdicts.items()):
        kinds = sorted(set(per.values()), key=lambda v: min(d for d in per if per[d] == v))
        if len(kinds) == 1:
            families.append(f"{kinds[0]} at every distance tested in {family}'s family")
            continue
        at = [(v, [f"{d:g}" for d in sorted(x for x in per if per[x] == v)]) for v in kinds]
        said = ", ".join(f"{v} at {' and '.join(ds)}" for v, ds in at)
        families.append(f"{said} wavelengths in {family}'s family")
    ahead, behind = cells.count("ahead"), cells.count("behind")
    then = (
        "so where both lead KNN, GRaF is the choice" if ahead and not behind
        else "so where both lead KNN, KNN-DL is the choice" if behind and not ahead
        else "so either does" if not ahead and not behind
        else "so which of the two pays depends on the room"
    )  # fmt: skip
    counts = f"{ahead} of {len(cells)} cells ahead, {behind} behind"
    return f"against KNN-DL, GRaF is {' and '.join(families)} ({counts}), {then}"


def advice(record: dict) -> str:
    """The sentence that turns a survey's spacing into a choice, from the record's thresholds alone (a method that
    leads from the smallest distance tested leads "at every distance tested"), and, where both learned methods lead
    KNN, which of them to take (:func:`between_learned`)."""
    t, wl = record["thresholds"], record.get("wavelength_m")
    within = bool(record.get("within_scene"))  # one scene tested within itself: no families to speak of
    everywhere, scenes = _everywhere(record), "in this scene" if within else "in these scenes"
    tested = sorted(float(d) for d in record["distances"]) or [0.0]
    span = f"{tested[0]:g} to {_wl(tested[-1])}"

    def cm(x: float) -> str:
        return _cm(x, wl, within)

    def since(x: float) -> str:
        return f"at every distance tested ({span})" if x <= tested[0] else f"from {_wl(x)}{cm(x)}"

    graf, dl = (t.get(GRAF) or {}).get("vs_knn", {}).get("all"), (t.get("knn-dl") or {}).get("vs_knn", {}).get("all")
    over_dl = (t.get(GRAF) or {}).get("vs_knn-dl", {}).get("all")
    if graf is None and dl is None:
        return (
            f"Up to {_wl(tested[-1])}{cm(tested[-1])} between a target and its nearest measured neighbour, "
            f"neither learned method leads KNN {everywhere} with an interval above 0: {scenes} a "
            "nearest-neighbour mean of the survey is the choice."
        )
    parts = []
    if graf is not None and graf > tested[0]:
        parts.append(
            f"If your nearest measurements are {_wl(graf)}{cm(graf)} or farther from where you predict (tested "
            f"up to {_wl(tested[-1])}), GRaF leads KNN {everywhere}"
        )
    elif graf is not None:
        parts.append(f"GRaF leads KNN {everywhere} {since(graf)}")
    if over_dl is not None:
        parts.append(f"GRaF leads KNN-DL {since(over_dl)}")
    if dl is not None:
        parts.append(f"KNN-DL leads KNN {since(dl)}")
    if graf is not None and dl is not None and over_dl is None and (which := between_learned(record)):
        parts.append(which)
    closer = min(v for v in (graf, dl) if v is not None)
    if closer <= tested[0]:
        return "; ".join(parts) + "."
    return "; ".join(parts) + f". Closer than {_wl(closer)}, no learned method leads KNN {everywhere}: use KNN."


def write_distance(runs: Path, out: Path) -> dict | None:
    """The study's distance record (``distance.json``) and figure (``vs_distance.png``) under ``out``; None when
    the study does not vary ``neighbors.exclude_within``."""
    cells, _ = collect_spectra(runs)
    distances = sorted({k[CELL.index(AXIS)] for k in cells}, key=float)
    if len(distances) < 2:
        return None
    choice = validation_choice(runs)
    diffs = differences(cells, choice)
    geo = geometry(runs)
    wavelengths = sorted({g["wavelength_m"] for g in geo.values()})
    record = {
        "distances": distances,
        "choice": choice,
        "differences": diffs,
        "thresholds": thresholds(diffs),
        "geometry": [
            {"trained_on": k[0], AXIS: k[1], "eval_scene": k[2], **v} for k, v in sorted(geo.items())
        ],  # fmt: skip
        "wavelength_m": wavelengths[0] if len(wavelengths) == 1 else None,
        "within_scene": bool(geo) and all(k[0] == k[2] for k in geo),  # tested on the training scene itself
    }
    record["advice"] = advice(record)
    atomic_write_json(out / "distance.json", record)
    figure(record, out / "vs_distance.png")
    return record


def figure(record: dict, path: Path) -> None:
    """GRaF (the chosen mode) and KNN-DL minus KNN (left), GRaF minus KNN-DL (right), against the distance, one
    line per family and method, with the 95% intervals as bars."""
    import matplotlib.pyplot as plt

    from graf.plotting import save_figure

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), constrained_layout=True)
    panels = (("vs_knn", (GRAF, "knn-dl"), "minus KNN"), ("vs_knn-dl", (GRAF,), "minus KNN-DL"))
    for ax, (ref, methods, title) in zip(axes, panels):
        for i, (family, points) in enumerate(sorted(record["differences"].items())):
            for j, m in enumerate(methods):
                xs, ys, lo, hi = [], [], [], []
                for d in sorted(points, key=float):
                    c = (points[d].get(m) or {}).get(ref)
                    if c is not None:
                        xs.append(float(d) + 0.04 * (2 * i + j))  # side by side, never hidden behind another
                        ys.append(c["diff"])
                        lo.append(c["diff"] - c["low"])
                        hi.append(c["high"] - c["diff"])
                if xs:
                    label = f"{method_label(record, m)}, trained on {family}"
                    ax.errorbar(xs, ys, yerr=[lo, hi], marker="os"[j], ls="-" if m == GRAF else "--", capsize=3,
                                color=f"C{i}", label=label)  # fmt: skip
        ax.axhline(0.0, color="k", lw=0.8)
        ax.set_xlabel("neighbours left out within (wavelengths): neighbors.exclude_within")
        ax.set_ylabel(f"test PSNR {title} (dB)")
        where = "within the scene" if record.get("within_scene") else "same-family test layouts pooled"
        ax.set_title(f"{title}, {where}, 95% intervals", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    save_figure(fig, path, dpi=100)


def _fmt(c: dict | None) -> str:
    if c is None:
        return "-"
    mark = {"ahead": " (ahead)", "behind": " (behind)"}.get(c["verdict"], "")
    return f"{c['diff']:+.2f} [{c['low']:+.2f}, {c['high']:+.2f}]{mark}"


def markdown(record: dict) -> str:
    """The distance record as a README section: per family and distance, the mode chosen on validation, the
    nearest neighbour used, and the paired differences; then the thresholds and the advice."""
    geo = defaultdict(list)
    for g in record["geometry"]:
        geo[(g["trained_on"], g[AXIS])].append(
            f"{g['eval_scene']}: {g['median_wavelengths']:.2f} λ, {100 * g['median_m']:.1f} cm"
        )
    head = ["trained on", "left out within (λ)", "GRaF mode", "nearest used (median)",
            "GRaF - KNN", "GRaF - KNN-DL", "KNN-DL - KNN"]  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for family, points in sorted(record["differences"].items()):
        for d in sorted(points, key=float):
            row = points[d]
            g, dl = row.get(GRAF) or {}, row.get("knn-dl") or {}
            used = "; ".join(geo.get((family, d), [])) or "-"
            how = CHOSEN.get(g.get("chosen_on"), "")
            mode = g.get("mode", "-") + how
            cells = [family, f"{float(d):g}", mode, used,
                     _fmt(g.get("vs_knn")), _fmt(g.get("vs_knn-dl")), _fmt(dl.get("vs_knn"))]  # fmt: skip
            lines.append("| " + " | ".join(cells) + " |")
    said, everywhere, fixed = [], _everywhere(record), fixed_mode(record)
    for m, refs in sorted(record["thresholds"].items()):
        if m == fixed:
            continue  # GRaF's line, which names the mode, says the same
        for ref, per in refs.items():
            v = per.get("all")
            said.append(
                f"- {method_label(record, m)} over {NAMES[ref.removeprefix('vs_')]}: "
                + (f"leads from {_wl(v)} {everywhere}" if v is not None else f"no distance {everywhere}")
                + " ("
                + ", ".join(f"{f}: {'-' if x is None else f'{x:g}'}" for f, x in per.items() if f != "all")
                + ")"
            )
    return "\n".join([*lines, "", "Where each learned method leads (interval above 0 at that distance and beyond):",
                      "", *said, "", f"**{record['advice']}**"])  # fmt: skip
