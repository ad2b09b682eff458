"""Rollout backends: the built-in engine stays the default; rollout.backend=vllm without vLLM (or without a GPU) is
one clear line before anything loads; the vLLM adapter (posttrain.rollout.vllm_backend) turns vLLM's outputs into
the same Rollout records and pushes the policy's weights after every update.

vLLM is not installed here (nor on the GPU machine the suite also runs on): the adapter tests run against a
stand-in `vllm` module (below, ~60 lines; with a stand-in "a CUDA GPU is there", whatever the machine has) that
has the shapes of vLLM's public objects (LLM, SamplingParams, RequestOutput / CompletionOutput,
Logprob, LLM.collective_rpc calling a function with the worker first) and returns scripted completions. It tests
OUR side of the boundary (parameter mapping, record conversion, finish reasons, log-probs, weight export and
when it happens, GRPO recomputing pi_old), not vLLM itself."""
from __future__ import annotations

import copy
import importlib.util
import json
import shutil
import subprocess
import sys
import types
from pathlib import Path

import pytest
import torch

from posttrain.cli import main
from posttrain.config import ConfigError
from posttrain.rollout import SamplingParams, configure, default_backend, generate
from posttrain.rollout import vllm_backend

HERE = Path(__file__).resolve().parent


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.fixture(autouse=True)
def _restore_backend():
    """These tests set the process default backend; give later tests theirs back."""
    yield
    configure()


@pytest.fixture(scope="module")
def tiny(tiny_lm):
    return tiny_lm("tiny-countdown", vocab_size=256, max_length=128, split_digits=True)


def _load(path):
    from posttrain.models import load_model, load_tokenizer

    return load_model(path), load_tokenizer(path)


# ----------------------------------------------------------------------------- a stand-in for vllm
def fake_vllm() -> types.ModuleType:
    """A module with the shapes of vLLM's offline API. `LLM.script(prompt_ids, params, j)` decides each completion:
    (token ids, finish_reason, stop_reason, per-token logprob); the default ends row j of a prompt after
    1 + (seed + j) % max_tokens tokens taken from the prompt, with EOS (finish "stop", stop_reason None) unless
    that is the whole budget (finish "length"); every log-prob is -1.0 (deliberately not the policy's)."""
    mod = types.ModuleType("vllm")

    class SamplingParams:
        def __init__(self, **kw):
            self.__dict__.update(kw)

    class Logprob:
        def __init__(self, logprob):
            self.logprob = logprob

    class LLM:
        instances: list = []
        eos_id = 1

        def __init__(self, model, **kwargs):
            self.model, self.kwargs = model, kwargs
            self.calls, self.pushes, self.cache_resets = [], [], 0
            loaded = self.pushes

            class Model:
                def load_weights(self, weights):
                    loaded.append({k: v.detach().clone() for k, v in weights})

            self.worker = types.SimpleNamespace(model_runner=types.SimpleNamespace(model=Model()))
            LLM.instances.append(self)

        def script(self, prompt_ids, sp, j):
            n = 1 + (sp.seed + j) % sp.max_tokens
            toks = [prompt_ids[(sp.seed + j + t) % len(prompt_ids)] for t in range(n)]
            if n < sp.max_tokens and not sp.ignore_eos:
                return toks[:-1] + [LLM.eos_id], "stop", None, -1.0
            return toks, "length", None, -1.0

        def generate(self, prompts, sampling_params, use_tqdm=True):
            assert len(prompts) == len(sampling_params)
            self.calls.append((prompts, sampling_params))
            outs = []
            for req, sp in zip(prompts, sampling_params):
                comps = []
                for j in range(sp.n):
                    toks, why, stop_reason, lp = self.script(req["prompt_token_ids"], sp, j)
                    comps.append(types.SimpleNamespace(index=j, text="(vllm's text, unused)", token_ids=toks,
                                                       cumulative_logprob=lp * len(toks), finish_reason=why,
                                                       stop_reason=stop_reason,
                                                       logprobs=[{t: Logprob(lp)} for t in toks]))
                outs.append(types.SimpleNamespace(prompt_token_ids=req["prompt_token_ids"], outputs=comps[::-1]))
            return outs

        def collective_rpc(self, method, timeout=None, args=(), kwargs=None):
            return [method(self.worker, *args, **(kwargs or {}))]

        def reset_prefix_cache(self):
            self.cache_resets += 1

    mod.LLM, mod.SamplingParams, mod.Logprob = LLM, SamplingParams, Logprob
    return mod


