"""graf-oracle: the per-pixel linear-fusion oracle of supplement A.2 on a scene (see graf.analysis.oracle).

    graf-oracle                                     # rfid_s23 test targets, L = 6, 200 iterations, lrs 1e-3, 1e-2
    graf-oracle oracle.split=all 'oracle.lrs=[1e-3]' scene=... neighbors.L=...

Writes results.json (the first lr's per-target PSNRs and their mean / std / median / min / max at the top
level, every lr under ``runs`` with its fitted-weight statistics, IDW KNN on the same neighbors under
``idw``, the paper's 20.5 +- 4.1 dB under ``reference``) and oracle_psnr.png into the Hydra output folder,
and prints a summary table.
"""

from __future__ import annotations

import time

from omegaconf import DictConfig, OmegaConf

from graf.analysis.oracle import PAPER_REFERENCE, plot_oracle, run_oracle, select_targets, summarize
from graf.app.config import output_dir, single_scene_config, task_wrapper
from graf.io import atomic_write_json
from graf.run.build import build_datamodule


def format_table(results: dict) -> str:
    head = f"{'':<18}{'lr':>8}{'n':>6}{'mean':>8}{'std':>7}{'median':>8}{'min':>8}{'max':>8}"
    lines = [head, "-" * len(head)]

    def row(name, lr, s):
        lines.append(
            f"{name:<18}{lr:>8}{s['n']:>6}{s['mean']:>8.2f}{s['std']:>7.2f}{s['median']:>8.2f}"
            f"{s['min']:>8.2f}{s['max']:>8.2f}"
        )

    for run in results["runs"]:
        row("oracle (A.2)", f"{run['lr']:g}", run["psnr"])
    row("IDW KNN", "-", results["idw"]["psnr"])
    ref = results["reference"]
    lines.append(f"{'paper A.2':<18}{'?':>8}{'':>6}{ref['psnr_mean']:>8.2f}{ref['psnr_std']:>7.2f}")
    return (
        f"PSNR (dB) of {results['scene']} {results['split']} targets, L={results['L']}, "
        f"{results['iterations']} iterations\n" + "\n".join(lines)
    )


@task_wrapper
def run(cfg: DictConfig) -> dict:
    """graf-oracle: the oracle and IDW KNN on the scene's targets; results.json and the figure, a table printed."""
    started = time.perf_counter()
    oc = cfg.oracle
    single_scene_config(cfg, "graf-oracle")
    bands, _, neighbors, dm = build_datamodule(cfg)
    band = bands[0]
    dm.setup()
    rows, src_index, src_mask = select_targets(dm, oc.split)
    fit = run_oracle(
        dm.data.spectra, dm.positions, rows, src_index, src_mask, list(oc.lrs), oc.iterations, oc.chunk_targets
    )
    runs = [{"lr": r["lr"], "psnr": summarize(r["psnr"]), "weights": r["weights"]} for r in fit["runs"]]
    head = runs[0]
    results = {
        "analysis": "oracle",
        "scene": dm.data.name,
        "band_hz": float(band.frequency_hz),
        "split": oc.split,
        "n": head["psnr"]["n"],
        "L": int(src_index.shape[1]),
        "neighbors": repr(neighbors),
        "iterations": int(oc.iterations),
        "lr": head["lr"],
        "psnr": head["psnr"],
        "weights": head["weights"],
        "ids": [int(i) for i in dm.ids[rows]],
        "runs": runs,
        "idw": {"psnr": summarize(fit["idw_psnr"])},
        "reference": PAPER_REFERENCE,
        "config": OmegaConf.to_container(cfg, resolve=True),
    }
    out = output_dir(cfg)
    results["figure"] = plot_oracle(results, out / "oracle_psnr.png").name
    results["seconds"] = round(time.perf_counter() - started, 3)
    atomic_write_json(out / "results.json", results)
    print(format_table(results))
    return results
