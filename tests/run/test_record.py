"""The run record: results.json keeps the key tree the code wrote before graf.run.record
(tests/fixtures/results_keys.json, written by the earlier code for six kinds of run), and a record read back from
results.json equals the one written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from graf.data.nerf2_format import write_nerf2_folder
from graf.run.evaluate import evaluate
from graf.run.record import RunRecord, Timing, Training
from graf.run.train import train
from tests.conftest import smooth_spectra

KEYS = Path(__file__).resolve().parents[1] / "fixtures" / "results_keys.json"
# payloads whose keys are the config's, the data's or a checkpoint's, not the record's
OPAQUE = {
    "config",
    "splits",
    "ray_sampling",
    "scene_table",
    "hyper_parameters",
    "checkpoint_settings",
    "changed",
    "base_scenes",
    "applied_overrides",
    "prediction_sha256",
    "scene_indices",
}
FAST = ("data.test_subset=2",)


def key_tree(v):
    """The keys of a results.json, nested, in order (a list by its first item; payloads as None)."""
    if isinstance(v, dict):
        return {k: (None if k in OPAQUE else key_tree(x)) for k, x in v.items()}
    if isinstance(v, list) and v and isinstance(v[0], dict):
        return [key_tree(v[0])]
    return None


def tiny_scene(folder: Path) -> Path:
    rng = np.random.default_rng(0)
    pos = rng.uniform([-1.0, 0.5, 0.0], [1.0, 1.5, 1.0], size=(16, 3))
    ids = np.arange(1, 17)
    gw_pos, gw_rot = np.array([0.0, 0.0, 0.5]), np.array([0.0, 0.0, 0.0, 1.0])
    return write_nerf2_folder(
        folder, smooth_spectra(pos), pos, ids, gw_pos, gw_rot, train_ids=ids[:12], test_ids=ids[12:]
    )


@pytest.mark.slow  # moved from the default run to keep it under 5 min on the 2-core machine (issue 68)
def test_results_json_keeps_its_keys_and_reads_back_as_the_record_written(compose_cfg, tmp_path):
    want = json.loads(KEYS.read_text())
    ck = tmp_path / "b" / "checkpoints" / "last.ckpt"
    knn_dl = ("model=knn_dl", "data.batch_size=2")
    cases = {
        "eval_knn": (evaluate, "eval", ("model=knn", "save_predictions=true", "save_samples=1", "plot_count=1")),
        "train_knn_dl": (train, "train", (*knn_dl, "trainer.max_steps=2", "plot_count=1")),
        "eval_checkpoint": (evaluate, "eval", ("model=knn_dl", f"ckpt_path={ck}", "plot_count=0")),
        "finetune": (
            train,
            "train",
            (
                *knn_dl,
                "finetune=f100",
                "finetune.max_steps=1",
                f"finetune.init_from={ck}",
                "baselines=null",
                "plot_count=0",
            ),
        ),
        "resume": (
            train,
            "train",
            (*knn_dl, "trainer.max_steps=3", f"ckpt_path={ck}", "baselines=null", "plot_count=0"),
        ),
        "eval_other_scene": (
            evaluate,
            "eval",
            (
                "model=knn",
                "eval_scene=nerf2",
                f"eval_scene.nerf2.path={tiny_scene(tmp_path / 'tiny')}",
                "band=2.4ghz",
                "neighbors=fixed",
                "neighbors.L=2",
                "cross_band=true",
                "plot_count=0",
            ),
        ),
    }
    for (case, (task, config, overrides)), folder in zip(cases.items(), "abcdef"):
        # threads held: training.batches_on_fewer_threads appears only beside busy processes (a busy test worker)
        held = ("callbacks.threads_beside_load=null",) if config == "train" else ()
        cfg = compose_cfg(config, (f"paths.output_dir={tmp_path / folder}", *FAST, *held, *overrides))
        _, run = task(cfg, overrides=[]) if task is evaluate else task(cfg)
        written = json.loads((tmp_path / folder / "results.json").read_text())
        assert key_tree(written) == want[case], case
        assert list(key_tree(written)) == list(want[case]), case  # in the same order
        assert RunRecord.read(tmp_path / folder / "results.json") == run.record, case
        assert run.record.to_json() == written, case


def test_optional_parts_are_left_out_and_read_back_as_none():
    t = Timing(val_s=1.0, test_s=2.0, reliance_s=0.5)
    assert t.to_json() == {"val_s": 1.0, "test_s": 2.0, "reliance_s": 0.5}  # no fit, no per-spectrum figure
    fit = Timing(fit_s=3.0, fit_steps=0, fit_s_per_step=None)
    assert fit.to_json()["fit_s_per_step"] is None  # a fit of no step keeps the key
    assert Timing.from_json(fit.to_json()) == fit
    tr = Training(10, -1, 0, 10, 10, 0, False, 1)
    assert "stop_reason" not in tr.to_json() and Training.from_json(tr.to_json()) == tr


@pytest.mark.parametrize("case", ["eval_knn", "train_knn_dl"])
def test_the_key_fixture_names_the_record_fields(case):
    """Every key of the fixture is a field of RunRecord (by its JSON name): nothing results.json held is lost."""
    fields = {f.metadata.get("key", f.name) for f in RunRecord.__dataclass_fields__.values()}
    assert set(json.loads(KEYS.read_text())[case]) <= fields
