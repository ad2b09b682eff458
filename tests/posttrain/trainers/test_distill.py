"""On-policy distillation on tiny models: the student's reverse KL to a sharp teacher falls; a student equal to its
teacher has zero loss; GKD's lambda = 0 trains on the teacher's samples; the verifier-reward term; resume; one
tokenizer for both (a clear error otherwise); bad settings are config errors; the whole chain from nothing with a
teacher of another size."""
import json
import shutil
from pathlib import Path

import pytest
import torch

from posttrain.cli import main

HERE = Path(__file__).resolve().parent
VERIFIERS = HERE.parent / "grpo_verifiers.py"


@pytest.fixture(scope="module")
def student(tiny_lm):
    """A random tiny model with a countdown tokenizer: the 'SFT model' the stage starts from."""
    return tiny_lm("tiny-countdown", vocab_size=256, max_length=128, split_digits=True)


@pytest.fixture(scope="module")
def sharp_teacher(student, tmp_path_factory):
    """Another random init of the same shape and tokenizer, its final norm x 6: peaked next-token distributions
    far from the student's (the final norm feeds only the head, so the inputs are untouched)."""
    from posttrain.models import build_model, load_tokenizer, save_model

    tok = load_tokenizer(student)
    model = build_model("tiny", tok, seed=123)
    with torch.no_grad():
        model.model.norm.weight.mul_(6.0)
    return save_model(model, tok, tmp_path_factory.mktemp("teacher") / "model")


def _args(student: Path, out: Path, teacher: Path, *extra: str) -> list[str]:
    sft = out / "tiny-countdown" / "sft" / "final"
    if not sft.exists():
        sft.parent.mkdir(parents=True, exist_ok=True)
        shutil.copytree(student, sft)  # the stage finds its "SFT model" and never runs SFT
    return ["distill", "--recipe", "tiny-countdown", f"run.output_dir={out}", f"teacher={teacher}",
            "prompts_per_step=4", "group_size=2", "max_new_tokens=12", "max_steps=2", "eval_every=0", "eval_rows=8",
            "final_eval_rows=8", "save_every=0", "lr=1e-3", "task.n_train=64", "task.n_eval=16", "run.quiet=true",
            "run.threads=1", *extra]


def _steps(out: Path) -> list[dict]:
    rows = [json.loads(l) for l in (out / "tiny-countdown" / "distill" / "metrics.jsonl").read_text().splitlines()]
    return [r for r in rows if "kl/reverse" in r]


@pytest.mark.learning
def test_the_students_reverse_kl_to_a_sharp_teacher_falls(student, sharp_teacher, tmp_path, learning):
    out = tmp_path / "learn"
    assert main(_args(student, out, sharp_teacher, "max_steps=20", *learning.overrides)) == 0
    kl = [r["kl/reverse"] for r in _steps(out)]
    assert len(kl) == 20 and all(k > 0 for k in kl)
    first, last = sum(kl[:3]) / 3, sum(kl[-3:]) / 3
    learning.above("reverse KL, first 3 / last 3 steps", first / last, 1.5, kl)  # seeds 0-3 x 1, 2 threads: 1.82-2.04
    run = out / "tiny-countdown" / "distill"
    ev = json.loads((run / "eval.json").read_text())
    assert {"sft", "distill", "teacher"} <= set(ev) and "eval/accuracy" in ev["teacher"]
    assert (run / "final" / "model.safetensors").is_file()
    from huggingface_hub import ModelCard

    card = ModelCard.load(run / "final" / "README.md")  # the model card the CLI writes
    assert "distill" in card.data.tags and "posttrain distill --recipe tiny-countdown" in card.text