@pytest.fixture
def vllm(monkeypatch):
    """The stand-in module as `vllm`, a 'GPU', and a fresh engine cache."""
    mod = fake_vllm()
    monkeypatch.setitem(sys.modules, "vllm", mod)
    monkeypatch.setattr(vllm_backend, "_has_cuda", lambda: True)
    monkeypatch.setattr(vllm_backend, "_engines", type(vllm_backend._engines)())
    monkeypatch.setenv("VLLM_ENABLE_V1_MULTIPROCESSING", "0")
    return mod


# ----------------------------------------------------------------------------- default and errors
def test_default_backend_is_the_built_in_engine(tiny):
    from posttrain.config import RolloutConfig, resolve
    from posttrain.trainers.grpo import GRPOConfig

    assert RolloutConfig().backend == "auto" and default_backend() == "auto"
    res = resolve("tiny-countdown", "grpo", GRPOConfig, ["rollout.backend=vllm", "rollout.vllm_dtype=bfloat16"])
    assert res.rollout.backend == "vllm" and res.to_dict()["rollout"]["vllm_dtype"] == "bfloat16"
    with pytest.raises(ConfigError, match="rollout.backend"):
        resolve("tiny-countdown", "grpo", GRPOConfig, ["rollout.backend=sglang"])
    model, tok = _load(tiny)
    params = SamplingParams(n=2, max_new_tokens=6, seed=3)
    a = generate(model, tok, ["2+2=", "10-3="], params)  # backend=None: the configured default, auto
    b = generate(model, tok, ["2+2=", "10-3="], params, backend="auto")
    assert [(r.completion_ids, r.logprobs, r.finish_reason) for r in a] == \
        [(r.completion_ids, r.logprobs, r.finish_reason) for r in b]
    # importing posttrain (rollout, the adapter module, trainers, CLI) never imports vllm
    code = ("import sys, posttrain.cli, posttrain.rollout, posttrain.rollout.vllm_backend, posttrain.trainers.grpo, "
            "posttrain.trainers.ppo, posttrain.preferences, posttrain.evaluation; assert 'vllm' not in sys.modules")
    assert subprocess.run([sys.executable, "-c", code], capture_output=True).returncode == 0


