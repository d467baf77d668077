"""GRaF's fast CPU inference (graf.models.graf.inference, graf.models.graf.kernels) gives the plain path's output
within float rounding: the compiled attention kernel and its torch stand-in against the blocks' own forward, and
whole spectra for every neighbor-feature mode, attention kernel and ray window, trained-looking weights (every
parameter perturbed, so no zero-initialised head hides the blocks), batches of one and of two targets."""

from __future__ import annotations

import time

import pytest
import torch

from graf.models.graf import inference
from graf.models.graf.attention import CrossAttentionBlock, SelfAttentionBlock
from graf.models.graf.inference import map_chunks, ray_transformer
from graf.models.graf.kernels import blocks as fast_blocks
from graf.models.graf.kernels import native
from tests.models.test_graf_model import _datamodule, _eval_batch, _small

ATOL = 2e-5


@pytest.fixture
def tiny(make_scene):
    return _datamodule(make_scene(n=16))


def _perturbed(model, seed=0):
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.2 * torch.randn(p.shape, generator=g))
    return model.eval()


@pytest.fixture(params=["native", "torch"])
def kernel(request, monkeypatch):
    """Both implementations of the fused attention: the compiled kernel (where this machine builds it) and torch."""
    if request.param == "native":
        if not native.available():
            pytest.skip("no C++ compiler here: the kernel cannot be built (the torch stand-in is tested)")
    else:
        monkeypatch.setattr(native, "supports", lambda *a: False)
        monkeypatch.setattr(native, "block_supported", lambda *a: False)
        monkeypatch.setattr(native, "mlp_supported", lambda *a: False)
    return request.param


SHAPES = [(7, 8, 8, 25, 25), (3, 16, 16, 1, 1), (2, 16, 16, 40, 3), (5, 8, 9, 17, 130)]


@pytest.mark.parametrize("B,Dk,Dv,Sq,Sk", SHAPES)
def test_fused_attention_equals_softmax_attention(kernel, B, Dk, Dv, Sq, Sk):
    g = torch.Generator().manual_seed(B * Sq + Sk)
    q, k = torch.randn(B, Dk, Sq, generator=g), torch.randn(B, Dk, Sk, generator=g)
    v = torch.randn(B, Dv, Sk, generator=g)
    mask = torch.rand(B, Sk, generator=g) > 0.5
    mask[:, -1] = True  # every entry attends to at least one key
    for m in (None, mask):
        a = q.transpose(1, 2) @ k
        if m is not None:
            a = a.masked_fill(~m[:, None, :], float("-inf"))
        expect = v @ a.softmax(-1).transpose(1, 2)
        assert torch.allclose(fast_blocks.attention_fm(q, k, v, m), expect, atol=1e-5, rtol=1e-5)


def test_fused_attention_at_the_extremes(kernel):
    """Huge scores (the row maximum is subtracted: no overflow), one key, a single unmasked key, equal keys."""
    q = torch.full((2, 8, 20), 40.0)
    k = torch.linspace(-3, 3, 2 * 8 * 5).view(2, 8, 5)
    v = torch.randn(2, 8, 5)
    out = fast_blocks.attention_fm(q, k, v, None)
    expect = v @ (q.transpose(1, 2) @ k).softmax(-1).transpose(1, 2)
    assert torch.isfinite(out).all() and torch.allclose(out, expect, atol=1e-5)
    only = torch.zeros(2, 5, dtype=torch.bool)
    only[:, 2] = True
    out = fast_blocks.attention_fm(q, k, v, only)
    assert torch.allclose(out, v[:, :, 2:3].expand(-1, -1, 20), atol=1e-6)
    same = fast_blocks.attention_fm(torch.randn(1, 8, 3), torch.ones(1, 8, 4), v[:1, :, :4], None)
    assert torch.allclose(same, v[:1, :, :4].mean(-1, keepdim=True).expand(-1, -1, 3), atol=1e-6)


def test_fast_blocks_equal_the_blocks_forward(kernel):
    torch.manual_seed(0)
    self_blk = _perturbed(SelfAttentionBlock(16, 10, 8, 64))
    cross_blk = _perturbed(CrossAttentionBlock(16, 1, 16, 64))
    x, ctx = torch.randn(6, 23, 16), torch.randn(6, 5, 16)
    mask = torch.rand(6, 5) > 0.4
    mask[:, 0] = True
    with torch.no_grad():
        assert torch.allclose(fast_blocks.block_forward(self_blk, x), self_blk(x), atol=ATOL)
        for m in (None, mask):
            assert torch.allclose(fast_blocks.block_forward(cross_blk, x, ctx, m), cross_blk(x, ctx, m), atol=ATOL)
        one = ctx[:1]  # one context for every query row (the pooled mode's one-item batches)
        assert torch.allclose(
            fast_blocks.block_forward(cross_blk, x.reshape(1, -1, 16), one, None),
            cross_blk(x.reshape(1, -1, 16), one, None),
            atol=ATOL,
        )


