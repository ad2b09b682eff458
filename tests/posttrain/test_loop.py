import json
import math
from pathlib import Path

import pytest
import torch

from posttrain import loop


def test_lr_factor_warmup_cosine_linear():
    assert loop.lr_factor(0, 10, 110, "cosine", 0.1) == pytest.approx(0.1)
    assert loop.lr_factor(9, 10, 110, "cosine", 0.1) == pytest.approx(1.0)
    assert loop.lr_factor(10, 10, 110, "cosine", 0.1) == pytest.approx(1.0)
    assert loop.lr_factor(60, 10, 110, "cosine", 0.1) == pytest.approx(0.1 + 0.9 * 0.5)
    assert loop.lr_factor(110, 10, 110, "cosine", 0.1) == pytest.approx(0.1)
    assert loop.lr_factor(60, 10, 110, "linear", 0.0) == pytest.approx(0.5)
    assert loop.lr_factor(60, 10, 110, "constant", 0.0) == 1.0


def test_batch_indices_pure_epochs_and_shards():
    a = loop.batch_indices(10, 4, seed=1, step=3)
    assert a == loop.batch_indices(10, 4, seed=1, step=3)
    # 2 batches per epoch (last partial dropped); an epoch has no repeats
    e0 = loop.batch_indices(10, 4, 1, 0) + loop.batch_indices(10, 4, 1, 1)
    assert len(set(e0)) == 8
    assert loop.batch_indices(10, 4, 1, 2) != loop.batch_indices(10, 4, 1, 0)  # new epoch, new order
    full = loop.batch_indices(10, 4, 1, 5)
    assert loop.batch_indices(10, 4, 1, 5, rank=0, world=2) + loop.batch_indices(10, 4, 1, 5, rank=1, world=2) \
        == full[0::2] + full[1::2]
    with pytest.raises(ValueError, match="fewer than batch_size"):
        loop.batch_indices(3, 4, 0, 0)


def _toy():
    torch.manual_seed(0)
    model = torch.nn.Linear(3, 1)
    opt = loop.build_optimizer(model, lr=0.1)
    sch = loop.build_scheduler(opt, 0, 10, "constant")
    return model, opt, sch


class _Acc:  # the subset of Accelerator used by optimizer_step / Checkpointer
    num_processes = 1
    is_main_process = True

    def backward(self, loss):
        loss.backward()

    def clip_grad_norm_(self, params, max_norm):
        return torch.nn.utils.clip_grad_norm_(params, max_norm)

    def unwrap_model(self, m):
        return m

    def get_state_dict(self, m):
        return m.state_dict()

    def wait_for_everyone(self):
        pass


def test_nonfinite_loss_on_another_process_stops_this_one_before_backward():
    """Under several processes every process must stop at the same micro-batch: one that raised while the others
    entered backward would leave them waiting in the gradient all-reduce forever."""

    class TwoProcesses(_Acc):
        num_processes = 2
        device = torch.device("cpu")

        def no_sync(self, model):
            import contextlib
            return contextlib.nullcontext()

        def reduce(self, t, reduction="sum"):  # the other process reports a non-finite loss
            return t + 1.0

        def gather(self, t):  # both processes bring one micro-batch
            return torch.cat([t, t])

        def backward(self, loss):
            raise AssertionError("backward must not start when any process's loss is non-finite")

    model, opt, sch = _toy()
    finite = lambda mb: (model(torch.ones(1, 3)).sum(), {})
    with pytest.raises(loop.TrainingError, match="non-finite loss on 1 other process.* at step 5"):
        loop.optimizer_step(TwoProcesses(), model, opt, sch, [0], finite, 1.0, 5)


