"""A local Hugging Face checkpoint in place of the presets: a tiny Qwen2 with a ChatML chat template, saved to disk
here. Prompts go through its template (one BOS), SFT targets end with <|im_end|> and generation stops there, SFT /
DPO / GRPO run on it; chat_template=on without a template, bf16 on CPU; gradient checkpointing gives the same losses."""
import json
from pathlib import Path

import pytest
import torch

from posttrain.cli import main

HERE = Path(__file__).resolve().parent
CHATML = ("{{ bos_token }}{% for m in messages %}<|im_start|>{{ m['role'] }}\n{{ m['content'] }}<|im_end|>\n"
          "{% endfor %}{% if add_generation_prompt %}<|im_start|>assistant\n{% endif %}")


def _rows(n: int, seed: int) -> list[dict]:
    """Always answer "ok": a tiny model learns it (and to stop after it) in a few dozen steps."""
    return [{"prompt": f"Item {seed * 1000 + i}: is it fine?", "completion": "ok"} for i in range(n)]


def _write(path: Path, rows: list[dict]) -> Path:
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


def _tokenizer(template: str | None):
    """A byte-level BPE with ChatML specials, eos <|im_end|>, and a BOS the tokenizer adds itself (as Llama's
    does): a template that writes {{ bos_token }} as well would give two if the prompt were tokenized naively."""
    from tokenizers import processors

    from posttrain.models import train_tokenizer

    texts = [r["prompt"] + " " + r["completion"] for r in _rows(200, 0)] + ["system user assistant"] * 20
    tok = train_tokenizer(texts, vocab_size=300, model_max_length=128)
    tok.add_special_tokens({"additional_special_tokens": ["<|im_start|>", "<|im_end|>"]})
    tok.eos_token = "<|im_end|>"
    tok.backend_tokenizer.post_processor = processors.TemplateProcessing(
        single=f"{tok.bos_token} $A", special_tokens=[(tok.bos_token, tok.bos_token_id)])
    tok.chat_template = template
    return tok


def _save_qwen(out: Path, template: str | None) -> Path:
    from transformers import Qwen2Config, Qwen2ForCausalLM

    tok = _tokenizer(template)
    cfg = Qwen2Config(vocab_size=len(tok), hidden_size=64, intermediate_size=128, num_hidden_layers=2,
                      num_attention_heads=4, num_key_value_heads=2, max_position_embeddings=128,
                      tie_word_embeddings=True, bos_token_id=tok.bos_token_id, eos_token_id=tok.eos_token_id,
                      pad_token_id=tok.pad_token_id)
    torch.manual_seed(0)
    model = Qwen2ForCausalLM(cfg)
    model.generation_config.eos_token_id = tok.eos_token_id
    model.save_pretrained(out)
    tok.save_pretrained(out)
    return out


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = tmp_path_factory.mktemp("real")
    return {"qwen": _save_qwen(root / "qwen", CHATML), "plain": _save_qwen(root / "plain", None),
            "train": _write(root / "train.jsonl", _rows(64, 0)), "eval": _write(root / "eval.jsonl", _rows(16, 1)),
            "root": root}


def _sft_args(world, out: Path, *extra: str, model: str = "qwen") -> list[str]:
    return ["sft", "--recipe", "tiny-summarize", f"run.output_dir={out}", f"model.path={world[model]}",
            f"task.train_file={world['train']}", f"task.eval_file={world['eval']}", "model.max_length=64",
            "batch_size=8", "max_steps=3", "lr=3e-3", "warmup_steps=0", "log_every=1", "eval_every=0",
            "final_eval_rows=0", "save_every=0", "prompt_loss_weight=0", "run.quiet=true", "run.threads=1", *extra]


def _losses(out: Path) -> list[float]:
    rows = [json.loads(l) for l in (out / "tiny-summarize" / "sft" / "metrics.jsonl").read_text().splitlines()]
    return [r["loss"] for r in rows if "loss" in r]


@pytest.fixture(scope="module")
def sft_run(world):
    """`posttrain sft` on the Qwen directory, long enough to learn to answer "ok" and stop."""
    out = world["root"] / "runs"
    assert main(_sft_args(world, out, "max_steps=40", "lr=1e-2")) == 0
    return out