def test_a_student_equal_to_its_teacher_has_zero_loss_for_every_divergence(student, tmp_path):
    for loss in ("reverse_kl", "forward_kl", "jsd"):
        out = tmp_path / loss
        assert main(_args(student, out, student, f"loss={loss}", "max_steps=1", "final_eval_rows=0",
                          "eval_rows=0")) == 0
        (s,) = _steps(out)
        assert s["loss"] == pytest.approx(0.0, abs=1e-6) and s["kl/reverse"] == pytest.approx(0.0, abs=1e-6)
        assert s["kl/forward"] == pytest.approx(0.0, abs=1e-6) and s["nll"] > 0 and s["samples/student"] == 1.0
        assert s["mismatch/kl"] == pytest.approx(0.0, abs=1e-6)  # the loss's student log-probs are the sampler's
        assert s["mismatch/max_ratio"] == pytest.approx(1.0, abs=1e-4) and s["tokens/trained"] == s["tokens/generated"]


def test_lambda_zero_trains_on_the_teachers_samples_and_the_reward_term(student, sharp_teacher, tmp_path, capsys):
    out = tmp_path / "seqkd"
    assert main(_args(student, out, sharp_teacher, "student_fraction=0", "loss=nll", "max_steps=6",
                      "final_eval_rows=0", "eval_rows=0", "run.quiet=false")) == 0
    steps = _steps(out)
    assert [s["samples/student"] for s in steps] == [0.0] * 6
    assert not any("mismatch/kl" in s for s in steps)  # the teacher sampled: no student sampler to compare with
    assert all(s["loss"] == pytest.approx(s["nll"], rel=1e-5) for s in steps)  # the loss IS the sampled-token NLL
    assert steps[-1]["nll"] < steps[0]["nll"]  # SFT on a sharp teacher's samples: they are easy to fit
    assert "nll on the teacher's samples" in capsys.readouterr().out
    out = tmp_path / "reward"
    assert main(_args(student, out, sharp_teacher, f"verifier={VERIFIERS}:digits", "reward_weight=0.5",
                      "group_size=4", "final_eval_rows=0", "eval_rows=0")) == 0
    for s in _steps(out):
        assert "pg_loss" in s and "reward/mean" in s and s["zero_var_frac"] <= 1.0


def test_resume_continues_exactly(student, sharp_teacher, tmp_path):
    from safetensors.torch import load_file

    straight = tmp_path / "straight"
    assert main(_args(student, straight, sharp_teacher, "max_steps=3", "final_eval_rows=0", "eval_rows=0")) == 0
    resumed = tmp_path / "resumed"
    assert main(_args(student, resumed, sharp_teacher, "max_steps=2", "save_every=1", "final_eval_rows=0",
                      "eval_rows=0")) == 0
    assert main(_args(student, resumed, sharp_teacher, "max_steps=3", "resume=true", "final_eval_rows=0",
                      "eval_rows=0")) == 0
    a = load_file(straight / "tiny-countdown" / "distill" / "final" / "model.safetensors")
    b = load_file(resumed / "tiny-countdown" / "distill" / "final" / "model.safetensors")
    for k in a:
        assert torch.allclose(a[k], b[k], atol=1e-5), k
    assert [r["step"] for r in _steps(resumed)] == [1, 2, 3]
    assert [s["kl/reverse"] for s in _steps(straight)] == pytest.approx([s["kl/reverse"] for s in _steps(resumed)])


def test_the_teacher_must_share_the_students_tokenizer(student, tiny_lm, tmp_path, capsys):
    other = tiny_lm("tiny-summarize", max_length=256)  # the same preset, a tokenizer trained on another task
    assert main(_args(student, tmp_path / "o", other)) == 2
    err = capsys.readouterr().err
    assert "has another tokenizer than the student" in err and "must share one tokenizer" in err
    assert not (tmp_path / "o" / "tiny-countdown" / "distill").exists()  # stopped before the run dir changed


@pytest.mark.parametrize("extra, message", [
    (["reward_weight=1", "group_size=1"], "group_size >= 2"),
    (["loss=jsd", "jsd_beta=1"], "jsd_beta"),
    (["student_fraction=1.5"], "student_fraction"),
    (["teacher_model=small"], "teacher STAGE"),
    (["reward_weight=1", "verifier=none"], "needs a verifier"),
    (["loss=tv"], "loss"),
])
def test_bad_settings_are_config_errors(student, sharp_teacher, tmp_path, capsys, extra, message):
    assert main(_args(student, tmp_path / "bad", sharp_teacher, *extra)) == 2
    assert message in capsys.readouterr().err


