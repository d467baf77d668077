"""Profile one GRaF training step (forward + backward + Adam) on a scene: top operators by self CPU time.

python scripts/profile_graf_train.py [scene] [model] [extra overrides...]
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
        "train",
        overrides=[
            f"scene={scene}",
            f"model={model_name}",
            "data_root=data",
            "data.batch_size=4",
            "model.rays_per_step=5120",
        ]
        + extra,
    )
band, sc, nb, dm = build_datamodule(cfg)
dm.setup("fit")
model = hydra.utils.instantiate(cfg.model).train()
model.log = lambda *a, **k: None
opt = torch.optim.Adam(model.parameters(), lr=1e-4)
batches = [dm.train_batch(k) for k in range(3)]


def step(b):
    loss = model.training_step(b, 0)
    loss.backward()
    opt.step()
    opt.zero_grad()


step(batches[0])
t = time.perf_counter()
step(batches[1])
print(f"train step {time.perf_counter() - t:.2f} s")
with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
    step(batches[2])
print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=22))
