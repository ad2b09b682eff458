"""Fixtures of the rollout tests that compare decoding paths (test_half_precision.py, test_static_decode.py).

- `trained_lm` (module scope): (model, tokenizer, prompts): the tiny preset trained for a few seconds on templated
  sentences until its greedy text is varied (healthy top-2 margins, EOS emitted), as test_rollout.py's `trained`.
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