# ----------------------------------------------------------------------------- (a) rendering, one BOS
def test_prompts_are_rendered_by_the_template_with_one_bos(world):
    from posttrain.chat import encode_prompts, render_prompt
    from posttrain.config import ModelConfig
    from posttrain.models import load_tokenizer

    tok = load_tokenizer(world["qwen"], ModelConfig(path=str(world["qwen"])))
    text = render_prompt(tok, "Is it fine?")
    assert text == "<|bos|><|im_start|>user\nIs it fine?<|im_end|>\n<|im_start|>assistant\n"
    ids = encode_prompts(tok, ["Is it fine?"])[0]
    assert ids == tok(text, add_special_tokens=False)["input_ids"]
    assert ids[0] == tok.bos_token_id and ids.count(tok.bos_token_id) == 1
    assert tok(text)["input_ids"][:2] == [tok.bos_token_id] * 2  # what naive tokenization would have done
    assert tok.decode(ids) == text
    # no template: the plain prompt with the tokenizer's own BOS, as before
    plain = load_tokenizer(world["plain"], ModelConfig(path=str(world["plain"])))
    assert render_prompt(plain, "Is it fine?") == "Is it fine?"
    assert encode_prompts(plain, ["Is it fine?"])[0] == plain("Is it fine?")["input_ids"]
    # off: the template is dropped (and a saved model would carry none)
    off = load_tokenizer(world["qwen"], ModelConfig(path=str(world["qwen"]), chat_template="off"))
    assert off.chat_template is None and render_prompt(off, "Is it fine?") == "Is it fine?"


def test_a_system_prompt_is_written_into_the_template_once(world):
    from posttrain.chat import render_prompt
    from posttrain.config import ModelConfig
    from posttrain.models import load_tokenizer

    sp = 'Answer "ok".\nBe brief \\ naïve'
    tok = load_tokenizer(world["qwen"], ModelConfig(path=str(world["qwen"]), system_prompt=sp))
    assert render_prompt(tok, "Q?") == f"<|bos|><|im_start|>system\n{sp}<|im_end|>\n<|im_start|>user\nQ?<|im_end|>\n" \
                                       "<|im_start|>assistant\n"
    tok.save_pretrained(world["root"] / "with_system")  # a later stage loads it back and sets it again: replaced
    again = load_tokenizer(world["root"] / "with_system", ModelConfig(system_prompt="Other."))
    assert render_prompt(again, "Q?").count("<|im_start|>system") == 1 and "Other." in render_prompt(again, "Q?")
    kept = load_tokenizer(world["root"] / "with_system", ModelConfig())  # null: what the saved template says
    assert sp in render_prompt(kept, "Q?")


# ----------------------------------------------------------------------------- (b) SFT, (d) generation stops
def test_sft_on_a_model_directory_trains_on_rendered_prompts_ending_with_im_end(world, sft_run):
    from posttrain.models import load_model, load_tokenizer
    from posttrain.data import tokenize_completions

    losses = _losses(sft_run)
    assert len(losses) == 40 and losses[-1] < 0.2 * losses[0], losses
    final = sft_run / "tiny-summarize" / "sft" / "final"
    model, tok = load_model(final), load_tokenizer(final)
    assert type(model).__name__ == "Qwen2ForCausalLM" and tok.chat_template is not None
    pairs, dropped = tokenize_completions(_rows(4, 2), tok, 64)
    assert dropped == 0
    im_end = tok.convert_tokens_to_ids("<|im_end|>")
    for (p, c), row in zip(pairs, _rows(4, 2)):
        assert c[-1] == im_end == tok.eos_token_id and tok.decode(c) == "ok<|im_end|>"
        assert tok.decode(p) == f"<|bos|><|im_start|>user\n{row['prompt']}<|im_end|>\n<|im_start|>assistant\n"
        assert p.count(tok.bos_token_id) == 1


def test_rollouts_stop_at_im_end(sft_run):
    from posttrain.chat import encode_prompts
    from posttrain.models import load_model, load_tokenizer
    from posttrain.rollout import generate

    final = sft_run / "tiny-summarize" / "sft" / "final"
    model, tok = load_model(final), load_tokenizer(final)
    prompts = [r["prompt"] for r in _rows(4, 3)]
    outs = generate(model, tok, prompts, greedy=True, max_new_tokens=16)
    im_end = tok.convert_tokens_to_ids("<|im_end|>")
    for o, ids in zip(outs, encode_prompts(tok, prompts)):
        assert o.prompt_ids == ids  # the engine prompts with the rendered template
        assert o.finish_reason == "eos" and o.completion_ids[-1] == im_end, o
        assert len(o.completion_ids) < 16 and o.text == "ok"


