"""Write the main job's headline tables into the README (between their headline markers) from the published records
``sweeps/main_job/results.json`` and, where the README has its block, the accurate variant's
``sweeps/main_job_accurate/results.json``, the neighbour-distance study's advice
(the ``distance.json`` of ``DISTANCE``, once made), the default tests' timed run (``sweeps/test_timing/results.json``,
``scripts/time_tests.py``) and the set-up and main job timed as a newcomer runs them
(``sweeps/newcomer_timing/results.json``, ``scripts/time_newcomer.sh``): ``python scripts/headline.py``
(``--check``: exit 1 if the README differs). The site's pages include the same table through ``<!-- gen: headline
-->``; tests/test_docs_layout.py checks that the README's is up to date."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from omegaconf import OmegaConf

from graf.errors import UserError
from graf.reports.table import ACCURATE, HEADLINE, markers, with_headline

ROOT = Path(__file__).resolve().parents[1]


TEST_TIMING = "sweeps/test_timing/results.json"  # scripts/time_tests.py's record of the README's test command
TEST_TIMING_MARKERS = (f"<!-- test-timing: generated from {TEST_TIMING}; do not edit -->", "<!-- /test-timing -->")


def test_timing(record: dict) -> str:
    """The README's words for the default tests' timed run (its record: :data:`TEST_TIMING`)."""
    minutes, seconds = divmod(round(float(record["wall_s"])), 60)
    m = record.get("machine") or {}
    busy = record.get("other_load_cores")
    quiet = "" if busy is None else (", the machine quiet" if busy < 0.2 else f", beside {busy:.1f} busy cores")
    return (
        f"the default tests {minutes} min {seconds} s ({record.get('pytest_closing')}; {m.get('cores')}-core "
        f"{m.get('cpu')}, {record.get('date')}, commit {record.get('commit')}{quiet}; `{TEST_TIMING}`)"
    )


def with_test_timing(text: str, record: dict) -> str:
    """``text`` (the README) with its test-timing block (inline, between :data:`TEST_TIMING_MARKERS`) regenerated."""
    start, end = TEST_TIMING_MARKERS
    if start not in text or end not in text.split(start, 1)[1]:
        raise UserError(f"no test-timing block ({start} ... {end}) to fill")
    before, rest = text.split(start, 1)
    return f"{before}{start}{test_timing(record)}{end}{rest.split(end, 1)[1]}"


NEWCOMER = "sweeps/newcomer_timing/results.json"  # scripts/time_newcomer.sh's record of the README's first command
NEWCOMER_MARKERS = (f"<!-- newcomer-timing: generated from {NEWCOMER}; do not edit -->", "<!-- /newcomer-timing -->")


def _mmss(seconds: float) -> str:
    minutes, seconds = divmod(round(float(seconds)), 60)
    return f"{minutes} min {seconds} s" if minutes else f"{seconds} s"


def newcomer_timing(record: dict) -> str:
    """The README's words for the set-up and the main job timed as a newcomer runs them (:data:`NEWCOMER`)."""
    m = record.get("machine") or {}
    return (
        f"the set-up took {_mmss(record['setup_s'])} and the main job {_mmss(record['main_job_s'])} "
        f"({m.get('cores')}-core {m.get('cpu')}, {record.get('date')}, commit {record.get('commit')}; `{NEWCOMER}`)"
    )


def with_block(text: str, markers: tuple[str, str], words: str) -> str:
    """``text`` with the inline block between ``markers`` holding ``words``."""
    start, end = markers
    if start not in text or end not in text.split(start, 1)[1]:
        raise UserError(f"no block ({start} ... {end}) to fill")
    before, rest = text.split(start, 1)
    return f"{before}{start}{words}{end}{rest.split(end, 1)[1]}"


SEEDS = "sweeps/main_job_accurate_seeds"  # the accurate variant's further seeds (seed 0: sweeps/main_job_accurate)
CLAIM = "target_rfid_paper_figure"  # the ledger's claim whose ``seeds`` (conf/claims.yaml) are the variant's runs
PLANNED_SEEDS = 3  # the runs the headline is to be reported over (seeds 0, 1 and 2)
SEEDS_MARKERS = (
    f"<!-- seeds: generated from the runs conf/claims.yaml names for {CLAIM} and sweeps/claims; do not edit -->",
    "<!-- /seeds -->",
)
README_SEEDS_MARKERS = ("<!-- seeds-sentence: generated from sweeps/claims and the seed runs; do not edit -->",
                        "<!-- /seeds-sentence -->")  # fmt: skip


def seed_runs() -> list[dict]:
    """The runs (results.json, read) that the ledger's :data:`CLAIM` averages, in its config's order."""
    claims = OmegaConf.load(ROOT / "src" / "graf" / "conf" / "claims.yaml").claims
    seeds = next(c for c in claims if c.id == CLAIM).seeds
    return [{"path": str(Path(f).parent), **json.loads((ROOT / f).read_text())} for f in seeds]


def ledger_row() -> dict:
    return next(r for r in json.loads((ROOT / "sweeps/claims/results.json").read_text())["rows"] if r["id"] == CLAIM)