def test_a_process_with_fewer_micro_batches_runs_zero_loss_copies_to_keep_in_step():
    """Token budgets may give processes different numbers of micro-batches: each runs as many as the most any
    process has (here the other has 3), the extra ones copies of its last with loss x 0, so its gradient, loss
    and metrics are those of its own micro-batches, and every collective of the step lines up."""
    calls = {"reduce": 0, "backward": 0}

    class OtherHasThree(_Acc):
        num_processes = 2
        device = torch.device("cpu")

        def no_sync(self, model):
            import contextlib
            return contextlib.nullcontext()

        def gather(self, t):
            return torch.cat([t, torch.tensor([3] * t.shape[0]).view_as(t)]) if t.dim() == 1 else torch.cat([t, t])

        def reduce(self, t, reduction="sum"):
            calls["reduce"] += 1
            return t * (2 if reduction == "sum" else 1)

        def backward(self, loss):
            calls["backward"] += 1
            loss.backward()

    x, y = torch.randn(4, 3), torch.randn(4, 1)
    loss_fn = lambda model: (lambda mb: (((model(x[mb]) - y[mb]) ** 2).sum() / 4, {"seen": float(len(mb))}))
    model, opt, sch = _toy()
    out = loop.optimizer_step(OtherHasThree(), model, opt, sch, [[0, 1, 2, 3]], loss_fn(model), 0.0, 1)
    assert calls["backward"] == 3  # one real micro-batch and two copies: the other process's count
    assert out["seen"] == 4.0  # the copies add no metric (averaged over processes: both saw 4 here)
    alone, opt_a, sch_a = _toy()
    loop.optimizer_step(_Acc(), alone, opt_a, sch_a, [[0, 1, 2, 3]], loss_fn(alone), 0.0, 1)
    for a, b in zip(model.parameters(), alone.parameters()):
        torch.testing.assert_close(a, b)  # the copies added no gradient


def test_accumulation_equals_one_big_batch():
    x = torch.randn(8, 3)
    y = torch.randn(8, 1)
    grads = []
    for splits in ([8], [4, 4], [2, 2, 2, 2]):
        model, opt, sch = _toy()
        mbs = list(torch.split(torch.arange(8), splits))

        def loss_fn(ix):
            return ((model(x[ix]) - y[ix]) ** 2).sum() / 8, {}

        before = model.weight.detach().clone()
        loop.optimizer_step(_Acc(), model, opt, sch, mbs, loss_fn, max_grad_norm=0, step=0)
        grads.append(model.weight.detach() - before)
    assert torch.allclose(grads[0], grads[1], atol=1e-6) and torch.allclose(grads[0], grads[2], atol=1e-6)


def test_nonfinite_loss_raises_with_step():
    model, opt, sch = _toy()
    with pytest.raises(loop.TrainingError, match="non-finite loss .* at step 17"):
        loop.optimizer_step(_Acc(), model, opt, sch, [0], lambda mb: (torch.tensor(float("nan"), requires_grad=True), {}), 1.0, 17)


def test_checkpoint_roundtrip_atomic_and_pruned(tmp_path):
    model, opt, sch = _toy()
    ck = loop.Checkpointer(tmp_path, keep=2, accelerator=_Acc())
    x = torch.randn(4, 3)
    for step in (1, 2, 3):
        loop.optimizer_step(_Acc(), model, opt, sch, [0], lambda mb: (model(x).pow(2).mean(), {}), 1.0, step)
        ck.save(step, model, opt, sch, {"step": step})
    assert [p.name for p in ck.all()] == ["step-000002", "step-000003"]
    # a torn temp dir from a killed save is ignored
    (ck.dir / ".tmp-step-000004-1").mkdir()
    assert ck.latest().name == "step-000003"
    torch.manual_seed(123)
    expected_next = torch.rand(1)
    m2, o2, s2 = _toy()
    torch.manual_seed(123)
    ck.save(4, model, opt, sch, {"step": 4})
    info = ck.load(ck.latest(), m2, o2, s2)
    assert info["step"] == 4 and info["data"] == {"step": 4}
    assert torch.equal(m2.weight, model.weight)
    assert o2.state_dict()["state"][0]["exp_avg"].equal(opt.state_dict()["state"][0]["exp_avg"])
    assert torch.rand(1).equal(expected_next)  # RNG restored to the saved state


class _Disk:
    """`shutil.disk_usage` of a disk of `capacity` bytes that holds only the checkpoint files under `root`."""

    def __init__(self, root, capacity):
        self.root, self.capacity = root, capacity

    def __call__(self, path):
        import collections

        used = sum(f.stat().st_size for f in self.root.rglob("*") if f.is_file())
        return collections.namedtuple("usage", "total used free")(self.capacity, used, self.capacity - used)


def _big():  # a model whose checkpoint (~400 kB with AdamW's two moments) dwarfs pickle's overhead
    torch.manual_seed(0)
    model = torch.nn.Linear(100, 300)
    opt = loop.build_optimizer(model, lr=0.1)
    return model, opt, loop.build_scheduler(opt, 0, 10, "constant")


def _two_checkpoints(tmp_path, keep):
    model, opt, sch = _big()
    ck = loop.Checkpointer(tmp_path, keep=keep, accelerator=_Acc())
    for step in (1, 2):
        loop.optimizer_step(_Acc(), model, opt, sch, [0], lambda mb: (model(torch.randn(2, 100)).pow(2).mean(), {}), 1.0,
                           step)
        ck.save(step, model, opt, sch, {"step": step})
    size = (ck.dir / "step-000002" / "state.pt").stat().st_size
    return ck, model, opt, sch, size


