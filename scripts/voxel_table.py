"""Voxels per ray of the GRaF presets on every scene and band (README table).

    .venv/bin/python scripts/voxel_table.py

Each ray of the 90 x 360 grid is cut into voxels of ``voxel_wavelengths`` (1) wavelengths from its entry to
its exit of the scene's box (``GRaFModule.ray_table``, ray-box intersection), at most ``max_samples`` per
ray.  Printed per preset: the most and the mean voxels per ray, the voxels of a whole spectrum (what its cost
is proportional to), and how many rays ``max_samples`` caps (their voxels are then longer than a wavelength).
A run records the same figures in results.json ("ray_sampling").
"""

from __future__ import annotations

import numpy as np
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from graf.app.config import CONF_DIR, scene_band_config
from graf.app.spec import RunSpec
from graf.sim.array import rotation_from_axes

SCENES = ["rfid_s23", "small_room", "bedroom", "conference_v1", "office_v1", "outdoor"]
PRESETS = ("graf", "graf_cpu")


def main() -> None:
    print(
        "| band | scene | box (m) | " + " | ".join(f"`{p}` max / mean S, voxels, capped rays" for p in PRESETS) + " |"
    )
    print("|---|---|---|" + "---|" * len(PRESETS))
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        models = {p: instantiate(compose(config_name="train", overrides=[f"model={p}"]).model) for p in PRESETS}
        for band_name in ("915mhz", "2.4ghz", "3ghz"):
            for name in SCENES:
                cfg = compose(config_name="train", overrides=[f"scene={name}", f"band={band_name}"])
                scene_cfg = RunSpec.of(cfg).one_scene("voxel_table")
                scene, band = instantiate(scene_cfg), instantiate(scene_band_config(scene_cfg, cfg.get("band")))
                if hasattr(scene, "geometry"):
                    bounds, gw = np.asarray(scene.geometry.bounds), np.asarray(scene.gateway["position"], float)
                    rot = rotation_from_axes(scene.gateway["normal"], scene.gateway["x_axis"]).as_matrix()
                else:
                    from scipy.spatial.transform import Rotation

                    d = scene.load(None, band)
                    bounds, gw = d.bounds(), d.gateway_position
                    rot = Rotation.from_quat(d.gateway_orientation).as_matrix()
                geo = {
                    "gw_pos": torch.tensor(gw, dtype=torch.float32)[None],
                    "gw_rot": torch.tensor(rot, dtype=torch.float32)[None],
                    "bounds": torch.tensor(bounds, dtype=torch.float32)[None],
                    "wavelength": torch.tensor([band.wavelength]),
                    "ray_length": torch.tensor([0.0]),
                    "scene_index": torch.tensor([0]),
                }
                cells = []
                for _p, model in models.items():
                    r = model.ray_sampling(geo)
                    cells.append(
                        f"{r['samples_per_ray']} / {r['mean_samples_per_ray']:.1f}, "
                        f"{r['voxels_per_spectrum']:,}, {r['capped_rays']:,}"
                    )
                size = " x ".join(f"{x:.1f}" for x in (bounds[1] - bounds[0]))
                print(f"| {band_name} | {name} | {size} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
