"""Profile GRaF inference (predict_spectra) and one training step on a scene: top operators by self CPU time.

python scripts/profile_graf.py [scene] [model] [extra overrides...]
"""

import sys
import time

import hydra
import torch
from hydra import compose, initialize_config_dir

from graf.app.config import CONF_DIR
from graf.run.build import build_datamodule

torch.set_num_threads(2)
scene = sys.argv[1] if len(sys.argv) > 1 else "rfid_s23"
model_name = sys.argv[2] if len(sys.argv) > 2 else "graf"
extra = sys.argv[3:]
with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
    cfg = compose(
        "eval", overrides=[f"scene={scene}", "data_root=data"] + [e for e in extra if not e.startswith("model.")]
    )
mcfg = compose  # noqa
with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
    m = compose(
        "train", overrides=[f"model={model_name}", f"scene={scene}"] + [e for e in extra if e.startswith("model.")]
    ).model
band, sc, nb, dm = build_datamodule(cfg)
dm.setup("test")
idx, mask = dm.eval_neighbors()
rows = dm.eval_rows[:3]
batches = [dm.make_batch(rows[i : i + 1], idx[i : i + 1], mask[i : i + 1]) for i in range(3)]
model = hydra.utils.instantiate(m).eval()
print("S =", model.samples_per_ray(batches[0]))
with torch.no_grad():
    model.predict_spectra(batches[0])
    t = time.perf_counter()
    model.predict_spectra(batches[1])
    print(f"infer {time.perf_counter() - t:.2f} s/spectrum")
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        model.predict_spectra(batches[2])
print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=18))
