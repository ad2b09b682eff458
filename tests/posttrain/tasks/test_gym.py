"""gym:DATASET tasks (posttrain/tasks/gym.py): reasoning-gym's datasets as posttrain tasks, offline: the Task
protocol, seeded disjoint splits, options, errors, and a GRPO run from a gym task through the CLI."""
from __future__ import annotations

import json

import pytest

pytest.importorskip("reasoning_gym")

from posttrain import tasks  # noqa: E402
from posttrain.data import validate_rows  # noqa: E402

SPECS = ["basic_arithmetic", "chain_sum,max_terms=2,max_digits=2", "leg_counting", "spell_backward"]


@pytest.mark.parametrize("spec", SPECS)
def test_a_gym_task_follows_the_protocol_with_seeded_disjoint_splits(spec):
    task = tasks.get_task(f"gym:{spec}")
    assert task.NAME == f"gym:{spec}" and task.VERIFIER == "gym" and task.gold_quality is None
    train, ev = task.make_examples(40, 0, "train"), task.make_examples(10, 0, "eval")
    validate_rows(train, "sft")
    validate_rows(train, "verifiable")
    assert not {r["prompt"] for r in train} & {r["prompt"] for r in ev}  # the question's hash picks the split
    assert len({r["prompt"] for r in train}) == 40
    assert task.make_examples(40, 0, "train") == train and task.make_examples(20, 0, "train")[:20] == train[:20]
    assert task.make_examples(10, 1, "train") != train[:10]  # the seed changes the stream
    assert json.loads(json.dumps(train)) == train  # rows are JSON as they are
    m = task.evaluate([r["meta"] for r in ev], [r["completion"] for r in ev])
    assert m == {"accuracy": 1.0, "mean_score": 1.0, "format": 1.0}
    wrong = task.evaluate([r["meta"] for r in ev], ["<answer>not it</answer>"] * 10)
    assert wrong["accuracy"] == 0.0 and wrong["format"] == 1.0


def test_options_reach_the_dataset_and_bad_ones_are_config_errors():
    rows = tasks.get_task("gym:chain_sum,max_terms=2,max_digits=1").make_examples(30, 0, "train")
    assert all(r["prompt"].split(":")[1].split("=")[0].count(" ") == 4 for r in rows)  # " a + b " : two terms
    from posttrain.config import TaskConfig
    from posttrain.errors import ConfigError

    for name, message in [("gym:no_such_dataset", "reasoning-gym has no dataset 'no_such_dataset'"),
                          ("gym:chain_sum,terms=2", "option 'terms=2': chain_sum's options are allow_negation, "),
                          ("gym:chain_sum,max_terms=0", "reasoning-gym refuses these options")]:
        with pytest.raises(ConfigError, match=f"task.name: .*{message}"):
            tasks.load_split(TaskConfig(name=name, n_train=4), "train")


def test_too_few_distinct_questions_is_a_clear_error():
    with pytest.raises(ValueError, match=r"only \d+ distinct eval questions"):
        tasks.get_task("gym:chain_sum,max_terms=2,max_digits=1").make_examples(200, 0, "eval")


@pytest.mark.slow
def test_grpo_on_a_gym_task_through_the_cli(tmp_path, capsys):
    """SFT then GRPO on gym:chain_sum from nothing (a few steps): the gym verifier scores the rollouts in the
    worker pool, and the held-out comparison uses the task's gold metrics."""
    from posttrain.cli import main

    out = tmp_path / "runs"
    assert main(["grpo", "--recipe", "gym-chain-sum", f"run.output_dir={out}", "run.quiet=true", "task.n_train=200",
                 "task.n_eval=20", "sft.max_steps=20", "sft.final_eval_rows=8", "max_steps=3", "prompts_per_step=4",
                 "group_size=4", "eval_every=0", "eval_rows=8", "save_rollouts_every=3"]) == 0
    run = out / "gym-chain-sum" / "grpo"
    saved = [json.loads(l) for l in (run / "rollouts" / "step-000003.jsonl").read_text().split("\n") if l]
    extras = [json.loads(r["extras_json"]) for r in saved]
    assert len(saved) == 16 and all("gym" in e["parts"] and "format" in e["parts"] for e in extras)
    ev = json.loads((run / "eval.json").read_text())
    assert "eval/accuracy" in ev["sft"] and "eval/accuracy" in ev["grpo"]
