"""Fine-tuning fractions: the measured part of a scene's training split (seeded, disjoint from the test split,
nested, limiting the test neighbor pool when asked), fine-tuning and zero-shot runs from a checkpoint, and
the errors of a checkpoint that does not fit the run (band, scene-index setting)."""

from __future__ import annotations

import json

import pytest
import torch

from graf.data.spectrum_set import DataFormatError
from graf.errors import ConfigError
from graf.models.base import CheckpointError
from graf.run.build import build_datamodule
from graf.run.train import train

QUIET = ["plot_count=0", "trainer.enable_progress_bar=false", "baselines={}"]


def _dm(compose_cfg, *overrides):
    cfg = compose_cfg("train", ("model=knn", *overrides))
    _, _, _, dm = build_datamodule(cfg)
    dm.setup("fit")
    return dm


def _ids(dm, rows) -> set[int]:
    return {int(i) for i in dm.ids[rows]}


def test_measured_fraction_is_seeded_nested_disjoint_from_test_and_limits_the_test_pool(compose_cfg):
    whole = _dm(compose_cfg)
    f20 = _dm(compose_cfg, "finetune=f20", "finetune.init_from=null")
    again = _dm(compose_cfg, "finetune=f20", "finetune.init_from=null")
    f10 = _dm(compose_cfg, "finetune=f10", "finetune.init_from=null")
    other_seed = _dm(compose_cfg, "finetune=f20", "finetune.init_from=null", "finetune.seed=7")
    n_train = len(whole.train_rows)
    assert len(f20.measured_rows) == round(0.2 * n_train) and len(f10.measured_rows) == round(0.1 * n_train)
    assert torch.equal(f20.measured_rows, again.measured_rows)  # reproducible
    assert _ids(f20, f20.measured_rows) != _ids(other_seed, other_seed.measured_rows)  # drawn with the seed
    assert _ids(f10, f10.measured_rows) < _ids(f20, f20.measured_rows)  # nested fractions
    assert _ids(f20, f20.measured_rows) <= _ids(whole, whole.train_rows)
    assert not _ids(f20, f20.measured_rows) & _ids(f20, f20.test_rows)  # the test split is never touched
    assert _ids(f20, f20.fit_rows) | _ids(f20, f20.val_rows) == _ids(f20, f20.measured_rows)
    assert torch.equal(f20.test_rows, whole.test_rows)

    rows, src, mask = f20.split_neighbors("test")  # test neighbors from the measured part only ...
    assert set(src[mask].tolist()) <= set(f20.measured_rows.tolist())
    full = _dm(compose_cfg, "finetune=f20", "finetune.init_from=null", "finetune.test_pool=train_split")
    rows, src, mask = full.split_neighbors("test")  # ... or, as named, from the whole training split
    assert not set(src[mask].tolist()) <= set(full.measured_rows.tolist())
    assert set(src[mask].tolist()) <= set(full.train_rows.tolist())
    for k in range(20):  # training draws stay inside the measured fit part
        b = f20.train_batch(k)
        assert set(b["tgt_index"].tolist()) <= set(f20.fit_rows.tolist())
        assert set(b["src_index"][b["src_mask"]].tolist()) <= set(f20.fit_rows.tolist())
    s = f20.split_summary()
    assert s["n_measured"] == len(f20.measured_rows) and len(s["measured_ids"]) == s["n_measured"]


def test_a_fraction_that_leaves_too_few_spectra_is_refused_naming_the_scene(compose_cfg):
    with pytest.raises(DataFormatError, match=r"rfid_s23_200.*measured fraction of 0.005 .* leaves 1"):
        _dm(compose_cfg, "finetune=f05", "finetune.init_from=null", "finetune.fraction=0.005")


