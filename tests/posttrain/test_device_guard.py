"""Device placement checked without a GPU: every stage runs a step with its model on a second device.

`device_guard.VirtualDevice` splits the CPU into a host and a device the way a CUDA machine is split (see its
docstring): the trainers put their model on `Accelerator.device`, which reports the virtual device inside the
guard, and an op that mixes a device tensor with a host tensor raises as CUDA does. On 880b27d the SFT step
raised here exactly where it crashed on an H200 (`nll_sum`: `logps * weights`, the weights built on the host);
docs/results-archive.md ("Device placement") lists what each stage hit.

Each stage runs one or two steps through the CLI in one process (the guard is a torch function mode of this
process), chained in one run directory: sft -> prefs -> rm -> dpo (sigmoid, kto, ipo) -> ppo, eval, distill,
and grpo from the base on tiny-math.
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest
import torch

from posttrain.cli import main


def _load_guard():
    """tests/posttrain/device_guard.py (the suite imports test modules by path: --import-mode=importlib)."""
    if "posttrain_device_guard" not in sys.modules:
        spec = importlib.util.spec_from_file_location("posttrain_device_guard",
                                                      Path(__file__).with_name("device_guard.py"))
        sys.modules[spec.name] = module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    return sys.modules["posttrain_device_guard"]


guard = _load_guard()

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

COMMON = ["task.n_train=48", "task.n_eval=8", "model.max_length=128", "model.vocab_size=384", "run.quiet=true",
          "run.threads=1"]
# Each earlier stage a stage builds through `ensure` (dotted overrides) takes one step too.
CHAIN = ["sft.max_steps=1", "sft.batch_size=4", "sft.eval_every=0", "sft.final_eval_rows=0", "sft.save_every=0",
         "sft.warmup_steps=0", "prefs.n_prompts=8", "prefs.n_eval_prompts=4", "prefs.samples_per_prompt=2",
         "prefs.max_new_tokens=8", "rm.max_steps=1", "rm.batch_size=4", "rm.eval_every=0", "rm.save_every=0",
         "rm.warmup_steps=0"]
STAGES = {
    "sft": ["sft", "--recipe", "tiny-summarize", "max_steps=2", "batch_size=4", "eval_every=1", "eval_loss_rows=4",
            "num_samples=1", "final_eval_rows=2", "max_new_tokens=8", "save_every=0", "warmup_steps=0"],
    "rm": ["rm", "--recipe", "tiny-summarize", "max_steps=2", "batch_size=4", "eval_every=0", "save_every=0",
           "warmup_steps=0"],
    "dpo": ["dpo", "--recipe", "tiny-summarize", "max_steps=2", "batch_size=4", "online=false", "eval_every=0",
            "eval_rows=0", "final_eval_rows=2", "save_every=0", "max_new_tokens=8"],
    "dpo-kto": ["dpo", "--recipe", "tiny-summarize", "max_steps=2", "batch_size=4", "online=false", "loss_type=kto",
                "eval_every=0", "eval_rows=0", "final_eval_rows=0", "save_every=0"],
    **{f"dpo-{loss}": ["dpo", "--recipe", "tiny-summarize", "max_steps=1", "batch_size=4", "online=false",
                        f"loss_type={loss}", "eval_every=0", "eval_rows=0", "final_eval_rows=0", "save_every=0"]
       for loss in ("ipo", "hinge", "simpo", "orpo")},
    "dpo-online": ["dpo", "--recipe", "tiny-summarize", "max_steps=1", "batch_size=4", "online=true",
                   "eval_every=0", "eval_rows=0", "final_eval_rows=0", "save_every=0", "max_new_tokens=8"],
    "ppo": ["ppo", "--recipe", "tiny-summarize", "max_steps=1", "rollout_batch_size=4", "minibatch_size=2", "eval_every=0", "eval_rows=0", "final_eval_rows=2",
            "save_every=0", "max_new_tokens=8"],
    "distill": ["distill", "--recipe", "tiny-math", "teacher=sft", "verifier_workers=0", "max_steps=1", "prompts_per_step=2",
                "group_size=2", "max_new_tokens=8", "eval_every=0", "eval_rows=0", "final_eval_rows=2",
                "save_every=0"],
    "eval": ["eval", "--recipe", "tiny-summarize", "rows=4", "max_new_tokens=8"],
    "grpo": ["grpo", "--recipe", "tiny-math", "model.start_from=base", "max_steps=2", "prompts_per_step=2",
             "group_size=4", "max_new_tokens=12", "zero_variance=keep", "eval_every=0", "eval_rows=0",
             "final_eval_rows=2", "save_every=0", "verifier_workers=0"],
}
# The same stages with LoRA adapters (peft), under bf16 autocast (accelerate's mixed precision) and with bf16
# weights (which the config refuses without a GPU: the test lifts that check), each in a run directory of its own.
VARIANTS = {"lora": ["lora.enabled=true"], "bf16": ["run.mixed_precision=bf16"], "bf16-weights": ["model.dtype=bfloat16"]}
VARIANT_STAGES = {"lora": ("sft", "dpo", "ppo", "grpo"), "bf16": ("sft", "rm", "dpo", "grpo", "distill"),
                  "bf16-weights": ("sft", "rm", "dpo", "ppo", "grpo", "distill")}


# ------------------------------------------------------------------ the guard itself
def test_guard_raises_where_cuda_would_and_allows_what_cuda_allows():
    with guard.VirtualDevice() as g:
        host = torch.ones(3, 4)
        dev = host.to(guard.DEVICE)
        assert dev.device == guard.DEVICE and host.device == torch.device("cpu") and not g.placed(host)
        with pytest.raises(guard.DeviceMismatch, match="mul at .* mixes"):
            dev * host
        with pytest.raises(guard.DeviceMismatch):
            torch.cat([dev, host])
        with pytest.raises(guard.DeviceMismatch):  # a 0-dim host tensor is fine in arithmetic, not in a stack
            torch.stack([dev.sum(), torch.tensor(1.0)])
        lin = torch.nn.Linear(4, 2).to(guard.DEVICE)
        with pytest.raises(guard.DeviceMismatch):
            lin(host)
        assert lin.weight.device == guard.DEVICE and lin(dev).device == guard.DEVICE
        assert (dev * torch.tensor(2.0)).device == guard.DEVICE  # a 0-dim host scalar is fine
        assert torch.zeros(3, device=dev.device).device == guard.DEVICE  # a factory that asks for the device
        assert torch.zeros_like(dev).device == guard.DEVICE and torch.zeros(3).device == torch.device("cpu")
        assert dev[torch.tensor([0, 2])].shape == (2, 4)  # a host index into a device tensor
        with pytest.raises(guard.DeviceMismatch):
            host[torch.tensor([0, 2]).to(guard.DEVICE)]
        host[:2] = dev[:2]  # a copy across devices
        syncs = g.syncs
        float(dev.sum())
        assert g.syncs == syncs + 1
        lin(dev).sum().backward()
        assert lin.weight.grad.device == guard.DEVICE
        torch.optim.AdamW(lin.parameters()).step()


def test_guard_catches_the_h200_sft_crash():
    """The bug an H200 found (880b27d): SFT's per-token weights built from a batch left on the host, multiplied by
    log-probs computed on the model's device."""
    logps_dev = torch.zeros(2, 5)
    with guard.VirtualDevice():
        logps = logps_dev.to(guard.DEVICE)
        weights = torch.ones(2, 5)  # a host batch's completion_mask
        with pytest.raises(guard.DeviceMismatch):
            (logps * weights).sum()


