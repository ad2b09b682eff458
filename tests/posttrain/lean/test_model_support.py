"""The model-support table (README "Model support"): which architectures the lean paths run and which fall back
to the Hugging Face forward, each row on a tiny random config built here. Every row, lean or not, must give
the same numbers: the engine's greedy tokens equal `model.generate`'s (left-padded batch), and
`sequence_logprobs` equals log_softmax of the model's own logits."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

from posttrain.lean.support import FALLBACK_REASONS, LEAN_MODEL_TYPES, lean_support
from posttrain.logprobs import sequence_logprobs

README = Path(__file__).resolve().parents[3] / "README.md"
V = 96
COMMON = dict(vocab_size=V, hidden_size=32, num_hidden_layers=2, num_attention_heads=4, max_position_embeddings=128,
              pad_token_id=0, bos_token_id=1, eos_token_id=2)


def _build(model_type: str):
    import transformers

    if model_type == "gpt2":
        cfg = transformers.GPT2Config(vocab_size=V, n_embd=32, n_layer=2, n_head=4, n_positions=128, pad_token_id=0,
                                      bos_token_id=1, eos_token_id=2)
        cls = transformers.GPT2LMHeadModel
    else:
        prefix = {"llama": "Llama", "mistral": "Mistral", "qwen2": "Qwen2", "qwen3": "Qwen3", "gemma2": "Gemma2",
                  "phi3": "Phi3"}[model_type]
        extra = {"num_key_value_heads": 2, "intermediate_size": 64}
        if model_type in ("qwen3", "gemma2"):
            extra["head_dim"] = 8
        cfg = getattr(transformers, f"{prefix}Config")(**COMMON, **extra)
        cls = getattr(transformers, f"{prefix}ForCausalLM")
    torch.manual_seed(0)
    model = cls(cfg).float().eval()
    with torch.no_grad():  # logits with a visible spread, so greedy ties cannot hide a difference
        model.get_output_embeddings().weight.mul_(20)
    return model


class _Tok:
    """Just what the engine needs from a tokenizer (ids in, ids out)."""
    pad_token_id, eos_token_id, bos_token_id = 0, 2, 1

    def decode(self, ids, skip_special_tokens=True):
        return " ".join(map(str, ids))

    def batch_decode(self, rows, skip_special_tokens=True):
        return [self.decode(r) for r in rows]


ROWS = [(t, True) for t in LEAN_MODEL_TYPES] + [(t, False) for t in FALLBACK_REASONS]


@pytest.mark.parametrize("model_type,lean", ROWS)
def test_each_row_of_the_table_takes_its_path_and_gives_the_hf_numbers(model_type, lean):
    from posttrain.rollout import generate

    model = _build(model_type)
    for mode in ("decode", "train"):
        ok, why = lean_support(model, 64, mode=mode)
        assert ok == lean, (mode, why)
        if not lean and mode == "decode":  # (train mode may stop earlier: GPT2LMHeadModel is no *ForCausalLM)
            assert FALLBACK_REASONS[model_type] in why, why
    prompts = [[1, 5, 9, 13, 17], [1, 40, 41], [1, 70, 3, 3, 8, 60, 11]]
    outs = generate(model, _Tok(), prompts, greedy=True, max_new_tokens=6)
    for o, p in zip(outs, prompts):
        x = torch.tensor([p])
        ref = model.generate(x, attention_mask=torch.ones_like(x), max_new_tokens=6, do_sample=False,
                             eos_token_id=2, pad_token_id=0)[0, len(p):].tolist()
        assert o.completion_ids == (ref[:ref.index(2) + 1] if 2 in ref else ref), model_type
    ids = torch.tensor([[0, 0, 1, 5, 9, 13], [1, 40, 41, 42, 43, 44]])
    am = (ids != 0).long()
    lp, _ = sequence_logprobs(model, ids, am)
    with torch.no_grad():
        pos = (am.cumsum(-1) - 1).clamp(min=0)
        logits = model(input_ids=ids, attention_mask=am, position_ids=pos).logits
    want = torch.log_softmax(logits.float(), -1)[:, :-1].gather(-1, ids[:, 1:, None]).squeeze(-1)
    real = (am[:, 1:] * am[:, :-1]).bool()
    torch.testing.assert_close(lp[:, 1:][real], want[real], atol=1e-5, rtol=1e-5)


def test_the_readme_table_lists_exactly_these_rows():
    text = README.read_text()
    table = text[text.index("## Model support"):]
    table = table[:table.index("\n## ", 5)]
    rows = dict(re.findall(r"^\| `(\w+)` \| (lean|Hugging Face forward)", table, flags=re.M))
    assert rows == {**{t: "lean" for t in LEAN_MODEL_TYPES}, **{t: "Hugging Face forward" for t in FALLBACK_REASONS}}
    for t, why in FALLBACK_REASONS.items():
        assert why in table, t
