"""The GPU path (marked `cuda`: skipped without a CUDA GPU, tests/conftest.py): log-probs and SFT's loss of a model on
the GPU given a batch still on the host, the same numbers as on the CPU; the rollout engine's greedy tokens on the GPU
equal the CPU's; one `posttrain sft` step with bf16 weights on the GPU. `scripts/gpu_check.py` covers every stage
and the speed; these are the small checks that run with the suite."""
from __future__ import annotations

import json
import math

import pytest
import torch
from safetensors.torch import load_file

from posttrain.chat import encode_prompts
from posttrain.cli import main
from posttrain.logprobs import nll_sum, sequence_logprobs
from posttrain.models import load_model, load_tokenizer
from posttrain.rollout import generate
from posttrain.tasks import summarize

pytestmark = [pytest.mark.cuda, pytest.mark.usefixtures("one_thread")]


@pytest.fixture(scope="module")
def models(tiny_lm):
    """The tiny preset (random init, a tokenizer trained on tiny-summarize) on the CPU and on the GPU, fp32, its
    head scaled up so log-probs are far from uniform (and greedy picks are far from ties)."""
    path = tiny_lm("tiny-summarize")
    cpu = load_model(path, "float32").eval()
    with torch.no_grad():
        cpu.lm_head.weight.mul_(20)  # tied: the embeddings too, on both copies
    gpu = load_model(path, "float32", device="cuda").eval()
    gpu.load_state_dict(cpu.state_dict())
    return cpu, gpu, load_tokenizer(path)


def _batch(tok, n: int = 6) -> dict[str, torch.Tensor]:
    """Host tensors: left-padded prompt + completion rows, completion_mask on the completion."""
    rows = summarize.make_examples(n, 0, "eval")
    prompts = encode_prompts(tok, [r["prompt"] for r in rows])
    completions = [tok(r["completion"], add_special_tokens=False)["input_ids"][:12] for r in rows]
    T = max(len(p) + len(c) for p, c in zip(prompts, completions))
    ids = torch.full((n, T), tok.pad_token_id, dtype=torch.long)
    am, cm = torch.zeros(n, T, dtype=torch.long), torch.zeros(n, T, dtype=torch.long)
    for i, (p, c) in enumerate(zip(prompts, completions)):
        start = T - len(p) - len(c)
        ids[i, start:] = torch.tensor(p + c)
        am[i, start:] = 1
        cm[i, T - len(c):] = 1
    return {"input_ids": ids, "attention_mask": am, "completion_mask": cm}


def test_logprobs_and_sft_loss_on_the_gpu_from_a_host_batch_equal_the_cpu(models):
    cpu, gpu, tok = models
    batch = _batch(tok)
    with torch.no_grad():
        want, _ = sequence_logprobs(cpu, batch["input_ids"], batch["attention_mask"], batch["completion_mask"])
        got, _ = sequence_logprobs(gpu, batch["input_ids"], batch["attention_mask"], batch["completion_mask"])
    assert got.device.type == "cuda" and got.shape == want.shape
    torch.testing.assert_close(got.cpu(), want, atol=1e-4, rtol=1e-4)
    assert float(want[batch["completion_mask"].bool()].mean()) < -0.5  # not a trivial comparison
    loss_cpu, weight_cpu = nll_sum(cpu, batch)
    loss_gpu, weight_gpu = nll_sum(gpu, batch)  # the batch is still on the host
    assert float(weight_gpu) == float(weight_cpu) == float(batch["completion_mask"].sum())
    assert float(loss_gpu.detach()) == pytest.approx(float(loss_cpu.detach()), rel=1e-4)
    loss_gpu.backward()  # differentiable on the GPU
    assert gpu.lm_head.weight.grad is not None and gpu.lm_head.weight.grad.device.type == "cuda"
    gpu.zero_grad(set_to_none=True)


def test_engine_greedy_tokens_on_the_gpu_equal_the_cpu(models):
    cpu, gpu, tok = models
    prompts = [r["prompt"] for r in summarize.make_examples(16, 1, "eval")]
    a = generate(cpu, tok, prompts, greedy=True, max_new_tokens=24)
    b = generate(gpu, tok, prompts, greedy=True, max_new_tokens=24)
    same = sum(x.completion_ids == y.completion_ids for x, y in zip(a, b))
    # fp32 on both; a near-tie of the top two logits (~1e-6 apart) may flip one row's later tokens, not more
    assert same >= 15, [(x.completion_ids, y.completion_ids) for x, y in zip(a, b) if x.completion_ids != y.completion_ids]
    assert [x.completion_ids[:1] for x in a] == [y.completion_ids[:1] for y in b]
    assert all(len(y.policy_logprobs) == len(y.completion_ids) for y in b)


def test_one_sft_step_with_bf16_weights_on_the_gpu(tiny_lm, tmp_path):
    out = tmp_path / "runs"
    assert main(["sft", "--recipe", "tiny-summarize", f"model.path={tiny_lm('tiny-summarize')}",
                 "model.dtype=bfloat16", f"run.output_dir={out}", "run.quiet=true", "max_steps=2", "batch_size=8",
                 "log_every=1", "eval_every=0", "final_eval_rows=0", "save_every=0", "warmup_steps=0",
                 "task.n_train=64", "task.n_eval=8"]) == 0
    run = out / "tiny-summarize" / "sft"
    losses = [r["loss"] for r in map(json.loads, (run / "metrics.jsonl").read_text().splitlines()) if "loss" in r]
    assert len(losses) == 2 and all(math.isfinite(x) and x > 0 for x in losses)
    weights = load_file(run / "final" / "model.safetensors")
    assert {w.dtype for w in weights.values()} == {torch.bfloat16}  # trained and saved in bf16
