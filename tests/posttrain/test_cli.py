import subprocess
import sys

import pytest

from posttrain.cli import main


def test_recipes_lists_tiny_summarize(capsys):
    assert main(["recipes"]) == 0
    assert "tiny-summarize" in capsys.readouterr().out


def test_stage_help_lists_fields_with_docs(capsys):
    assert main(["sft", "--help"]) == 0
    out = capsys.readouterr().out
    assert "lr" in out and "Peak learning rate" in out and "model.path" in out


def test_unknown_key_is_one_line_error_before_model_loads(capsys, tmp_path):
    rc = main(["sft", "--recipe", "tiny-summarize", "learning_rate=1", f"run.output_dir={tmp_path}"])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert err.count("\n") == 0 and "unknown config key 'learning_rate'" in err and "lr" in err
    assert not any(tmp_path.iterdir())  # nothing was built


def test_missing_model_path_is_one_line_error(capsys, tmp_path):
    rc = main(["sft", "--recipe", "tiny-summarize", f"model.path={tmp_path}/nope", f"run.output_dir={tmp_path}/runs"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.count("\n") == 0
    assert "nope" in err and "does not exist" in err


def test_smol_math_without_the_fetched_model_says_how_to_fetch_it(capsys, tmp_path):
    missing = tmp_path / "models" / "smollm2-135m-instruct"
    rc = main(["grpo", "--recipe", "smol-math", f"model.path={missing}", f"run.output_dir={tmp_path}/runs"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.count("\n") == 0
    assert f"posttrain models fetch smollm2-135m-instruct {missing}" in err


def test_bad_data_row_is_one_line_error(capsys, tmp_path):
    bad = tmp_path / "train.jsonl"
    bad.write_text('{"prompt": "a", "completion": "b"}\n{"prompt": "c"}\n')
    rc = main(["sft", "--recipe", "tiny-summarize", f"task.train_file={bad}", f"run.output_dir={tmp_path}/runs"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.count("\n") == 0
    assert str(bad) in err and "row 2" in err and "'completion'" in err


def test_unknown_task_and_command(capsys):
    assert main(["sft", "--recipe", "tiny-summarize", "task.name=nope"]) == 2
    assert "task.name" in capsys.readouterr().err
    assert main(["frobnicate"]) == 2
    assert "unknown command" in capsys.readouterr().err


def test_python_dash_m_entry_point():
    out = subprocess.run([sys.executable, "-m", "posttrain", "recipes"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "tiny-summarize" in out.stdout


# ----------------------------------------------------------------------------- recipe tools
def test_validate_resolves_and_range_checks_every_stage_without_a_model(capsys, tmp_path, monkeypatch):
    from posttrain import models

    monkeypatch.setattr(models, "load_model", lambda *a, **k: (_ for _ in ()).throw(AssertionError("loaded a model")))
    assert main(["validate", "--recipe", "tiny-math"]) == 0
    assert "tiny-math: valid (sft, grpo, distill, eval)" in capsys.readouterr().out
    # a range check that lives in a trainer (grpo.check_config), a type error, a typo in another stage's section
    for override, message in (("grpo.clip_eps=-1", "grpo.clip_eps and clip_eps_high must be > 0"),
                              ("distill.student_fraction=2", "distill.student_fraction must be in [0, 1]"),
                              ("sft.max_steps=many", "sft.max_steps"),
                              ("grpo.clip_epss=0.1", "clip_epss"),
                              ("lr=1e-3", "name the section")):
        assert main(["validate", "--recipe", "tiny-math", override]) == 2, override
        assert message in capsys.readouterr().err, override
    bad = tmp_path / "bad.yaml"
    bad.write_text("# a recipe with a DPO setting out of range\ntask: {name: tiny-summarize}\ndpo: {beta: 0}\n")
    assert main(["validate", "--recipe", str(bad)]) == 2
    assert "dpo.beta must be > 0" in capsys.readouterr().err


def test_recipes_show_prints_every_resolved_stage_and_cp_makes_a_runnable_copy(capsys, tmp_path):
    import yaml

    assert main(["recipes", "show", "tiny-summarize", "dpo.beta=0.2"]) == 0
    text = capsys.readouterr().out
    parts = [p for p in text.split("# ---- ")[1:]]
    stages = [p.split("\n", 1)[0] for p in parts]
    assert stages[-1] == "eval" and {"sft", "dpo", "ppo"} <= set(stages)
    dpo = yaml.safe_load(parts[stages.index("dpo")].split("\n", 1)[1])
    assert dpo["dpo"]["beta"] == 0.2 and dpo["model"]["path"] and dpo["recipe"] == "tiny-summarize"
    dst = tmp_path / "mine.yaml"
    assert main(["recipes", "cp", "tiny-summarize", str(dst)]) == 0
    assert "run it with `--recipe" in capsys.readouterr().out
    assert main(["validate", "--recipe", str(dst)]) == 0
    assert f"{dst}: valid (sft, prefs, rm, dpo, ppo, eval)" in capsys.readouterr().out
    assert main(["recipes", "cp", "tiny-summarize", str(dst)]) == 2  # never overwrites
    assert "exists" in capsys.readouterr().err
    assert main(["recipes", "frobnicate"]) == 2
    assert "recipes show NAME" in capsys.readouterr().err