# ----------------------------------------------------------------------------- (c) DPO and GRPO on it
def test_dpo_runs_on_the_sft_model_of_a_directory(world, sft_run):
    pairs = [{"prompt": r["prompt"], "chosen": "ok", "rejected": "no it is not"} for r in _rows(16, 4)]
    train = _write(world["root"] / "pairs.jsonl", pairs)
    assert main(["dpo", "--recipe", "tiny-summarize", f"run.output_dir={sft_run}", f"model.path={world['qwen']}",
                 f"train_file={train}", f"eval_file={train}", "model.max_length=64", "batch_size=8", "max_steps=2",
                 "warmup_steps=0", "log_every=1", "eval_every=0", "eval_rows=0", "final_eval_rows=0",
                 "proxy_rm=none", "online=false", "lr=1e-3", "run.quiet=true", "run.threads=1"]) == 0
    rows = [json.loads(l) for l in (sft_run / "tiny-summarize" / "dpo" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows if "loss" in r] == [1, 2]
    assert (sft_run / "tiny-summarize" / "dpo" / "final" / "chat_template.jinja").is_file()


def test_grpo_runs_on_the_sft_model_of_a_directory(world, sft_run):
    from posttrain.chat import encode_prompts
    from posttrain.models import load_tokenizer
    from posttrain.rollout import load_rollouts

    problems = [{"prompt": r["prompt"], "answer": "ok", "verifier": "math"} for r in _rows(16, 5)]
    train = _write(world["root"] / "problems.jsonl", problems)
    assert main(["grpo", "--recipe", "tiny-summarize", f"run.output_dir={sft_run}", f"model.path={world['qwen']}",
                 f"train_file={train}", f"eval_file={train}", f"verifier={HERE / 'grpo_verifiers.py'}:digits",
                 "zero_variance=keep", "model.max_length=64", "prompts_per_step=2", "group_size=4",
                 "max_new_tokens=8", "max_steps=2", "eval_every=0", "eval_rows=0", "final_eval_rows=0",
                 "save_every=0", "save_rollouts_every=1", "lr=1e-3", "run.quiet=true", "run.threads=1"]) == 0
    run = sft_run / "tiny-summarize" / "grpo"
    assert (run / "final" / "chat_template.jinja").is_file()
    tok = load_tokenizer(run / "final")
    rollouts = load_rollouts(run / "rollouts" / "step-000001.jsonl")
    rendered = encode_prompts(tok, [p["prompt"] for p in problems])
    assert len(rollouts) == 8
    for r in rollouts:
        assert r.prompt_ids in rendered  # GRPO samples from the rendered prompts
        if r.finish_reason == "eos":
            assert r.completion_ids[-1] == tok.eos_token_id == tok.convert_tokens_to_ids("<|im_end|>")
    assert sum(r.finish_reason == "eos" for r in rollouts) >= 4  # the SFT model stops at <|im_end|>


# ----------------------------------------------------------------------------- (e) (f) clear errors
def test_chat_template_on_without_a_template_names_the_directory(world, tmp_path, capsys):
    assert main(_sft_args(world, tmp_path, "model.chat_template=on", model="plain")) == 2
    err = capsys.readouterr().err
    assert "model.chat_template=on" in err and str(world["plain"]) in err and "no chat template" in err
    assert len(err.strip().splitlines()) == 1
    # YAML reads a bare off as false: the key still takes it, and the run trains on plain prompts
    assert main(_sft_args(world, tmp_path / "off", "model.chat_template=off", "max_steps=1")) == 0
    assert (tmp_path / "off" / "tiny-summarize" / "sft" / "config.yaml").read_text().count("chat_template: 'off'") == 1
    assert not (tmp_path / "off" / "tiny-summarize" / "sft" / "final" / "chat_template.jinja").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="the half dtypes are allowed when a GPU is present")
def test_bf16_on_cpu_is_a_clear_error(world, tmp_path, capsys):
    from posttrain.models import ModelError, load_model

    assert main(_sft_args(world, tmp_path, "model.dtype=bfloat16")) == 2
    err = capsys.readouterr().err
    assert "model.dtype=bfloat16" in err and "CPU" in err and "float32" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "tiny-summarize").exists()  # stopped before anything ran
    with pytest.raises(ModelError, match="model.dtype=float16"):
        load_model(world["qwen"], "float16")
    assert main(_sft_args(world, tmp_path, "model.dtype=float64")) == 2
    assert "model.dtype" in capsys.readouterr().err


# ----------------------------------------------------------------------------- (g) gradient checkpointing
@pytest.mark.parametrize("lora", [False, True], ids=["full", "lora"])
def test_gradient_checkpointing_gives_the_same_losses(world, tmp_path, monkeypatch, lora):
    import transformers.modeling_utils as mu

    calls = []
    real = mu.checkpoint

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(mu, "checkpoint", counting)
    extra = ["lora.enabled=true", "lora.r=4", "lr=3e-2"] if lora else []
    assert main(_sft_args(world, tmp_path / "plain", *extra)) == 0
    assert not calls
    assert main(_sft_args(world, tmp_path / "ckpt", "model.gradient_checkpointing=true", *extra)) == 0
    assert len(calls) >= 3 * 2  # every decoder layer, every step: it was really on
    plain, ckpt = _losses(tmp_path / "plain"), _losses(tmp_path / "ckpt")
    assert len(plain) == 3 and plain[2] != plain[0]  # the weights moved: gradients flowed
    assert ckpt == pytest.approx(plain, abs=1e-5), (plain, ckpt)