def test_a_checkpoint_short_of_disk_first_drops_the_old_ones_its_save_would_drop(tmp_path, monkeypatch):
    ck, model, opt, sch, size = _two_checkpoints(tmp_path, keep=2)
    # room for the two on disk plus half of a third: dropping step 1 (which this save drops anyway) makes room
    monkeypatch.setattr(loop.shutil, "disk_usage", _Disk(ck.dir, int(2.5 * size) + 2**20))
    ck.save(3, model, opt, sch, {"step": 3})
    assert [p.name for p in ck.all()] == ["step-000002", "step-000003"]


@pytest.mark.parametrize("keep", [1, 2])
def test_a_checkpoint_the_disk_has_no_room_for_stops_the_run_naming_sizes_and_keeps_the_newest(tmp_path, monkeypatch, keep):
    ck, model, opt, sch, size = _two_checkpoints(tmp_path, keep=keep)
    kept = [p.name for p in ck.all()]
    monkeypatch.setattr(loop.shutil, "disk_usage", _Disk(ck.dir, int((len(kept) + 0.5) * size)))
    with pytest.raises(loop.TrainingError, match=r"not enough disk for the checkpoint of step 3: it takes [\d,.]+ MiB "
                       r"and .*checkpoints has [\d,.]+ MiB free \(the newest checkpoint, step-000002, is intact\)"):
        ck.save(3, model, opt, sch, {"step": 3})
    assert [p.name for p in ck.all()] == ["step-000002"]  # step 1 (keep=2) went first: this save drops it anyway
    assert not list(ck.dir.glob(".tmp-*"))
    m2, o2, s2 = _big()
    assert ck.load(ck.latest(), m2, o2, s2)["step"] == 2 and torch.equal(m2.weight, model.weight)


# What a full disk raises: torch.save a bare RuntimeError from its zip writer, safetensors its own error (both seen
# on a 2 MiB tmpfs, torch 2.13, safetensors 0.7), plain writes OSError(ENOSPC).
TORCH_FULL = RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 576 vs 534")
SAFETENSORS_FULL = RuntimeError("Error while serializing: I/O error: No space left on device (os error 28)")


@pytest.mark.parametrize("error, disk_left, full", [
    (OSError(28, "No space left on device"), None, True),
    (TORCH_FULL, 0, True),  # no errno: the bytes written plus those free fall short of the checkpoint
    (SAFETENSORS_FULL, None, True),
    (TORCH_FULL, None, False),  # the disk had room: some other failure, raised as it is
])
def test_a_write_that_fails_on_a_full_disk_stops_the_run_and_leaves_no_temp_dir(tmp_path, monkeypatch, error,
                                                                                 disk_left, full):
    ck, model, opt, sch, size = _two_checkpoints(tmp_path, keep=2)
    disk = _Disk(ck.dir, 10 * size + 2**21)

    def failing_save(obj, f):
        Path(f).write_bytes(b"half a checkpoint")
        if disk_left is not None:  # something else filled the disk meanwhile
            disk.capacity = sum(p.stat().st_size for p in ck.dir.rglob("*") if p.is_file()) + disk_left
        raise error

    monkeypatch.setattr(loop.shutil, "disk_usage", disk)
    monkeypatch.setattr(loop.torch, "save", failing_save)
    if full:
        with pytest.raises(loop.TrainingError, match=r"the disk filled while writing the checkpoint of step 3 in "
                           r".*\(the newest checkpoint, step-000002, is intact; its temp dir removed\)"):
            ck.save(3, model, opt, sch, {"step": 3})
    else:
        with pytest.raises(type(error), match="enforce fail"):
            ck.save(3, model, opt, sch, {"step": 3})
    assert [p.name for p in ck.all()] == ["step-000001", "step-000002"] and not list(ck.dir.glob(".tmp-*"))


def test_out_of_disk_tells_a_full_disk_from_other_write_failures(tmp_path, monkeypatch):
    from posttrain.models import out_of_disk

    part = tmp_path / "partial"
    part.mkdir()
    (part / "a").write_bytes(b"x" * 1000)
    import collections

    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(loop.shutil, "disk_usage", lambda p: usage(10**6, 10**6 - 500, 500))
    assert out_of_disk(OSError(28, "No space left on device"), part, 10**9)
    assert out_of_disk(SAFETENSORS_FULL, part, 10**9)
    assert out_of_disk(TORCH_FULL, part, 2000)  # 1000 written + 500 free < 2000
    assert not out_of_disk(TORCH_FULL, part, 1500)  # it would have fit
    assert not out_of_disk(OSError(13, "Permission denied"), part, 1500)
    assert out_of_disk(TORCH_FULL, tmp_path / "never-written", 501)


