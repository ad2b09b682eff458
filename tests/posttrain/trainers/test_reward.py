"""Reward model on a tiny synthetic preference set: it learns (held-out pair accuracy), reloads as a HF dir, bad rows."""
import json
import shutil
from pathlib import Path

import pytest
import torch

from posttrain.cli import main
from posttrain.tasks import summarize


def _pairs(n: int, seed: int, split: str) -> list[dict]:
    """chosen: the concise summary; rejected: the same plus a filler sentence (learnable from the text alone)."""
    rows = summarize.make_examples(n, seed, split)
    fillers = [" The weather was warm that day.", " People in the town were glad.", " It likes to sing at night."]
    return [{"prompt": r["prompt"], "chosen": " " + r["meta"]["concise_summary"],
             "rejected": " " + r["meta"]["concise_summary"] + fillers[i % 3]} for i, r in enumerate(rows)]


@pytest.fixture(scope="module")
def world(tmp_path_factory, tiny_lm, write_jsonl):
    root = tmp_path_factory.mktemp("rm")
    return {"root": root, "sft": tiny_lm("tiny-summarize", max_length=256), "train": write_jsonl(root / "train.jsonl", _pairs(192, 0, "train")),
            "eval": write_jsonl(root / "eval.jsonl", _pairs(48, 0, "eval"))}


def _args(world, out: Path, *extra: str, train: Path | None = None) -> list[str]:
    sft = out / "tiny-summarize" / "sft" / "final"
    if not sft.exists():
        sft.parent.mkdir(parents=True, exist_ok=True)
        shutil.copytree(world["sft"], sft)
    return ["rm", "--recipe", "tiny-summarize", f"run.output_dir={out}", f"train_file={train or world['train']}",
            f"eval_file={world['eval']}", "batch_size=16", "warmup_steps=2", "log_every=5", "run.quiet=true",
            "run.threads=1", *extra]


@pytest.mark.learning
def test_reward_model_learns_and_reloads_as_a_hf_directory(world, tmp_path, learning):
    from transformers import AutoModelForSequenceClassification, AutoTokenizer

    from posttrain.scoring import RewardModelScorer, rm_token_ids

    out = tmp_path / "rm"
    assert main(_args(world, out, "max_steps=16", "lr=3e-3", "batch_size=8", "eval_every=8", *learning.overrides)) == 0
    run = out / "tiny-summarize" / "rm"
    ev = json.loads((run / "eval.json").read_text())["heldout"]
    learning.above("held-out pair accuracy", ev["eval/accuracy"], 0.85, ev)  # 48 pairs, prompts never trained on
    rows = [json.loads(l) for l in (run / "metrics.jsonl").read_text().splitlines()]
    assert any("eval/accuracy" in r and r["step"] == 8 for r in rows) and any("accuracy" in r for r in rows)

    # a plain transformers load scores like the scorer (and like the trainer's held-out numbers)
    model = AutoModelForSequenceClassification.from_pretrained(run / "final")
    tok = AutoTokenizer.from_pretrained(run / "final")
    held = [json.loads(l) for l in world["eval"].read_text().splitlines()][:8]
    scorer = RewardModelScorer(run / "final", batch_size=3)
    for side in ("chosen", "rejected"):
        prompts, comps = [r["prompt"] for r in held], [r[side] for r in held]
        ours = scorer.score(prompts, comps).rewards
        with torch.no_grad():
            plain = [float(model(torch.tensor([ids])).logits[0, 0]) for ids in rm_token_ids(tok, prompts, comps)]
        assert ours == pytest.approx(plain, abs=1e-4), side
    wins = [c > r for c, r in zip(scorer.score([h["prompt"] for h in held], [h["chosen"] for h in held]).rewards,
                                  scorer.score([h["prompt"] for h in held], [h["rejected"] for h in held]).rewards)]
    learning.above("scorer wins of 8 held-out pairs", sum(wins), 5.5)


def test_reward_model_bad_rows(world, tmp_path, capsys, write_jsonl):
    rows = _pairs(40, 1, "train")
    rows[7]["chosen"] = rows[7]["rejected"]
    bad = write_jsonl(tmp_path / "bad.jsonl", rows)
    assert main(_args(world, tmp_path / "a", "max_steps=1", train=bad)) == 2
    assert f"{bad}: row 8: field 'rejected': identical to 'chosen'" in capsys.readouterr().err
    assert main(_args(world, tmp_path / "b", "max_steps=1", "on_bad_rows=skip", train=bad)) == 0
    assert "skipped 1 bad row" in capsys.readouterr().out


def test_resume_continues_exactly(world, tmp_path):
    """6 steps in one go == 3 steps, then resume=true to 6: same final weights (data order, optimizer,
    scheduler and RNG all restored from the checkpoint)."""
    from safetensors.torch import load_file

    common = ("batch_size=8", "schedule=constant", "lr=1e-3", "eval_every=0")
    full, cut = tmp_path / "full", tmp_path / "cut"
    assert main(_args(world, full, "max_steps=6", *common)) == 0
    assert main(_args(world, cut, "max_steps=3", "save_every=3", *common)) == 0
    assert main(_args(world, cut, "max_steps=6", "resume=true", *common)) == 0
    a = load_file(full / "tiny-summarize" / "rm" / "final" / "model.safetensors")
    b = load_file(cut / "tiny-summarize" / "rm" / "final" / "model.safetensors")
    assert a.keys() == b.keys()
    for k in a:
        assert torch.allclose(a[k], b[k], atol=1e-5), k