def test_whole_blocks_equal_the_blocks_forward(kernel):
    """run_blocks (each block one fused kernel call where the library is there): self-attention over rays of
    several lengths (vector tails), cross-attention with per-entry and shared contexts and key masks."""
    torch.manual_seed(1)
    selfs = torch.nn.ModuleList(_perturbed(SelfAttentionBlock(16, 10, 8, 64)) for _ in range(2))
    crosses = torch.nn.ModuleList(_perturbed(CrossAttentionBlock(16, 1, 16, 64)) for _ in range(2))
    odd = torch.nn.ModuleList([_perturbed(SelfAttentionBlock(12, 3, 4, 24))])  # sizes not specialised
    with torch.no_grad():
        for S in (1, 16, 17, 40):
            x = torch.randn(5, S, 16)
            expect = x
            for blk in selfs:
                expect = blk(expect)
            assert torch.allclose(fast_blocks.run_blocks(selfs, x), expect, atol=ATOL)
        x, ctx = torch.randn(4, 23, 16), torch.randn(4, 10, 16)
        mask = torch.rand(4, 10) > 0.5
        mask[:, 3] = True
        for c, m in ((ctx, mask), (ctx, None), (ctx[:1], mask[:1])):
            expect = x
            for blk in crosses:
                expect = blk(expect, c.expand(4, -1, -1), None if m is None else m.expand(4, -1))
            assert torch.allclose(fast_blocks.run_blocks(crosses, x, c, m), expect, atol=ATOL)
        y = torch.randn(3, 9, 12)
        assert torch.allclose(fast_blocks.run_blocks(odd, y), odd[0](y), atol=ATOL)


def test_fused_mlp_equals_the_mlp():
    """MLP2 fused with the distance code (native.mlp, feature-major) against ``mlp2(x) + code``, vector tails
    (no torch stand-in: without the library the plain MLP runs)."""
    if not native.available():
        pytest.skip("no C++ compiler here: the kernel cannot be built")
    torch.manual_seed(2)
    for d, m in ((16, 64), (12, 24)):  # GRaF's (specialised) and sizes read at run time
        seq = _perturbed(torch.nn.Sequential(torch.nn.Linear(d, m), torch.nn.ReLU(), torch.nn.Linear(m, d)))
        assert fast_blocks.mlp_fusable(seq)
        for S in (1, 16, 17, 40):
            x, code = torch.randn(3, S, d), torch.randn(3, S, d)
            with torch.no_grad():
                fused = native.mlp(fast_blocks.mlp_weights(seq), x.transpose(1, 2).contiguous(), code)
                assert torch.allclose(fused.transpose(1, 2), seq(x) + code, atol=ATOL)


@pytest.mark.parametrize("d_model", [16, 12])
def test_ray_pass_fast_equals_plain(kernel, d_model):
    """inference.ray_pass (scene blocks, MLP2 + code, ray blocks, mean): on the fast path one compiled call per
    group of rays (every stage per ray while it is in cache), against the plain path; rays of several lengths,
    per-ray and shared tokens, with and without a key mask, GRaF's sizes and sizes not specialised."""
    model = _perturbed(_small(max_samples=64, d_model=d_model, mlp_dim=2 * d_model), seed=3)
    n, L, d = 6, 7, d_model
    g = torch.Generator().manual_seed(4)
    for S in (1, 16, 17, 40):
        x, code = torch.randn(n, S, d, generator=g), torch.randn(n, S, d, generator=g)
        tokens = torch.randn(n, L, d, generator=g)
        mask = torch.rand(n, L, generator=g) > 0.5
        mask[:, 0] = True
        for t, m in ((tokens, None), (tokens, mask), (tokens[:1], mask[:1])):
            assert inference._fused_ok(model, x, t, n, S) == (kernel == "native")
            with torch.no_grad():
                fast = inference.ray_pass(model, x, t, m, code, fast=True)
                plain = inference.ray_pass(
                    model, x, t.expand(n, -1, -1), None if m is None else m.expand(n, -1), code, fast=False
                )
            assert fast.shape == (n, d)
            assert torch.allclose(fast, plain, atol=ATOL), (fast - plain).abs().max()