def test_a_disk_that_fills_while_final_is_saved_stops_the_run_and_keeps_the_earlier_one(tiny_lm, tmp_path, monkeypatch):
    from posttrain import models

    src = tiny_lm()
    model, tok = models.load_model(src), models.load_tokenizer(src)
    out = models.save_model(model, tok, tmp_path / "final")
    before = sorted(p.name for p in out.iterdir())

    def full(self, path, **kw):
        (Path(path) / "model.safetensors").write_bytes(b"half a model")
        raise SAFETENSORS_FULL

    monkeypatch.setattr(type(model), "save_pretrained", full)
    with pytest.raises(loop.TrainingError, match=r"the disk filled while saving the model to .*final \(its temp dir "
                       r"removed, the one there before kept\)"):
        models.save_model(model, tok, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["final"] and sorted(p.name for p in out.iterdir()) == before


def test_metrics_truncate_after(tmp_path):
    m = loop.MetricsLog(tmp_path / "metrics.jsonl", 10, quiet=True)
    for s in (1, 2, 3, 4):
        m.log(s, {"loss": 1.0 / s})
    with open(tmp_path / "metrics.jsonl", "a") as f:
        f.write('{"step": 5, "lo')  # torn line of a killed run
    m.truncate_after(2)
    rows = [json.loads(l) for l in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [1, 2]
    assert math.isclose(rows[1]["loss"], 0.5)


def test_prepare_run_dir_keeps_previous(tmp_path):
    d = tmp_path / "sft"
    d.mkdir()
    (d / "metrics.jsonl").write_text("x")
    loop.prepare_run_dir(d, resume=False, log=lambda s: None)
    assert (tmp_path / "sft.prev" / "metrics.jsonl").read_text() == "x"
    assert d.is_dir() and not any(d.iterdir())


def test_build_optimizer_is_fused_and_bumps_versions_so_the_rollout_engine_sees_updates():
    """The fused AdamW kernel writes weights without bumping version counters; the engine caches its fused
    weights by version counters, so a stale cache would sample from the weights before the update."""
    from posttrain.models import build_model, train_tokenizer
    from posttrain.rollout import generate

    tok = train_tokenizer([f"a b c {i} d e" for i in range(50)], vocab_size=300)
    model = build_model("tiny", tok, seed=0)
    opt = loop.build_optimizer(model, lr=0.5)
    assert opt.param_groups[0]["fused"]
    greedy = dict(max_new_tokens=8, greedy=True, ignore_eos=True)
    before = generate(model, tok, ["a b"], **greedy)[0].policy_logprobs
    versions = [p._version for p in model.parameters()]
    ids = torch.tensor([tok("a b c d e")["input_ids"]])
    model(input_ids=ids, labels=ids).loss.backward()
    opt.step()
    assert all(p._version > v for p, v in zip(model.parameters(), versions))
    after = generate(model, tok, ["a b"], **greedy)[0].policy_logprobs
    fresh = generate(model, tok, ["a b"], backend="hf", **greedy)[0].policy_logprobs
    assert after != before and max(abs(a - b) for a, b in zip(after, fresh)) < 1e-4


def test_optimizer_step_metrics_plain_and_weighted():
    """Without weights: means over micro-batches; with weights (shares of the batch): weighted means, `_sum`
    summed, `_max` maxed, and a weight-0 (padding) micro-batch adds to no metric. Hand-computed."""
    torch.manual_seed(0)
    model = torch.nn.Linear(2, 1)
    x = torch.randn(3, 2)
    metrics = [{"a": 1.0, "n_sum": 2.0, "r_max": 5.0}, {"a": 3.0, "n_sum": 4.0, "r_max": 7.0},
               {"a": 100.0, "n_sum": 100.0, "r_max": 100.0}]  # the third one: a padding copy

    def loss_fn(i):
        return model(x[i]).sum() * 0.0, metrics[i]

    def step(mbs, weights=None):
        opt = loop.build_optimizer(model, 1e-3)
        sch = loop.build_scheduler(opt, 0, 10, "constant")
        return loop.optimizer_step(_Acc(), model, opt, sch, mbs, loss_fn, 0.0, 1, weights=weights)

    plain = step([0, 1])
    assert (plain["a"], plain["n_sum"], plain["r_max"]) == (2.0, 6.0, 7.0)
    weighted = step([0, 1, 2], weights=[0.25, 0.75, 0.0])
    assert weighted["a"] == 0.25 * 1.0 + 0.75 * 3.0
    assert (weighted["n_sum"], weighted["r_max"]) == (6.0, 7.0)
    with pytest.raises(ValueError, match="2 weights for 3 micro-batches"):
        step([0, 1, 2], weights=[0.5, 0.5])


def test_naming_checkpoint_and_check_weights(tmp_path):
    ckpt = loop.Checkpointer(tmp_path)
    model = torch.nn.Linear(2, 1)
    with pytest.raises(loop.TrainingError, match=r"^boom \(iteration 3; no checkpoint was written yet\)$"):
        with loop.naming_checkpoint(ckpt, "iteration 3"):
            raise loop.TrainingError("boom")
    ckpt.save(2, model)
    with torch.no_grad():
        model.weight[0, 0] = float("inf")
    assert not loop.weights_finite(model)
    with pytest.raises(loop.TrainingError, match=r"non-finite weights after step 4; .*last good checkpoint: .*step-000002"):
        with loop.naming_checkpoint(ckpt):
            loop.check_weights(4, model)


def test_resume_run_fresh_missing_and_restored(tmp_path):
    said = []
    model = torch.nn.Linear(2, 1)
    ckpt = loop.Checkpointer(tmp_path)
    log = loop.MetricsLog(tmp_path / "metrics.jsonl", 10)
    assert loop.resume_run(ckpt, log, model, resume=False, say=said.append, tag="t")["step"] == 0 and not said
    assert loop.resume_run(ckpt, log, model, resume=True, say=said.append, tag="t")["step"] == 0
    assert "resume=true but no checkpoint" in said[-1] and said[-1].endswith("starting from step 0")
    for s in (1, 2, 3):
        log.log(s, {"loss": float(s)}, console=False)
    ckpt.save(2, model, extra={"k": 1})
    state = loop.resume_run(ckpt, log, model, resume=True, say=said.append, tag="t", unit="iteration")
    assert state["step"] == 2 and state["extra"] == {"k": 1} and said[-1].endswith("at iteration 2")
    assert [r["step"] for r in loop.iter_jsonl(tmp_path / "metrics.jsonl")] == [1, 2]


def test_mixed_precision_auto_is_bf16_only_where_the_hardware_has_it_and_it_measures_faster(monkeypatch):
    from posttrain import runtime

    probes = []
    monkeypatch.setattr(runtime.torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(runtime, "_bf16_speedups", {})
    monkeypatch.setattr(runtime, "_matmul_time_ratio", lambda rows, **kw: probes.append(rows) or speed[rows])
    speed = {16: 1.5, 256: 2.4}  # Zen 4-like
    monkeypatch.setattr(runtime, "cpu_flags", lambda: {"avx2", "avx512f", "avx512_bf16"})
    assert runtime.native_bf16() and runtime.mixed_precision("auto") == "bf16"
    assert runtime.bf16_speedup() == 1.5 and probes == [16, 256]  # the smaller ratio; measured once per process
    monkeypatch.setattr(runtime, "cpu_flags", lambda: {"avx2", "amx_bf16", "amx_tile"})
    assert runtime.mixed_precision("auto") == "bf16" and probes == [16, 256]
    monkeypatch.setattr(runtime, "cpu_flags", lambda: {"avx2", "avx512f", "avx512_bf16"})
    monkeypatch.setattr(runtime, "_bf16_speedups", {})
    speed = {16: 1.1, 256: 0.6}  # the Intel Xeon whose flags list AVX512-BF16 without AMX
    assert not runtime.native_bf16() and runtime.mixed_precision("auto") is None
    monkeypatch.setattr(runtime, "cpu_flags", lambda: {"avx2", "avx512f"})  # Zen 3 / older Intel: emulated bf16
    monkeypatch.setattr(runtime, "_bf16_speedups", {})
    assert not runtime.native_bf16() and runtime.mixed_precision("auto") is None and probes == [16, 256, 16, 256]
    assert runtime.mixed_precision("bf16") == "bf16" and runtime.mixed_precision("no") is None  # no probe: as set
    with pytest.raises(ValueError, match="run.mixed_precision must be no, bf16 or auto"):
        runtime.mixed_precision("fp8")


def test_posttrain_bf16_and_a_pinned_decision_answer_auto_without_a_probe(monkeypatch):
    """POSTTRAIN_BF16=1|0 decides both auto settings on any machine, a pinned decision (a resumed run's) when it is
    unset; neither runs the probe; a bad value is one clear error naming the variable."""
    from posttrain import runtime
    from posttrain.errors import ConfigError

    def no_probe(rows, **kw):
        raise AssertionError("the probe ran")

    monkeypatch.setattr(runtime.torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(runtime, "_bf16_speedups", {})
    monkeypatch.setattr(runtime, "_matmul_time_ratio", no_probe)
    monkeypatch.setattr(runtime, "cpu_flags", lambda: {"avx2", "avx512f", "avx512_bf16"})
    monkeypatch.setattr(runtime, "_bf16_pinned", None)
    for value, bf16 in (("1", True), ("on", True), ("0", False), ("False", False)):
        monkeypatch.setenv("POSTTRAIN_BF16", value)
        assert runtime.native_bf16() is bf16 and runtime.mixed_precision("auto") == ("bf16" if bf16 else None)
        assert runtime.bf16_forced() == (bf16, f"POSTTRAIN_BF16={value.lower()}")
    runtime.pin_bf16(True)  # the environment beats a pin
    assert runtime.native_bf16() is False
    monkeypatch.setenv("POSTTRAIN_BF16", "yes please")
    with pytest.raises(ConfigError, match=r"POSTTRAIN_BF16='yes please': use 1 \(bf16\) or 0 \(fp32\)"):
        runtime.native_bf16()
    monkeypatch.delenv("POSTTRAIN_BF16")
    assert runtime.native_bf16() is True  # the pin, even on a CPU whose probe would say otherwise
    monkeypatch.setattr(runtime, "cpu_flags", lambda: {"avx2"})
    runtime.pin_bf16(False)
    assert runtime.native_bf16() is False and runtime.mixed_precision("bf16") == "bf16"  # explicit settings win
    runtime.pin_bf16(None)
    assert runtime.native_bf16() is False and runtime.bf16_forced() is None  # decided by the flags again


def test_recorded_bf16_reads_what_start_run_wrote_and_names_a_bad_file(tmp_path):
    from posttrain.errors import ConfigError

    assert loop.recorded_bf16(tmp_path) is None  # no record: no auto setting, or an older run
    (tmp_path / loop.PRECISION_FILE).write_text(json.dumps({"bf16": True, "decided_by": "probe"}))
    assert loop.recorded_bf16(tmp_path) is True
    (tmp_path / loop.PRECISION_FILE).write_text("{not json")
    with pytest.raises(ConfigError, match="precision.json: not the JSON object posttrain wrote"):
        loop.recorded_bf16(tmp_path)


def test_the_bf16_probe_measures_a_positive_ratio_once_per_thread_count(monkeypatch):
    from posttrain import runtime

    monkeypatch.setattr(runtime, "_bf16_speedups", {})
    assert runtime.bf16_measured() is None
    first = runtime.bf16_speedup()
    assert runtime.bf16_measured() == first  # what the run prints
    assert 0 < first < 100 and runtime.bf16_speedup() == first  # cached: the second call does not re-measure
    assert list(runtime._bf16_speedups) == [runtime.torch.get_num_threads()]


def test_progress_prints_only_long_phases_throttled_with_an_eta():
    from posttrain.loop import Progress

    clock, lines = [0.0], []
    p = Progress("[eval] generating", every_s=10.0, quiet=False, clock=lambda: clock[0], out=lines.append)
    for done, t in [(8, 4.0), (16, 12.0), (24, 15.0), (32, 24.0), (64, 40.0)]:
        clock[0] = t
        p(done, 64)
    assert lines == ["[eval] generating: 16/64 (25%), 12s elapsed, eta 36s",
                     "[eval] generating: 32/64 (50%), 24s elapsed, eta 24s",
                     "[eval] generating: 64/64 done in 40s"]
    short, quiet = [], []
    p = Progress("x", every_s=10.0, quiet=False, clock=lambda: 1.0, out=short.append)
    p(5, 10), p(10, 10)
    q = Progress("x", every_s=0.0, quiet=True, out=quiet.append)
    q(5, 10), q(10, 10)
    assert short == [] and quiet == []


def test_progress_follows_the_stage_quiet_setting(tmp_path, capsys):
    """run.quiet=true (and every process but the main one) silences the progress lines of long phases."""
    from posttrain import loop

    before = loop.Progress.default_quiet
    try:
        for quiet, expect in ((True, []), (False, ["x: 5/10 (50%), 0s elapsed, eta 0s"])):
            loop.set_progress_quiet(quiet)
            lines = []
            loop.Progress("x", every_s=0.0, clock=lambda: 0.0, out=lines.append)(5, 10)
            assert lines == expect, quiet
        from posttrain.config import resolve
        from posttrain.trainers.sft import SFTConfig

        res = resolve("tiny-summarize", "sft", SFTConfig, [f"run.output_dir={tmp_path}", "run.quiet=true"])
        loop.start_run(res, 0, False)
        assert loop.Progress.default_quiet is True
    finally:
        loop.set_progress_quiet(before)


def test_generate_reports_progress_per_micro_batch(tiny_lm):
    from posttrain.models import load_model, load_tokenizer
    from posttrain.rollout import generate

    d = tiny_lm()
    model, tok = load_model(d), load_tokenizer(d)
    calls = []
    generate(model, tok, ["a b", "c d e", "f"], n=2, max_new_tokens=4, max_batch_tokens=16,
             progress=lambda done, total: calls.append((done, total)))
    assert len(calls) >= 2 and calls[-1] == (6, 6)
    assert all(t == 6 for _, t in calls) and [c for c, _ in calls] == sorted(c for c, _ in calls)
    # one micro-batch (a real model's whole evaluation may be one): reported at every decoding step, rows counted
    # as they finish, and "all done" only once, at the end
    one = []
    generate(model, tok, ["a b", "c d e", "f"], n=2, max_new_tokens=4, ignore_eos=True,
             progress=lambda done, total: one.append((done, total)))
    assert one == [(0, 6), (0, 6), (0, 6), (5, 6), (6, 6)]  # 4 steps; every row ends at its limit on the last


def test_several_processes_adopt_process_zeros_bf16_probe(monkeypatch):
    """Under `accelerate launch` (WORLD_SIZE > 1) only process 0 probes; every process adopts its ratio, so `auto`
    picks one precision on all ranks even where a rank's own probe would land on the other side of the bar."""
    import accelerate
    import accelerate.utils

    from posttrain import runtime

    sent = []

    class FakeState:
        def __init__(self, cpu=False):
            assert cpu
            self.is_main_process = rank == 0

    def broadcast(values, from_process=0):
        assert from_process == 0
        if rank == 0:
            sent.append(values[0])
        else:
            values[0] = sent[0]
        return values

    monkeypatch.setattr(accelerate, "PartialState", FakeState)
    monkeypatch.setattr(accelerate.utils, "broadcast_object_list", broadcast)
    monkeypatch.setattr(runtime.torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(runtime, "cpu_flags", lambda: {"avx2", "avx512f", "avx512_bf16"})
    monkeypatch.setattr(runtime, "_bf16_pinned", None)
    monkeypatch.delenv("POSTTRAIN_BF16", raising=False)
    monkeypatch.setenv("WORLD_SIZE", "2")
    own = {0: 1.5, 1: 1.1}  # each rank's own measurement: bf16 on rank 0, fp32 on rank 1 had they decided alone
    for rank in (0, 1):
        monkeypatch.setattr(runtime, "_bf16_speedups", {})
        monkeypatch.setattr(runtime, "_matmul_time_ratio", lambda rows, **kw: own[rank] if rank == 0 else
                            pytest.fail("a process other than 0 ran the probe"))
        loop.share_bf16_probe()
        assert runtime.bf16_measured() == 1.5 and runtime.native_bf16() and runtime.mixed_precision("auto") == "bf16"
    assert sent == [1.5]

    def untouched():  # the no-op cases: no process group, no probe, no broadcast
        monkeypatch.setattr(runtime, "_bf16_speedups", {})
        loop.share_bf16_probe()
        assert runtime.bf16_measured() is None and sent == [1.5]

    monkeypatch.setattr(accelerate, "PartialState", lambda cpu=False: pytest.fail("a process group was started"))
    monkeypatch.setenv("WORLD_SIZE", "1")
    untouched()
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("POSTTRAIN_BF16", "0")
    untouched()
    monkeypatch.delenv("POSTTRAIN_BF16")
    monkeypatch.setattr(runtime, "cpu_flags", lambda: {"avx2"})  # no bf16 units listed: nothing to agree on
    untouched()
    monkeypatch.setattr(runtime, "cpu_flags", lambda: {"avx2", "avx512f", "avx512_bf16"})
    monkeypatch.setattr(runtime.torch.cuda, "is_available", lambda: True)  # a GPU decides by its capability
    untouched()


def test_nonfinite_grads_names_the_parameters_whose_gradient_is_not_finite():
    from posttrain.loop import nonfinite_grads

    model = torch.nn.Sequential(torch.nn.Linear(3, 3), torch.nn.Linear(3, 1))
    model(torch.ones(2, 3)).sum().backward()
    assert nonfinite_grads(model) == ""
    model[1].weight.grad[0, 1] = float("nan")
    model[0].bias.grad[2] = float("inf")
    assert nonfinite_grads(model) == " (non-finite gradients in 0.bias, 1.weight: 2 of 4 parameters)"


def test_tune_malloc_keeps_large_blocks_in_the_heap_once_per_process(monkeypatch):
    """`runtime.tune_malloc` turns glibc's mmap of large blocks off (M_MMAP_MAX 0) and raises the trim threshold,
    once; POSTTRAIN_NO_MALLOPT=1 or a platform other than Linux leaves malloc alone."""
    import sys

    from posttrain import runtime

    calls = []

    class FakeLibc:
        def mallopt(self, param, value):
            calls.append((param, value))
            return 1

    monkeypatch.setattr(runtime.ctypes, "CDLL", lambda name: FakeLibc())
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("POSTTRAIN_NO_MALLOPT", raising=False)
    monkeypatch.setattr(runtime, "_malloc_tuned", False)
    assert runtime.tune_malloc() is True
    assert calls == [(-4, 0), (-1, 512 << 20)]  # M_MMAP_MAX, M_TRIM_THRESHOLD
    assert runtime.tune_malloc() is True and len(calls) == 2  # once per process
    monkeypatch.setattr(runtime, "_malloc_tuned", False)
    monkeypatch.setenv("POSTTRAIN_NO_MALLOPT", "1")
    assert runtime.tune_malloc() is False and len(calls) == 2


@pytest.mark.parametrize("max_norm", [0.05, 100.0])  # clipping, and a norm under the bound (nothing to clip)
def test_clipping_inside_the_fused_adamw_step_equals_clip_grad_norm_then_step(max_norm):
    """One process, fused AdamW: the clip rides in the optimizer step as its gradient divisor (`clip_divisor`)
    instead of a pass of its own over the gradients. The weights after the step and the logged norm are those of
    `torch.nn.utils.clip_grad_norm_` followed by the step, and the divisor does not outlive the step."""
    accelerator = loop.setup(0)
    x, y = torch.randn(16, 6), torch.randn(16, 2)

    def build():
        torch.manual_seed(1)
        model = torch.nn.Sequential(torch.nn.Linear(6, 8), torch.nn.LayerNorm(8), torch.nn.Linear(8, 2))
        opt = loop.build_optimizer(model, lr=0.1, weight_decay=0.1)
        return model, opt, loop.build_scheduler(opt, 0, 10, "constant")

    model, opt, sch = build()
    model, opt = accelerator.prepare(model, opt)
    assert loop._fused_clip_target(accelerator, opt) is opt.optimizer  # the path under test
    ref, ref_opt, ref_sch = build()
    for step in (1, 2, 3):
        out = loop.optimizer_step(accelerator, model, opt, sch, [0], lambda mb: (((model(x) - y) ** 2).mean(), {}),
                                  max_norm, step)
        ((ref(x) - y) ** 2).mean().backward()
        norm = torch.nn.utils.clip_grad_norm_(ref.parameters(), max_norm)
        ref_opt.step()
        ref_sch.step()
        ref_opt.zero_grad(set_to_none=True)
        assert out["grad_norm"] == pytest.approx(float(norm), rel=1e-6)
        assert (float(norm) > max_norm) == (max_norm == 0.05)  # both regimes really happen
        assert getattr(opt.optimizer, "grad_scale", None) is None
        for a, b in zip(model.parameters(), ref.parameters()):
            torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)


def test_clip_divisor_is_the_reciprocal_of_clip_grad_norms_coefficient():
    assert float(loop.clip_divisor(torch.tensor(4.0), 1.0)) == pytest.approx((4.0 + 1e-6) / 1.0)
    assert float(loop.clip_divisor(torch.tensor(0.5), 1.0)) == 1.0  # under the bound: unchanged
    g = [torch.tensor([3.0, 4.0]), torch.tensor([12.0])]
    assert float(loop.total_norm(g)) == pytest.approx(13.0)
    assert float(loop.total_norm([])) == 0.0
