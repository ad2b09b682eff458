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