def test_vllm_backend_without_vllm_or_without_a_gpu_is_one_clear_line(tiny, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "vllm", None)  # `import vllm` raises ImportError
    out = tmp_path / "runs"
    assert main(["grpo", "--recipe", "tiny-countdown", f"run.output_dir={out}", "rollout.backend=vllm"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "pip install vllm" in err and "GPU" in err, err
    assert not out.exists()  # stopped before anything ran
    model, tok = _load(tiny)
    with pytest.raises(ConfigError, match="pip install vllm"):
        generate(model, tok, ["2+2="], backend="vllm")
    real_has_cuda = vllm_backend._has_cuda
    monkeypatch.setitem(sys.modules, "vllm", fake_vllm())  # installed, but no GPU (whatever this machine has)
    monkeypatch.setattr(vllm_backend, "_has_cuda", lambda: False)
    with pytest.raises(ConfigError, match="needs a CUDA GPU"):
        configure("vllm")
    # this machine as it is: the line that fits it (vLLM missing, or no GPU), or none where both are there
    monkeypatch.delitem(sys.modules, "vllm")
    monkeypatch.setattr(vllm_backend, "_has_cuda", real_has_cuda)
    if importlib.util.find_spec("vllm") is None:
        with pytest.raises(ConfigError, match="vLLM is not installed; pip install vllm"):
            configure("vllm")
    elif not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="needs a CUDA GPU"):
            configure("vllm")
    else:
        try:
            configure("vllm")
            assert default_backend() == "vllm"
        finally:
            configure()  # the process default back to the built-in engine
    with pytest.raises(ValueError, match="rollout backend must be one of"):
        generate(model, tok, ["2+2="], backend="sglang")


# ----------------------------------------------------------------------------- the adapter
def test_adapter_maps_sampling_params_and_builds_rollout_records(tiny, vllm):
    model, tok = _load(tiny)
    eos = tok.eos_token_id
    vllm.LLM.eos_id = eos
    stop_ids = tok("hello world", add_special_tokens=False)["input_ids"]  # ends inside the stop string "world"
    long_prompt = [5] * 500  # 500 of the model's 512 positions: the budget is clipped to 12

    def script(self, prompt_ids, sp, j):
        if prompt_ids == long_prompt:
            return [7] * sp.max_tokens, "length", None, -0.5
        if j == 0:
            return [11, 12, eos], "stop", None, -0.25  # EOS
        if j == 1:
            return stop_ids, "stop", "world", -0.75  # a stop string
        return [13] * sp.max_tokens, "length", None, -1.5

    vllm.LLM.script = script
    params = SamplingParams(n=3, max_new_tokens=64, temperature=0.7, top_k=0, top_p=0.9, stop=("world",), seed=5)
    rollouts = generate(model, tok, ["2+2=", long_prompt], params, prompt_keys=[40, 41], backend="vllm")

    llm = vllm.LLM.instances[-1]
    assert llm.model == str(tiny) and llm.kwargs["gpu_memory_utilization"] == 0.3  # built from the model's directory
    (requests, sps), = llm.calls
    assert [r["prompt_token_ids"] for r in requests] == [tok("2+2=")["input_ids"], long_prompt]
    for sp, key, budget in zip(sps, (40, 41), (64, 12)):
        assert (sp.n, sp.temperature, sp.top_k, sp.top_p, sp.max_tokens, sp.stop, sp.logprobs) == \
            (3, 0.7, -1, 0.9, budget, ["world"], 0)
        assert sp.seed == vllm_backend.request_seed(5, key) and not sp.include_stop_str_in_output
    assert sps[0].seed != sps[1].seed

    assert [(r.prompt_index, r.sample_index) for r in rollouts] == [(i, j) for i in range(2) for j in range(3)]
    by = {(r.prompt_index, r.sample_index): r for r in rollouts}
    r = by[0, 0]
    assert (r.completion_ids, r.finish_reason, r.completion_mask) == ([11, 12, eos], "eos", [1, 1, 1])
    assert r.policy_logprobs == r.logprobs == [-0.25] * 3 and r.text == tok.decode([11, 12], skip_special_tokens=True)
    r = by[0, 1]
    full = tok.decode(stop_ids)
    assert (r.finish_reason, r.completion_ids, r.text) == ("stop", stop_ids, full[:full.index("world")])
    assert by[0, 2].finish_reason == "length" and len(by[0, 2].completion_ids) == 64
    assert all(by[1, j].finish_reason == "length" and len(by[1, j].completion_ids) == 12 for j in range(3))
    assert by[1, 0].prompt_ids == long_prompt and by[0, 0].prompt == "2+2="

    greedy = generate(model, tok, ["2+2="], SamplingParams(greedy=True, max_new_tokens=8, top_k=4), backend="vllm")
    sp = llm.calls[-1][1][0]
    assert (sp.temperature, sp.top_k) == (0.0, 4)
    assert greedy[0].logprobs == [0.0] * len(greedy[0].completion_ids)  # the contract: 0 for greedy
    assert greedy[0].policy_logprobs == [-0.25] * 3

    def aborted(self, prompt_ids, sp, j):
        return [11], "abort", None, -1.0

    vllm.LLM.script = aborted
    with pytest.raises(RuntimeError, match="abort"):
        generate(model, tok, ["2+2="], max_new_tokens=4, backend="vllm")


def test_weights_are_pushed_after_every_policy_update(tiny, vllm):
    model, tok = _load(tiny)
    generate(model, tok, ["2+2="], max_new_tokens=4, backend="vllm")
    llm = vllm.LLM.instances[-1]
    assert len(llm.pushes) == 1 and llm.cache_resets == 1  # the first call pushes (a resumed run's weights)
    state = model.state_dict()
    assert set(llm.pushes[0]) == set(state)  # Hugging Face checkpoint names
    assert all(torch.equal(llm.pushes[0][k], state[k]) for k in state)
    generate(model, tok, ["3+4="], max_new_tokens=4, backend="vllm")
    assert len(llm.pushes) == 1  # nothing changed: no push

    opt = torch.optim.AdamW(model.parameters(), lr=1e-2)
    ids = torch.tensor([tok("2+2=4")["input_ids"]])
    model(input_ids=ids, labels=ids).loss.backward()
    opt.step()  # a policy update
    generate(model, tok, ["2+2="], max_new_tokens=4, backend="vllm")
    assert len(llm.pushes) == 2 and llm.cache_resets == 2
    state = model.state_dict()
    assert all(torch.equal(llm.pushes[1][k], state[k]) for k in state)
    assert not torch.equal(llm.pushes[1]["model.embed_tokens.weight"], llm.pushes[0]["model.embed_tokens.weight"])
    assert len(vllm.LLM.instances) == 1  # one engine per model, reused


def test_lora_weights_are_exported_merged_without_touching_the_model(tiny):
    from posttrain.config import LoRAConfig
    from posttrain.models import apply_lora

    base, _ = _load(tiny)
    plain = {k: v.clone() for k, v in base.state_dict().items()}
    model = apply_lora(base, LoRAConfig(enabled=True, r=4, alpha=8.0))
    torch.manual_seed(0)
    for name, p in model.named_parameters():
        if "lora_B" in name:
            torch.nn.init.normal_(p, std=0.1)  # adapters away from 0, as after training
    before = {k: v.clone() for k, v in model.state_dict().items()}
    got = dict(vllm_backend.export_weights(model))
    assert set(got) == set(plain)
    merged = copy.deepcopy(model).merge_and_unload().state_dict()
    assert max(float((got[k] - merged[k]).abs().max()) for k in merged) < 1e-6
    q = "model.layers.0.self_attn.q_proj.weight"
    assert not torch.allclose(got[q], plain[q])  # the adapters are in it
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())  # the model is not modified