# ------------------------------------------------------------------ every stage, one step
@pytest.fixture(scope="module")
def out(tmp_path_factory):
    return tmp_path_factory.mktemp("device-guard")


def stage_argv(stage: str, out, variant: str = "") -> list[str]:
    return [*STAGES[stage], f"run.output_dir={out / (variant or 'plain')}", *COMMON,
            *(CHAIN if stage != "grpo" else []), *VARIANTS.get(variant, [])]


@pytest.mark.slow
@pytest.mark.parametrize("stage,variant", [(s, "") for s in STAGES] +
                         [(s, v) for v, stages in VARIANT_STAGES.items() for s in stages])
def test_stage_runs_with_its_model_on_another_device(stage, variant, out, monkeypatch):
    if variant == "bf16-weights":  # as on a GPU: half weights allowed
        import posttrain.config
        import posttrain.models

        for module in (posttrain.config, posttrain.models):
            monkeypatch.setattr(module, "dtype_problem", lambda name: None)
    with guard.VirtualDevice() as g:
        rc = main(stage_argv(stage, out, variant))
    assert rc == 0
    assert g.syncs > 0  # the guard saw the run's tensors (a guard that sees nothing passes anything)


# ------------------------------------------------------------------ host syncs in the decode loop
def _decode_syncs(model, tok, new_tokens: int, every: int, monkeypatch) -> tuple[int, dict]:
    from posttrain.rollout import engine, generate

    monkeypatch.setattr(engine, "STATIC_DECODE", True)  # the CUDA loop: static step, no compaction
    monkeypatch.setattr(engine, "EOS_CHECK_EVERY", every)
    with guard.VirtualDevice() as g:
        on_device = model.to(guard.DEVICE)
        generate(on_device, tok, ["a b c", "d e f g h"], max_new_tokens=new_tokens, temperature=1.0)
    return g.syncs, dict(g.sync_sites)


def test_the_cuda_decode_loop_reads_the_device_once_per_eos_window(tiny_lm, monkeypatch):
    """The engine's loop on CUDA (static step, EOS checked every 16 steps) must not sync with the host every step:
    32 more sampled tokens cost at most 32 / 16 more device reads (plus one), where a per-step check costs 32."""
    from posttrain.models import load_model, load_tokenizer

    path = tiny_lm("tiny-summarize", max_length=256)
    model, tok = load_model(path), load_tokenizer(path)
    short, _ = _decode_syncs(model, tok, 32, 16, monkeypatch)
    long, sites = _decode_syncs(model, tok, 64, 16, monkeypatch)
    assert long - short <= 32 // 16 + 1, sites
    per_step_short, _ = _decode_syncs(model, tok, 32, 1, monkeypatch)
    per_step_long, _ = _decode_syncs(model, tok, 64, 1, monkeypatch)
    assert per_step_long - per_step_short >= 32  # the guard sees a per-step check: the bound above means something