def seeds_table() -> str:
    """The accurate variant's runs side by side (each planned seed not run yet: "not run yet"), and the ledger's
    interval over their test spectra (``sweeps/claims/results.json``, :data:`CLAIM`)."""
    lines = ["| seed | test PSNR (dB) | SSIM | LPIPS | val PSNR (dB) | KNN test PSNR (dB) | torch threads | training |",
             "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    runs = seed_runs()
    for r in runs:
        m, knn = r["metrics"], (r.get("baselines") or {}).get("knn", {}).get("metrics", {})
        threads = (r.get("config") or {}).get("torch_threads") or "torch's default (the cores)"
        resumed = (r.get("resumed") or {}).get("global_step")
        trained = f"{r['global_step']:,} steps" + (f" (resumed at step {resumed})" if resumed else "")
        lines.append(
            f"| {r['config']['seed']} (`{r['path']}`) | {m['test/psnr']:.2f} | {m['test/ssim']:.3f} "
            f"| {m['test/lpips']:.3f} | {m['val/psnr']:.2f} | {knn.get('test/psnr', float('nan')):.2f} | {threads} "
            f"| {trained}, {r['timing']['fit_s'] / 60:.0f} min in its last attempt |"
        )
    ran = {int(r["config"]["seed"]) for r in runs}
    lines += [f"| {s} | not run yet | | | | | | |" for s in range(PLANNED_SEEDS) if s not in ran]
    row = ledger_row()
    return "\n".join(lines) + (
        f"\n\nThe ledger's reading (`{CLAIM}`): {row['platform']} {row['interval']}, "
        f"**{row['verdict']}** against the paper's 21.94 dB."
    )


def seeds_sentence() -> str:
    """The README's words on the accurate variant's seeds: which have run, and the ledger's reading of them."""
    seeds = [str(r["config"]["seed"]) for r in seed_runs()]
    row, missing = ledger_row(), PLANNED_SEEDS - len(seeds)
    told = " and ".join([", ".join(seeds[:-1]), seeds[-1]]) if len(seeds) > 1 else seeds[0]
    return (
        f"Over seeds {told} (`{SEEDS}/`), each test spectrum averaged over the runs, the mean is "
        f"{row['platform']} dB with the 95% interval {row['interval']}: the ledger reads **{row['verdict']}** against "
        f"the paper's 21.94 dB, judged on the interval's lower end ([Claims ledger](docs/claims.md), `{CLAIM}`)"
        + (f"; {missing} seed{'s' * (missing > 1)} still to run." if missing else ".")
    )


DISTANCE = "sweeps/neighbor_distance_paper"  # the rooms' neighbour-distance study (experiment=neighbor_distance)
DISTANCE_MARKERS = (f"<!-- distance-sentence: generated from {DISTANCE}/distance.json; do not edit -->",
                    "<!-- /distance-sentence -->")  # fmt: skip


def distance_sentence() -> str:
    """The README's words on how sparse a survey may be: the rooms' neighbour-distance record's advice, or how far
    its run has got (the jobs finished of those planned: docs_hooks/distance.py)."""
    sys.path.insert(0, str(ROOT))
    from docs_hooks.distance import finished_jobs, planned_jobs, script, seeds

    record = ROOT / DISTANCE / "distance.json"
    done, planned = finished_jobs(ROOT / DISTANCE), planned_jobs()
    if record.is_file():
        data = json.loads(record.read_text())
        n = " to ".join(str(k) for k in sorted({min(seeds(data)), max(seeds(data))}))
        so_far = "" if done >= planned else f"; {done} of its {planned} jobs so far, `{script()}` goes on"
        return (
            f"From the neighbour-distance study (`{DISTANCE}/`, {n} seed{'s' if n != '1' else ''} a point, paired 95% "
            f"intervals{so_far}): **{data['advice']}**"
        )
    return (
        f"The neighbour-distance study, which answers this with intervals across the rooms, is under way: {done} of "
        f"its {planned} jobs have finished (`{script()}` goes on with it)."
    )


def main(argv: list[str]) -> int:
    readme = ROOT / "README.md"
    text = readme.read_text()
    new = with_headline(text, json.loads((ROOT / HEADLINE).read_text()))
    if markers(ACCURATE)[0] in new:
        new = with_headline(new, json.loads((ROOT / ACCURATE).read_text()), ACCURATE)
    if TEST_TIMING_MARKERS[0] in new:  # the default tests' timed run (scripts/time_tests.py)
        new = with_test_timing(new, json.loads((ROOT / TEST_TIMING).read_text()))
    if NEWCOMER_MARKERS[0] in new:  # the set-up and the main job, timed as a newcomer (scripts/time_newcomer.sh)
        new = with_block(new, NEWCOMER_MARKERS, newcomer_timing(json.loads((ROOT / NEWCOMER).read_text())))
    if README_SEEDS_MARKERS[0] in new:
        new = with_block(new, README_SEEDS_MARKERS, seeds_sentence())
    if DISTANCE_MARKERS[0] in new:  # how sparse a survey may be (the rooms' neighbour-distance study)
        new = with_block(new, DISTANCE_MARKERS, distance_sentence())
    seeds = ROOT / SEEDS / "README.md"
    seeds_text = seeds.read_text() if seeds.is_file() else ""
    seeds_new = with_block(seeds_text, SEEDS_MARKERS, "\n" + seeds_table() + "\n") if seeds_text else ""
    if "--check" in argv:
        return 0 if new == text and seeds_new == seeds_text else 1
    readme.write_text(new)
    if seeds_text:
        seeds.write_text(seeds_new)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