@pytest.mark.parametrize("d_model", [16, 12])
def test_ray_pass_layouts_give_the_same_bits(d_model):
    """The fused ray pass with 16 positions of a ray per vector and with 16 rays per vector: the same arithmetic
    in the same order, so the same bits, for short and long rays, group sizes off the vector width, per-ray and
    shared tokens, with and without a key mask; auto picks rays for short rays in groups of many."""
    if not native.available():
        pytest.skip("no C++ compiler here: the kernel cannot be built")
    model = _perturbed(_small(max_samples=64, d_model=d_model, mlp_dim=2 * d_model), seed=5)
    weights = fast_blocks.ray_pass_weights(model)
    g = torch.Generator().manual_seed(6)
    for n, S in ((37, 3), (16, 1), (5, 40), (33, 17)):
        x, code = torch.randn(n, S, d_model, generator=g), torch.randn(n, S, d_model, generator=g)
        tokens = torch.randn(n, 7, d_model, generator=g)
        mask = torch.rand(n, 7, generator=g) > 0.5
        mask[:, 0] = True
        for t, m in ((tokens, None), (tokens, mask), (tokens[:1], mask[:1])):
            by_positions = native.ray_pass(weights, x, t, m, code, layout="positions")
            assert torch.equal(native.ray_pass(weights, x, t, m, code, layout="rays"), by_positions)
    assert native.choose_layout(1000, 3) == "rays" and native.choose_layout(2, 3) == "positions"
    assert native.choose_layout(1000, 32) == "positions" and native.choose_layout(1000, 17) == "rays"


@pytest.mark.parametrize("window", [0, 3])
def test_ray_transformer_fast_equals_plain(kernel, window):
    model = _perturbed(_small(max_samples=8, ray_window=window))
    v = torch.randn(9, 8, model.d_model)
    with torch.no_grad():
        fast = ray_transformer(model.ray_blocks, v, window, fast=True)
        plain = ray_transformer(model.ray_blocks, v, window, fast=False)
    assert torch.allclose(fast, plain, atol=ATOL)


CASES = [(f, "auto", 0) for f in ("pooled", "ray", "ray_knn", "ray_weights")] + [
    (f, a, w) for f in ("pooled", "ray_weights") for a, w in (("sdpa", 0), ("math", 0), ("auto", 3))
]


@pytest.mark.parametrize("features,attention,window", CASES)
@pytest.mark.slow  # moved from the default run to keep it under 5 min on the 2-core machine (issue 68)
def test_whole_spectra_fast_equal_plain(tiny, features, attention, window):
    """predict_spectra with fast_inference (the kernel, chunks on two threads) equals it without, every mode,
    attention kernel and ray window, for a batch of two targets and of one."""
    model = _perturbed(
        _small(max_samples=8, chunk_rays=5000, attention=attention, ray_window=window, features=features), seed=1
    )
    batch = _eval_batch(tiny)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        for b in (batch, {k: v[:1] if torch.is_tensor(v) else v for k, v in batch.items()}):
            with torch.no_grad():
                fast = model.predict_spectra(b)
                model.fast_inference = False
                plain = model.predict_spectra(b)
                model.fast_inference = True
            assert torch.allclose(fast, plain, atol=ATOL), (fast - plain).abs().max()
            assert plain.std() > 1e-3  # the blocks' output reaches the prediction
    finally:
        torch.set_num_threads(threads)
    assert torch.get_num_threads() == 2 or threads != 2


def test_map_chunks_keeps_order_and_threads():
    threads = torch.get_num_threads()
    with torch.no_grad():
        out = map_chunks(lambda i: torch.full((3,), float(i)) * 2, range(7), torch.device("cpu"), workers=2)
    assert [float(o[0]) for o in out] == [2.0 * i for i in range(7)]
    assert torch.get_num_threads() == threads
    with torch.enable_grad():  # autograd mode is thread-local: chunks stay in this thread
        out = map_chunks(lambda i: torch.is_grad_enabled(), range(4), torch.device("cpu"), workers=2)
    assert out == [True] * 4


def test_serial_phases_take_the_cores_other_processes_leave(monkeypatch):
    """The encoder and the first ray run on torch's intra-op threads: as many as the cores other processes leave
    free (their load read live from /proc), at least one, never more than set."""
    import graf.models.graf.inference as inference
    from graf.machine import monitor
    from graf.studies.bench_load import Competitor

    live = monitor()
    with Competitor():
        time.sleep(1.2)  # three of the monitor's readings with the competitor running
        assert live.other() is not None and live.other() > 0.5

    class Load:
        def __init__(self, cores):
            self.cores = cores

        def other(self):
            return self.cores

        def window_s(self):
            return 1.0

    import graf.machine as machine

    monkeypatch.setattr(machine, "available_cores", lambda: 2)
    for other, threads, expect in ((None, 2, 2), (0.4, 2, 2), (1.0, 2, 1), (1.9, 2, 1), (0.0, 1, 1), (3.5, 2, 1)):
        monkeypatch.setattr(machine, "monitor", lambda o=other: Load(o))
        assert inference.serial_threads(threads) == expect


