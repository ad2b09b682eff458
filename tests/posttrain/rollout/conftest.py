"""Fixtures of the rollout tests that compare decoding paths (test_half_precision.py, test_static_decode.py).

- `trained_lm` (module scope): (model, tokenizer, prompts): the tiny preset trained for a few seconds on templated
  sentences until its greedy text is varied (healthy top-2 margins, EOS emitted); test_rollout.py's `trained`.
- `small_llama(kind, device="cpu", dtype=torch.float32)`: a 2-layer random model: Llama with GQA ("llama-gqa"), with
  linear-scaled RoPE too ("llama-gqa-scaled-rope"), Mistral ("mistral") or Qwen2 with q/k/v biases ("qwen2"), weights
  scaled up for larger activations than the init, in eval mode.
"""
from __future__ import annotations

import random

import pytest
import torch

NAMES = "anna bob carl dora eve finn gus hana ivan jade".split()
COLORS = "red blue green pink gold gray".split()
THINGS = "cats dogs boats kites lamps maps".split()


def _sentence(rng: random.Random) -> str:
    return (f"{rng.choice(NAMES)} likes {rng.choice(COLORS)} {rng.choice(THINGS)} and "
            f"{rng.choice(NAMES)} has {rng.randint(2, 99)} {rng.choice(THINGS)}.")


@pytest.fixture(scope="module")
def trained_lm():
    from posttrain.models import build_model, train_tokenizer
    from posttrain.rollout import generate

    rng = random.Random(0)
    corpus = [" ".join(_sentence(rng) for _ in range(3)) for _ in range(200)]
    tok = train_tokenizer(corpus, vocab_size=256)
    model = build_model("tiny", tok, seed=0)
    data = torch.tensor([(tok(c)["input_ids"] + [tok.eos_token_id])[:40] for c in corpus])
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2)
    g = torch.Generator().manual_seed(0)
    prompts = [_sentence(rng)[: rng.randint(4, 30)] for _ in range(6)]
    for step in range(1, 601):
        model.train()
        batch = data[torch.randint(0, len(data), (16,), generator=g)]
        loss = model(input_ids=batch, labels=batch).loss
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step >= 60 and step % 20 == 0:
            model.eval()
            out = generate(model, tok, prompts, greedy=True, max_new_tokens=24)
            if sum(len(set(r.completion_ids)) > 3 for r in out) >= 4:
                break
    else:
        raise AssertionError("the fixture model's greedy text stayed degenerate after 600 steps")
    model.eval()
    return model, tok, prompts


def _small_llama(kind: str, device: str = "cpu", dtype: torch.dtype = torch.float32):
    from transformers import LlamaConfig, LlamaForCausalLM, MistralConfig, MistralForCausalLM, Qwen2Config, \
        Qwen2ForCausalLM

    common = dict(vocab_size=97, hidden_size=64, intermediate_size=128, num_hidden_layers=2, num_attention_heads=4,
                  max_position_embeddings=128, pad_token_id=0, eos_token_id=1, bos_token_id=2)
    if kind == "llama-gqa":
        cfg, cls = LlamaConfig(num_key_value_heads=2, **common), LlamaForCausalLM
    elif kind == "llama-gqa-scaled-rope":
        cfg = LlamaConfig(num_key_value_heads=2, rope_parameters={"rope_type": "linear", "factor": 2.0,
                                                                 "rope_theta": 500.0}, **common)
        cls = LlamaForCausalLM
    elif kind == "mistral":
        cfg, cls = MistralConfig(num_key_value_heads=2, sliding_window=None, **common), MistralForCausalLM
    else:  # qwen2: q/k/v biases
        cfg, cls = Qwen2Config(num_key_value_heads=4, **common), Qwen2ForCausalLM
    torch.manual_seed(0)
    model = cls(cfg).eval()
    with torch.no_grad():
        for p in model.parameters():
            p.mul_(10.0 if p.dim() == 1 and p.numel() != 64 else 3.0)  # larger activations than the init
    return model.to(device, dtype)


@pytest.fixture
def small_llama():
    return _small_llama
