"""Every stage on a real pretrained instruct model, SmolLM2-135M-Instruct (134.5M parameters, 49k vocabulary,
ChatML template with a default system prompt), a few steps each at real size on CPU.

- the GGUF import is a plain fp32 Llama that `from_pretrained` loads without the gguf package;
- rendered prompts carry the chat template exactly once (system prompt, user turn, assistant header);
- the rollout engine's greedy output equals `model.generate` token for token, batched with left padding;
- sampling log-probs equal log-probs recomputed by `posttrain.logprobs` within 1e-4;
- SFT, prefs, RM (a scalar head on the real model), DPO, PPO (value model from the RM), GRPO, eval and
  LoRA run through the CLI; short overfits of SFT / DPO / GRPO lower their loss or raise their reward;
- `final/` loads with `from_pretrained` and generates what the engine generates.
Run it alone: `python -m pytest -m real` (~4 min on 2 Zen 4 cores after the one-off fetch; ~20 min on one xdist
worker of a Zen 1 EPYC, whose fp32 matmuls run at 39 GFLOP/s on 2 threads). It needs ~8 GiB of free disk (conftest).
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
import torch

from posttrain.cli import main

pytestmark = pytest.mark.real
HERE = Path(__file__).resolve().parent
DIGITS = HERE.parent / "posttrain" / "grpo_verifiers.py"
# both cores when the suite runs in one process (-n 0), one beside the other xdist workers (tests/conftest.py)
THREADS = f"run.threads={1 if int(os.environ.get('PYTEST_XDIST_WORKER_COUNT', '1')) > 1 else 2}"
QUESTIONS = ["What is 7 + 5?", "Name a fruit that is yellow.", "Tom has 3 apples and buys 4 more. How many now?",
             "Write one word that rhymes with cat."]


def _write(path: Path, rows: list[dict]) -> Path:
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


def _metrics(run: Path) -> list[dict]:
    return [json.loads(l) for l in (run / "metrics.jsonl").read_text().splitlines()]


def _drop_checkpoints(root: Path) -> None:
    """At real size a checkpoint is the weights plus two Adam moments (1.6 GB per model): the tests read only
    metrics and final/, so every checkpoint under `root` goes as soon as its run ends (a CI disk stays free)."""
    for ckpt in Path(root).rglob("checkpoints"):
        shutil.rmtree(ckpt, ignore_errors=True)


@pytest.fixture(scope="module")
def loaded(smol):
    from posttrain.config import ModelConfig
    from posttrain.models import load_model, load_tokenizer

    return load_model(smol), load_tokenizer(smol, ModelConfig())


def _hf_greedy(model, ids: list[int], n: int, eos: int) -> list[int]:
    x = torch.tensor([ids])
    out = model.generate(x, attention_mask=torch.ones_like(x), max_new_tokens=n, do_sample=False, eos_token_id=eos,
                         pad_token_id=eos)[0, len(ids):].tolist()
    return out[:out.index(eos) + 1] if eos in out else out


# ----------------------------------------------------------------------------- the model itself
def test_the_import_is_a_plain_fp32_llama_with_its_chat_template(smol):
    from transformers import AutoConfig, AutoModelForCausalLM, AutoTokenizer

    cfg = AutoConfig.from_pretrained(smol)
    assert cfg.model_type == "llama" and cfg.num_hidden_layers == 30 and cfg.hidden_size == 576
    assert getattr(cfg, "quantization_config", None) is None  # dropped: a plain checkpoint
    model = AutoModelForCausalLM.from_pretrained(smol)
    assert model.dtype == torch.float32 and 134e6 < sum(p.numel() for p in model.parameters()) < 135e6
    tok = AutoTokenizer.from_pretrained(smol)
    assert len(tok) == 49152 and tok.eos_token == "<|im_end|>" and "<|im_start|>" in tok.chat_template


def test_rendered_prompts_carry_the_template_exactly_once(loaded):
    from posttrain.chat import encode_prompts, render_prompt
    from posttrain.data import tokenize_completions

    _, tok = loaded
    text = render_prompt(tok, "What is 7 + 5?")
    assert text.count("<|im_start|>system\n") == 1 and text.count("<|im_start|>user\nWhat is 7 + 5?<|im_end|>") == 1
    assert text.endswith("<|im_start|>assistant\n") and text.count("<|im_start|>assistant") == 1
    ids = encode_prompts(tok, ["What is 7 + 5?"])[0]
    assert tok.decode(ids) == text  # no second BOS or template from the tokenizer itself
    (prompt, completion), = tokenize_completions([{"prompt": "What is 7 + 5?", "completion": "12"}], tok, 128)[0]
    assert prompt == ids and tok.decode(completion) == "12<|im_end|>"


def test_multi_turn_conversation_trains_the_assistant_turns_only(loaded):
    """SmolLM2's ChatML template (a default system prompt, a newline after each <|im_end|>): the SFT mask of a
    two-exchange conversation covers exactly the two replies and their <|im_end|>."""
    from posttrain.chat import encode_prompts
    from posttrain.data import collate_completions, normalize_row, tokenize_completions

    _, tok = loaded
    messages = [{"role": "user", "content": "What is 2 + 2?"}, {"role": "assistant", "content": "4"},
                {"role": "user", "content": "And 7 + 5?"}, {"role": "assistant", "content": "It is 12."}]
    row, _ = normalize_row({"messages": messages}, "sft")
    (item,), _ = tokenize_completions([row], tok, 256)
    batch = collate_completions([item], tok.pad_token_id)
    ids, trained = batch["input_ids"][0], batch["completion_mask"][0]
    assert tok.decode(ids) == tok.apply_chat_template(messages, tokenize=False).rstrip("\n")
    runs, cur = [], []
    for t, m in zip(ids.tolist(), trained.tolist()):
        if m:
            cur.append(t)
        elif cur:
            runs.append(tok.decode(cur))
            cur = []
    runs.append(tok.decode(cur))
    assert runs == ["4<|im_end|>", "It is 12.<|im_end|>"]
    assert item[0] == encode_prompts(tok, [messages[:-1]])[0]  # the prompt as generation renders it


def test_engine_greedy_equals_model_generate_token_for_token(loaded):
    from posttrain.chat import encode_prompts
    from posttrain.rollout import generate

    model, tok = loaded
    outs = generate(model, tok, QUESTIONS, greedy=True, max_new_tokens=24)  # one batch, left-padded
    for o, ids in zip(outs, encode_prompts(tok, QUESTIONS)):
        assert o.prompt_ids == ids
        assert o.completion_ids == _hf_greedy(model, ids, 24, tok.eos_token_id), (o.text, tok.decode(o.completion_ids))


@pytest.mark.parametrize("temperature", [1.0, 0.7])
def test_sampling_logprobs_equal_recomputed_ones(loaded, temperature):
    from posttrain.logprobs import batched_logprobs
    from posttrain.rollout import collate_rollouts, generate

    model, tok = loaded
    outs = generate(model, tok, QUESTIONS[:2], n=3, temperature=temperature, max_new_tokens=16, seed=0)
    batch = collate_rollouts(outs, tok.pad_token_id)
    lp, _ = batched_logprobs(model, batch, temperature=temperature)
    cm = batch.completion_mask.bool()
    torch.testing.assert_close(lp[cm], batch.logprobs[cm], atol=1e-4, rtol=0)
    raw, _ = batched_logprobs(model, batch)
    torch.testing.assert_close(raw[cm], batch.policy_logprobs[cm], atol=1e-4, rtol=0)


# ----------------------------------------------------------------------------- every stage through the CLI
@pytest.fixture(scope="module")
def chain(smol, tmp_path_factory):
    """SFT (a short overfit), then preference pairs and a reward model on the SFT model: the runs later tests use."""
    out = tmp_path_factory.mktemp("smol-runs")
    common = [f"run.output_dir={out}", f"model.path={smol}", "model.max_length=320", "run.quiet=true", THREADS,
              "task.n_train=8", "task.n_eval=8"]
    assert main(["sft", "--recipe", "tiny-summarize", *common, "max_steps=8", "batch_size=4", "lr=5e-5",
                 "warmup_steps=0", "log_every=1", "eval_every=0", "final_eval_rows=4", "max_new_tokens=32",
                 "save_every=0"]) == 0
    _drop_checkpoints(out)
    assert main(["prefs", "--recipe", "tiny-summarize", *common, "n_prompts=8", "n_eval_prompts=4",
                 "samples_per_prompt=4", "max_new_tokens=32"]) == 0
    assert main(["rm", "--recipe", "tiny-summarize", *common, "max_steps=4", "batch_size=4", "warmup_steps=0",
                 "log_every=1", "eval_every=0"]) == 0
    _drop_checkpoints(out)
    yield {"out": out, "common": common, "run": out / "tiny-summarize"}
    shutil.rmtree(out, ignore_errors=True)  # ~2 GB of models: gone with the module


@pytest.mark.learning
def test_sft_overfits_its_rows_and_final_generates_what_the_engine_does(chain, learning):
    from transformers import AutoModelForCausalLM, AutoTokenizer

    from posttrain.chat import encode_prompts
    from posttrain.models import load_model, load_tokenizer
    from posttrain.rollout import generate

    losses = [r["loss"] for r in _metrics(chain["run"] / "sft") if "loss" in r]
    learning.above("SFT loss first / last 2 (8 rows, 8 steps)", losses[0] / (sum(losses[-2:]) / 2), 1.5, losses)
    final = chain["run"] / "sft" / "final"
    hf = AutoModelForCausalLM.from_pretrained(final)
    hf_tok = AutoTokenizer.from_pretrained(final)
    assert hf_tok.chat_template == load_tokenizer(final).chat_template
    model, tok = load_model(final), load_tokenizer(final)
    ours = generate(model, tok, QUESTIONS[:2], greedy=True, max_new_tokens=20)
    for o, ids in zip(ours, encode_prompts(tok, QUESTIONS[:2])):
        assert o.completion_ids == _hf_greedy(hf, ids, 20, hf_tok.eos_token_id)


def test_prefs_and_a_reward_model_with_a_scalar_head_on_the_real_model(chain):
    from transformers import AutoModelForSequenceClassification

    pairs = chain["run"] / "prefs" / "final"
    assert pairs.exists()
    rm = AutoModelForSequenceClassification.from_pretrained(chain["run"] / "rm" / "final")
    assert rm.config.num_labels == 1 and rm.config.num_hidden_layers == 30
    rows = [r for r in _metrics(chain["run"] / "rm") if "loss" in r]
    assert len(rows) == 4 and all(r["loss"] == r["loss"] for r in rows)  # finite


@pytest.mark.learning
def test_dpo_overfits_its_pairs(chain, learning):
    pairs = chain["run"] / "prefs" / "final"
    train = next(p for p in sorted(pairs.iterdir()) if p.name.startswith("train"))
    assert main(["dpo", "--recipe", "tiny-summarize", *chain["common"], f"train_file={train}", f"eval_file={train}",
                 "online=false", "proxy_rm=none", "max_steps=6", "batch_size=4", "lr=1e-5", "warmup_steps=0",
                 "log_every=1", "eval_every=6", "eval_rows=8", "final_eval_rows=4", "max_new_tokens=32",
                 *learning.overrides]) == 0
    _drop_checkpoints(chain["run"] / "dpo")
    m = _metrics(chain["run"] / "dpo")
    shutil.rmtree(chain["run"] / "dpo" / "final")  # read nothing more: room for the next stage
    loss = [r["eval/loss"] for r in m if "eval/loss" in r]
    assert loss[0] == pytest.approx(0.6931, abs=1e-3)  # policy == reference at step 0
    learning.above("DPO loss on its pairs, step 0 - step 6", loss[0] - loss[-1], 0.05, loss)


def test_ppo_with_the_value_model_from_the_reward_model(chain):
    assert main(["ppo", "--recipe", "tiny-summarize", *chain["common"], "max_steps=2", "rollout_batch_size=4",
                 "minibatch_size=2", "ppo_epochs=1", "max_new_tokens=24", "eval_every=0", "eval_rows=4",
                 "final_eval_rows=4", "save_every=0", "reward_norm_prompts=8"]) == 0  # 8, not 128, SFT samples
    _drop_checkpoints(chain["run"] / "ppo")
    m = [r for r in _metrics(chain["run"] / "ppo") if "rollout/score" in r]
    assert len(m) == 2 and all(r["rollout/logprob_gap"] < 1e-3 for r in m)  # recomputed old log-probs == engine's
    assert (chain["run"] / "ppo" / "final" / "model.safetensors").is_file()
    shutil.rmtree(chain["run"] / "ppo")


@pytest.mark.learning
def test_grpo_raises_an_easy_reward_on_the_real_model(smol, tmp_path, learning):
    problems = [{"prompt": q, "answer": "0", "verifier": "math"} for q in ("Write a long number.", "Count from one to ten.")]
    train = _write(tmp_path / "problems.jsonl", problems)
    out = tmp_path / "runs"
    assert main(["grpo", "--recipe", "tiny-math", f"run.output_dir={out}", f"model.path={smol}", "model.start_from=base",
                 "run.quiet=true",
                 THREADS, f"train_file={train}", f"eval_file={train}", f"verifier={DIGITS}:digits",
                 "model.max_length=160", "prompts_per_step=2", "group_size=8", "max_new_tokens=24", "max_steps=6",
                 "lr=2e-5", "beta=0", "eval_every=0", "eval_rows=0", "final_eval_rows=0", "save_every=0",
                 *learning.overrides]) == 0
    _drop_checkpoints(out)
    r = [x["reward/mean"] for x in _metrics(out / "tiny-math" / "grpo") if "reward/mean" in x]
    learning.above("digit fraction, last 2 - first 2 steps", sum(r[-2:]) / 2 - sum(r[:2]) / 2, 0.05, r)


def test_the_smol_math_recipe_runs_end_to_end(smol, tmp_path, capsys):
    """`posttrain grpo --recipe smol-math` as the README shows it (shortened): the instruct model as it is, LoRA,
    bf16 rollout weights (mismatch/kl logged and small; set here, as the recipe's auto picks fp32 on CPUs without
    native bf16), the console naming the base model, final/ saved."""
    out = tmp_path / "runs"
    assert main(["grpo", "--recipe", "smol-math", f"run.output_dir={out}", f"model.path={smol}", "run.quiet=true",
                 THREADS, "rollout.dtype=bfloat16", "prompts_per_step=2", "group_size=4", "max_new_tokens=24", "max_steps=2", "eval_every=0",
                 "eval_rows=4", "final_eval_rows=4", "save_every=0", "task.n_train=16",
                 "zero_variance=keep"]) == 0  # keep: every step trains, so every step measures mismatch/kl
    _drop_checkpoints(out)
    steps = [x for x in _metrics(out / "smol-math" / "grpo") if "reward/mean" in x]
    assert len(steps) == 2 and all(0 <= s["mismatch/kl"] < 0.1 for s in steps)
    assert "held-out greedy accuracy on 4 problems: base" in capsys.readouterr().out
    assert (out / "smol-math" / "grpo" / "final" / "adapter_config.json").is_file() or \
        (out / "smol-math" / "grpo" / "final" / "model.safetensors").is_file()


def test_eval_and_lora_on_the_real_model(chain, capsys):
    from transformers import AutoModelForCausalLM

    assert main(["eval", "--recipe", "tiny-summarize", *chain["common"], "rows=4", "max_new_tokens=24"]) == 0
    assert "held-out" in capsys.readouterr().out
    out = chain["out"] / "lora"
    assert main(["sft", "--recipe", "tiny-summarize", *chain["common"], f"run.output_dir={out}", "max_steps=3",
                 "batch_size=4", "lr=1e-3", "warmup_steps=0", "log_every=1", "eval_every=0", "final_eval_rows=0",
                 "save_every=0", "lora.enabled=true", "lora.r=8"]) == 0
    _drop_checkpoints(out)
    final = out / "tiny-summarize" / "sft" / "final"
    assert not (final / "adapter_config.json").exists()  # merged: a plain model
    assert AutoModelForCausalLM.from_pretrained(final).config.num_hidden_layers == 30
    shutil.rmtree(out)


# ----------------------------------------------------------------------------- tools: multi-turn episodes (issue 35)
def test_the_tool_call_format_round_trips_through_the_chatml_template(loaded):
    """A word-calc demonstration rendered by SmolLM2's template: each rendering of a shorter conversation is a prefix
    of the longer one's (what multi-turn episodes append relies on), and the call parses back from the rendered
    text to the same name and arguments."""
    from posttrain.tasks import wordcalc
    from posttrain.verifiers.envs.base import parse_tool_calls

    _, tok = loaded
    row = wordcalc.make_examples(8, 0, "eval")[7]  # the eighth recovers from a refused call first
    messages = row["messages"]
    assert [m["role"] for m in messages][-3:] == ["assistant", "tool", "assistant"]
    renders = [tok.apply_chat_template(messages[:k], tokenize=False) for k in range(2, len(messages) + 1)]
    for short, long in zip(renders, renders[1:]):
        assert long.startswith(short)
    call = [m for m in messages if m["role"] == "assistant"][-2]["content"]
    parsed = parse_tool_calls(renders[-1][renders[-1].index(call):])[0]
    assert (parsed.error, parsed.name, parsed.arguments) == (None, "calculator", {"expression": row["meta"]["expression"]})


def test_smol_tools_trains_on_exactly_the_sampled_multi_turn_tokens(smol, tmp_path):
    """`posttrain grpo --recipe smol-tools`, shortened and in fp32: a short LoRA SFT teaches the call, two GRPO steps
    in calc-words sample episodes with tool results; the trainer's log-probs of the saved episodes (recomputed with
    the policy that sampled them: the SFT model, GRPO's adapters start at 0) equal the sampling log-probs within
    1e-4 on sampled tokens, environment tokens are masked out, mismatch/kl is ~0, and final/ reloads and calls the
    tool."""
    from posttrain.config import ModelConfig
    from posttrain.logprobs import batched_logprobs
    from posttrain.models import load_model, load_tokenizer
    from posttrain.rollout import collate_rollouts, load_rollouts
    from posttrain.rollout.multiturn import generate_episodes
    from posttrain.verifiers.envs import get_env

    out = tmp_path / "runs"
    assert main(["grpo", "--recipe", "smol-tools", f"run.output_dir={out}", f"model.path={smol}", "run.quiet=true",
                 THREADS, "run.mixed_precision=no", "rollout.dtype=float32", "task.n_train=48", "task.n_eval=8",
                 "sft.max_steps=12", "sft.batch_size=4", "sft.lr=1e-3", "sft.warmup_steps=0", "sft.final_eval_rows=0",
                 "grpo.prompts_per_step=2", "grpo.group_size=4", "grpo.max_steps=2", "grpo.eval_every=0",
                 "grpo.eval_rows=0", "grpo.final_eval_rows=0", "grpo.save_every=0", "grpo.save_rollouts_every=1",
                 "grpo.zero_variance=keep", "grpo.env_options={max_turns: 3}"]) == 0
    _drop_checkpoints(out)
    run = out / "smol-tools"
    steps = [x for x in _metrics(run / "grpo") if "reward/mean" in x]
    assert len(steps) == 2 and all(abs(s["mismatch/kl"]) < 1e-3 for s in steps), steps
    rollouts = load_rollouts(run / "grpo" / "rollouts" / "step-000001.jsonl")
    multi = [r for r in rollouts if 0 in r.completion_mask]  # episodes with environment tokens (a tool result)
    assert multi, [r.extras["episode"]["turns"] for r in rollouts]
    sft, tok = load_model(run / "sft" / "final"), load_tokenizer(run / "sft" / "final", ModelConfig())
    batch = collate_rollouts(multi, tok.pad_token_id)
    lp, _ = batched_logprobs(sft, batch, temperature=0.7)
    cm = batch.completion_mask.bool()
    torch.testing.assert_close(lp[cm], batch.logprobs[cm], atol=1e-4, rtol=0)
    assert (batch.logprobs[~cm] == 0).all()
    final = load_model(run / "grpo" / "final")
    eps = generate_episodes(final, tok, get_env("calc-words"), [{"prompt": multi[0].extras["episode"]["messages"][1]
                                                                 ["content"], "answer": "0"}], greedy=True)
    assert eps[0].extras["episode"]["turns"][0]["tool_calls"], eps[0].text