def test_grpo_with_the_vllm_backend_pushes_every_step_and_recomputes_pi_old(tiny, vllm, tmp_path, capsys):
    """Through the CLI: rollout.backend=vllm samples every rollout (baseline eval, steps, final eval) through the
    adapter, pushes the weights once before the first rollout and once after each step's update, and GRPO
    recomputes pi_old: the stand-in's log-probs are all -1.0, so a ratio of exactly 1 on the first pass proves
    they were not used."""
    model, tok = _load(tiny)
    vllm.LLM.eos_id = tok.eos_token_id
    out = tmp_path / "runs"
    sft = out / "tiny-countdown" / "sft" / "final"
    shutil.copytree(tiny, sft)
    assert main(["grpo", "--recipe", "tiny-countdown", f"run.output_dir={out}", "rollout.backend=vllm",
                 f"verifier={HERE.parent / 'grpo_verifiers.py'}:digits", "verifier_workers=0", "prompts_per_step=4",
                 "group_size=4", "max_new_tokens=8", "max_steps=2", "eval_every=0", "eval_rows=4",
                 "final_eval_rows=4", "save_every=0", "lr=1e-3", "task.n_train=32", "task.n_eval=8", "run.threads=1",
                 "old_logprobs=rollout", "zero_variance=keep", "run.quiet=true"]) == 0
    assert "rollouts: vllm backend (pi_old recomputed)" in capsys.readouterr().out
    llm, = vllm.LLM.instances
    assert llm.model == str(sft)
    # baseline eval (push 1), step 1 samples (same weights), step 2 samples (push 2), final eval (push 3)
    assert len(llm.calls) == 4 and len(llm.pushes) == 3
    assert any(sp.temperature == 0.0 for sp in llm.calls[0][1]) and llm.calls[1][1][0].n == 4
    from safetensors.torch import load_file

    final = load_file(out / "tiny-countdown" / "grpo" / "final" / "model.safetensors")
    assert all(torch.equal(llm.pushes[-1][k].cpu(), v) for k, v in final.items())  # vLLM ends with the trained policy
    steps = [json.loads(l) for l in (out / "tiny-countdown" / "grpo" / "metrics.jsonl").read_text().splitlines()
             if "reward/mean" in l]
    assert len(steps) == 2
    for s in steps:
        assert s["ratio_mean"] == pytest.approx(1.0, abs=1e-5) and s["ratio_max"] == pytest.approx(1.0, abs=1e-4)
        assert 0 < s["completion/length"] <= 8