def test_a_teacher_path_that_is_no_model_is_named(student, tmp_path, capsys):
    assert main(_args(student, tmp_path / "x", tmp_path / "nowhere")) == 2
    assert "distill.teacher" in capsys.readouterr().err


@pytest.mark.slow
def test_from_nothing_with_a_teacher_of_another_size(tmp_path, write_jsonl):
    """`posttrain distill` on a fresh run directory: the student's base model and SFT, the teacher's base model
    (another preset) and SFT in its own run tree, then distillation; one tokenizer, trained on the same task."""
    recipe = tmp_path / "mini.yaml"
    recipe.write_text(
        "task: {name: tiny-countdown, n_train: 64, n_eval: 16}\n"
        "model: {vocab_size: 256, max_length: 128, split_digits: true}\n"
        "sft: {max_steps: 4, batch_size: 8, eval_every: 0, save_every: 0, final_eval_rows: 0, max_new_tokens: 8}\n"
        "distill: {teacher: sft, teacher_model: small, prompts_per_step: 4, max_new_tokens: 8, max_steps: 2,\n"
        "          eval_every: 0, eval_rows: 4, final_eval_rows: 4, save_every: 0}\n")
    out = tmp_path / "runs"
    assert main(["distill", "--recipe", str(recipe), f"run.output_dir={out}", "run.quiet=true", "run.threads=1"]) == 0
    teacher = out / "model-small" / "mini" / "sft" / "final"
    assert json.loads((teacher / "config.json").read_text())["hidden_size"] == 384  # the small preset
    assert json.loads((out / "mini" / "sft" / "final" / "config.json").read_text())["hidden_size"] == 128
    ev = json.loads((out / "mini" / "distill" / "eval.json").read_text())
    assert Path(ev["teacher_model"]) == teacher and Path(ev["sft_model"]) == out / "mini" / "sft" / "final"
    assert "eval/accuracy" in ev["teacher"] and "eval/accuracy" in ev["distill"] and Path(ev["model"]).is_dir()


def test_lora_distills_adapters_and_saves_a_merged_model(student, sharp_teacher, tmp_path, capsys):
    out = tmp_path / "lora"
    assert main(_args(student, out, sharp_teacher, "lora.enabled=true", "lora.r=4", "max_steps=3", "final_eval_rows=0",
                      "eval_rows=0", "run.quiet=false")) == 0
    assert "[distill] LoRA r=4" in capsys.readouterr().out
    final = out / "tiny-countdown" / "distill" / "final"
    assert (final / "model.safetensors").is_file() and not (final / "adapter_config.json").exists()
    kl = [s["kl/reverse"] for s in _steps(out)]
    assert len(kl) == 3 and all(k > 0 for k in kl)


def test_prompts_without_answers_and_no_verifier(student, sharp_teacher, tmp_path, write_jsonl, capsys):
    """verifier=none: a file of bare prompts (the `prompt` schema) is enough; nothing is evaluated for accuracy."""
    prompts = write_jsonl(tmp_path / "p.jsonl", [{"prompt": f"Reach {i} with 3 4 5."} for i in range(8)])
    out = tmp_path / "bare"
    assert main(_args(student, out, sharp_teacher, "verifier=none", f"train_file={prompts}", "max_steps=2")) == 0
    steps = _steps(out)
    assert len(steps) == 2 and "reward/mean" not in steps[0]
    assert not (out / "tiny-countdown" / "distill" / "teacher_eval.json").exists()
    bad = write_jsonl(tmp_path / "bad.jsonl", [{"prompt": "ok"}, {"question": "no prompt"}])
    assert main(_args(student, tmp_path / "b", sharp_teacher, "verifier=none", f"train_file={bad}")) == 2
    assert f"{bad}: row 2: field 'prompt': missing" in capsys.readouterr().err
