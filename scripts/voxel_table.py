"""Samples per ray and effective voxel size of the GRaF presets on every scene and band (README table).

    .venv/bin/python scripts/voxel_table.py

S = min(max_samples, ceil(ray_length / wavelength)); ray_length is the farthest corner of the scene's box
from its gateway (what the datamodule computes).  A run records the same figures in results.json
("ray_sampling") and logs a warning when max_samples caps S.
"""

from __future__ import annotations

import math

import numpy as np
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from graf.cli.common import CONF_DIR

SCENES = ["rfid_s23", "small_room", "bedroom", "conference_v1", "office_v1", "outdoor"]
PRESETS = {"graf": 128, "graf_cpu": 32}


def main() -> None:
    print("| band | scene | ray length (m) | S needed | " + " | ".join(f"`{p}` S, voxel" for p in PRESETS) + " |")
    print("|---|---|---|---|" + "---|" * len(PRESETS))
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        for band_name in ("915mhz", "2.4ghz", "3ghz"):
            for name in SCENES:
                cfg = compose(config_name="train", overrides=[f"scene={name}", f"band={band_name}"])
                scene, band = instantiate(cfg.scene), instantiate(cfg.band)
                caps = {p: compose(config_name="train", overrides=[f"model={p}"]).model.max_samples for p in PRESETS}
                if hasattr(scene, "geometry"):
                    bounds, gw = np.asarray(scene.geometry.bounds), np.asarray(scene.gateway["position"], float)
                else:
                    d = scene.load(None, band)
                    bounds, gw = d.bounds(), d.gateway_position
                corners = np.array([[bounds[i, 0], bounds[j, 1], bounds[k, 2]] for i in (0, 1) for j in (0, 1)
                                    for k in (0, 1)])
                length, lam = float(np.linalg.norm(corners - gw, axis=1).max()), band.wavelength
                need = math.ceil(length / lam - 1e-6)
                cells = []
                for p, cap in caps.items():
                    S = min(need, cap)
                    cells.append(f"{S}, {length / S / lam:.2f} λ" + (" (capped)" if need > cap else ""))
                print(f"| {band_name} | {name} | {length:.2f} | {need} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