@pytest.mark.slow  # moved from the default run to keep it under 5 min on the 2-core machine (issue 68)
def test_finetune_and_zero_shot_from_a_checkpoint_record_what_they_did(compose_cfg, tmp_path):
    base = compose_cfg("train", ("model=knn_dl", "trainer.max_steps=3", *QUIET, f"paths.output_dir={tmp_path / 'b'}"))
    train(base)
    ckpt = tmp_path / "b" / "checkpoints" / "last.ckpt"
    saved = torch.load(ckpt, map_location="cpu", weights_only=False)
    scenes = saved["graf"]["scenes"]
    assert list(scenes) == ["rfid_s23"] and (scenes["rfid_s23"]["index"], scenes["rfid_s23"]["band_hz"]) == (0, 915e6)
    assert scenes["rfid_s23"]["fingerprint"]["n"] == 200  # the scene's content (graf.data.fingerprint)

    ft = compose_cfg(
        "train",
        (
            "model=knn_dl",
            "finetune=f20",
            f"finetune.init_from={ckpt}",
            "finetune.max_steps=2",
            "finetune.lr=1e-4",
            *QUIET,
            f"paths.output_dir={tmp_path / 'f'}",
        ),
    )
    train(ft)
    r = json.loads((tmp_path / "f" / "results.json").read_text())
    assert r["global_step"] == 2 and r["config"]["model"]["lr"] == 1e-4
    f = r["finetune"]
    assert (f["mode"], f["fraction"], f["steps"], f["n_measured"]) == ("fine-tune", 0.2, 2, 32)
    assert f["test_pool"] == "measured"
    assert f["base_steps"] == 3 and f["base_scenes"] == saved["graf"]["scenes"]
    assert r["splits"]["n_fit"] + r["splits"]["n_val"] == 32

    zs = compose_cfg(
        "train", ("model=knn_dl", f"finetune.init_from={ckpt}", *QUIET, f"paths.output_dir={tmp_path / 'z'}")
    )
    train(zs)
    z = json.loads((tmp_path / "z" / "results.json").read_text())
    assert z["finetune"]["mode"] == "zero-shot" and z["finetune"]["steps"] == 0 and z["global_step"] == 0
    assert z["finetune"]["test_pool"] == "train_split" and z["finetune"]["n_measured"] == 160
    # zero-shot weights are the checkpoint's: the same test figures as the base run's own test
    b = json.loads((tmp_path / "b" / "results.json").read_text())
    assert z["metrics"]["test/psnr"] == pytest.approx(b["metrics"]["test/psnr"], abs=1e-4)


GRAF_TINY = [
    "model=graf_cpu",
    "model.rays_per_step=64",
    "model.max_samples=8",
    "data.batch_size=2",
    "model.encoder_widths=[4,8,8,8]",
    "data.test_subset=2",
    "callbacks.model_checkpoint.every_n_train_steps=1",
]


@pytest.mark.slow  # 15-25 s: fine-tuning end to end stays in the default set (test_finetune_and_zero_shot_...)
def test_a_checkpoint_of_another_band_or_scene_index_setting_is_refused(compose_cfg, small_room_root, tmp_path):
    tiny = [*GRAF_TINY, *QUIET, f"data_root={small_room_root}", "sim_num_tx=24"]
    base = compose_cfg(
        "train", (*tiny, "model.use_scene_index=true", "trainer.max_steps=1", f"paths.output_dir={tmp_path / 'g'}")
    )
    train(base)
    ckpt = tmp_path / "g" / "checkpoints" / "last.ckpt"
    wrong = compose_cfg(
        "train",
        (
            *tiny,
            "model.use_scene_index=false",
            "finetune=f50",
            f"finetune.init_from={ckpt}",
            "finetune.max_steps=1",
            f"paths.output_dir={tmp_path / 'w'}",
        ),
    )
    with pytest.raises(CheckpointError, match="use_scene_index=True .*set model.use_scene_index=True"):
        train(wrong)

    # a 915 MHz model tested on a 2.4 GHz scene: a transfer only when asked for
    ev = compose_cfg(
        "train",
        (
            *tiny,
            "model.use_scene_index=true",
            f"finetune.init_from={ckpt}",
            "eval_band=2.4ghz",
            "eval_scene=[small_room]",
            f"paths.output_dir={tmp_path / 'x'}",
        ),
    )
    with pytest.raises(ConfigError, match=r"trained at 915 MHz .*small_room is at 2.41 GHz.*cross_band=true"):
        train(ev)
    ok = compose_cfg(
        "train",
        (
            *tiny,
            "model.use_scene_index=true",
            f"finetune.init_from={ckpt}",
            "cross_band=true",
            "eval_scene=[small_room]",
            f"paths.output_dir={tmp_path / 'y'}",
        ),
    )
    train(ok)
    r = json.loads((tmp_path / "y" / "results.json").read_text())
    ev = r["evaluations"][0]
    assert (ev["eval_scene"], ev["within_scene"], ev["scene_index"], ev["band_hz"]) == ("small_room", False, 1, 2.412e9)


def test_a_zero_shot_test_records_the_scenes_its_model_was_trained_on():
    """A zero-shot job tested on rfid_s23 with a model trained on two conference layouts records those layouts as
    its train_scenes (in scene-index order), not rfid_s23; a fine-tuning run records the scene it trained on."""
    from types import SimpleNamespace

    from graf.run.record import Finetune
    from graf.run.writer import trained_scenes

    dm = SimpleNamespace(sets=[SimpleNamespace(name="rfid_s23")])
    base = {"conference_v2": {"index": 1}, "conference_v1": {"index": 0}}
    zs = Finetune("ck", "zero-shot", None, 0, "train_split", 160, 160, 0, None, 300, base)
    assert trained_scenes(dm, zs) == ["conference_v1", "conference_v2"]
    ft = Finetune("ck", "fine-tune", 0.2, 0, "measured", 32, 160, 50, None, 300, base)
    assert trained_scenes(dm, ft) == ["rfid_s23"] and trained_scenes(dm, None) == ["rfid_s23"]