def test_a_run_goes_on_the_cores_busy_processes_leave_and_back_on_all_once_they_stop(monkeypatch):
    """graf.callbacks.ThreadsBesideLoad: every batch of a CPU run on the threads the measured load leaves (a quiet
    machine: the threads set, untouched), all of them again once the load ends and after the loop."""
    import graf.machine as machine
    from graf.callbacks import ThreadsBesideLoad

    load = {"cores": 0.1}

    class Load:
        def other(self):
            return load["cores"]

    class Module:
        device = torch.device("cpu")

    monkeypatch.setattr(machine, "monitor", lambda: Load())
    monkeypatch.setattr(machine, "available_cores", lambda: 2)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        cb, seen = ThreadsBesideLoad(hold_s=0.0), []
        for cores in (0.1, 1.0, 1.0, 0.2):
            load["cores"] = cores
            cb.on_train_batch_start(None, Module(), None, 0)
            seen.append(torch.get_num_threads())
        assert seen == [2, 1, 1, 2] and cb.fewer_batches == 2
        load["cores"] = 1.2
        cb.on_test_batch_start(None, Module(), None, 0)
        assert torch.get_num_threads() == 1
        cb.on_test_end(None, Module())
        assert torch.get_num_threads() == 2  # the threads set, after the loop
        held, seen = ThreadsBesideLoad(hold_s=3600.0), []
        for cores in (1.0, 0.1, 0.1):  # a load that just ended: the change made a moment ago holds
            load["cores"] = cores
            held.on_train_batch_start(None, Module(), None, 0)
            seen.append(torch.get_num_threads())
        assert seen == [1, 1, 1] and held.fewer_batches == 3
    finally:
        torch.set_num_threads(before)


def test_load_is_measured_from_cpu_time_and_a_burst_that_ended_reads_as_quiet():
    """Other processes' load (issue 68): CPU time over two half-second windows, the quieter one counting, so a
    burst of CPU work that has just ended (an install's compile) lowers nothing; a load lasting both does."""
    from graf.machine import LoadMonitor

    m = LoadMonitor.__new__(LoadMonitor)  # no thread: readings set by hand, (wall s, (machine busy s, own busy s))
    burst_then_quiet = [(0.0, (0.0, 0.0)), (0.25, (0.5, 0.0)), (0.5, (1.0, 0.0)), (0.75, (1.0, 0.0)), (1.0, (1.0, 0))]
    m.readings = burst_then_quiet  # 2 cores busy in the first window, none in the last
    assert m.other() == 0.0 and m.window_s() == 1.0
    m.readings = [(0.25 * i, (0.5 * i, 0.0)) for i in range(5)]  # 2 cores busy all along: a real load
    assert m.other() == 2.0
    m.readings = [(0.25 * i, (0.5 * i, 0.5 * i)) for i in range(5)]  # all of it this process's own work
    assert m.other() == 0.0
    m.readings = m.readings[:2]
    assert m.other() is None  # no window read yet: the threads set stay


def test_a_processs_children_count_as_its_own_work_not_as_other_load():
    """A compile GRaF runs at first use, or a data-loading worker, is this process's work: its CPU time is counted
    as its own (graf.machine.own_ticks), whether the child still runs or has been waited for."""
    import os
    import subprocess
    import sys

    from graf.machine import own_ticks

    burn = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.6: pass\n"
    before = own_ticks(os.getpid())
    subprocess.run([sys.executable, "-c", burn], check=True)  # waited for: its time is in cutime
    waited = own_ticks(os.getpid())
    assert waited - before >= 0.5 * os.sysconf("SC_CLK_TCK")
    child = subprocess.Popen([sys.executable, "-c", burn + "time.sleep(5)\n"])  # still running: read through /proc
    try:
        time.sleep(0.3)
        deadline = time.monotonic() + 10
        while own_ticks(os.getpid()) - waited < 0.5 * os.sysconf("SC_CLK_TCK") and time.monotonic() < deadline:
            time.sleep(0.1)
        assert own_ticks(os.getpid()) - waited >= 0.5 * os.sysconf("SC_CLK_TCK")
    finally:
        child.kill()
        child.wait()
