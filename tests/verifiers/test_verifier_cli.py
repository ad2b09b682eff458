"""posttrain.verifiers.cli: list, audit, score; bad files and rows are one line naming file, line and field (exit 2)."""
import json
import os
import subprocess
import sys

import pytest

from posttrain.verifiers.cli import main

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def write_jsonl(path, rows):
    path.write_text("".join((r if isinstance(r, str) else json.dumps(r)) + "\n" for r in rows))
    return str(path)


def test_list(capsys):
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].split() == ["name", "origin", "description"]
    assert any(line.startswith("math ") and "built-in" in line for line in out.splitlines())
    assert "format" in out and "length" in out


def test_audit_builtin_problems_with_json(tmp_path, capsys):
    out_json = tmp_path / "report.json"
    assert main(["audit", "math", "--n", "15", "--seed", "2", "--workers", "2", "--json", str(out_json)]) == 0
    out = capsys.readouterr().out
    assert "problems: audit_problems(n=15, seed=2)" in out and "-> OK" in out
    report = json.loads(out_json.read_text())
    assert report["ok"] is True and report["problems"] == 15 and report["false_positives"] == 0


def test_audit_with_problems_file_and_naive_verifier(tmp_path, capsys):
    problems = write_jsonl(tmp_path / "p.jsonl", [
        {"prompt": f"{a}+1?", "reference": str(a + 1), "gold": f"It is {a + 1}."} for a in (10, 20, 30)])
    naive = tmp_path / "naive.py"
    naive.write_text("def contains(completion, reference):\n    return str(reference) in completion\n")
    assert main(["audit", "math", "--problems", problems, "--workers", "1"]) == 0
    assert main(["audit", f"{naive}:contains", "--problems", problems, "--workers", "1"]) == 1
    out = capsys.readouterr().out
    assert "PROBLEMS FOUND" in out and "false positives" in out


def test_audit_problem_file_errors(tmp_path, capsys):
    bad = write_jsonl(tmp_path / "bad.jsonl", [{"prompt": "p", "reference": "1", "gold": "1"}, {"prompt": "p", "reference": "2"}])
    assert main(["audit", "math", "--problems", bad]) == 2
    assert capsys.readouterr().err.strip() == f"error: {bad} line 2: missing field 'gold' (fields: prompt, reference)"
    assert main(["audit", "0.5*math+0.5*format", "--problems", str(tmp_path / "none.jsonl")]) == 2
    assert capsys.readouterr().err.strip() == f"error: {tmp_path / 'none.jsonl'}: no such file"


def test_audit_verifier_without_problems(tmp_path, capsys):
    assert main(["audit", "format"]) == 2
    assert "ships no audit problems; pass --problems FILE.jsonl" in capsys.readouterr().err


def test_score_summary_and_out(tmp_path, capsys):
    data = write_jsonl(tmp_path / "r.jsonl", [
        {"completion": r"\boxed{4}", "answer": "4"},
        {"completion": "The answer is 5.", "answer": "4"},
        "",
        {"completion": "no idea", "answer": 4},
        {"completion": "#### 4", "answer": "4.0"},
    ])
    out_file = tmp_path / "verdicts.jsonl"
    assert main(["score", "math", data, "--workers", "1", "--out", str(out_file)]) == 0
    out = capsys.readouterr().out
    assert f"scored 4 rows from {data} with 'math'" in out
    assert "mean score  0.5000" in out and "pass rate   0.5000 (2/4)" in out
    assert "2  correct" in out and "1  wrong answer" in out and "1  no answer found" in out
    rows = [json.loads(line) for line in out_file.read_text().splitlines()]
    assert [r["line"] for r in rows] == [1, 2, 4, 5] and rows[1]["reason"] == "wrong answer"


def test_score_custom_fields_and_options(tmp_path, capsys):
    data = write_jsonl(tmp_path / "r.jsonl", [{"text": r"\boxed{0.333}", "gold": "1/3"}])
    assert main(["score", "math", data, "--completion-field", "text", "--reference-field", "gold", "-o", "rel_tol=0.01"]) == 0
    assert "pass rate   1.0000 (1/1)" in capsys.readouterr().out
    assert main(["score", "math", data, "--completion-field", "text", "--reference-field", "gold"]) == 0
    assert "pass rate   0.0000 (0/1)" in capsys.readouterr().out


@pytest.mark.parametrize("rows,message", [
    pytest.param([{"completion": "1", "answer": "1"}, "{not json"], "line 2: invalid JSON", id="invalid-json"),
    pytest.param([{"completion": "1", "answer": "1"}, [1, 2]], "line 2: expected a JSON object, got list", id="not-an-object"),
    pytest.param([{"completion": "1", "answer": "1"}, {"completion": "2"}, {"answer": "3"}],
                 "line 2: missing field 'answer' (fields: completion)", id="missing-field"),
    pytest.param([{"completion": 5, "answer": "1"}], "line 1: field 'completion' must be a string, got int", id="wrong-type"),
    pytest.param([{"completion": "1", "answer": "1"}, {"completion": "1", "answer": ""}],
                 "line 2: verifier 'math' raised ValueError: malformed reference", id="bad-reference"),
    pytest.param([""], ": no rows", id="empty-file"),
])
def test_score_bad_rows(tmp_path, capsys, rows, message):
    data = write_jsonl(tmp_path / "bad.jsonl", rows)
    assert main(["score", "math", data, "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: {data}") and message in err and "\n" not in err


def test_usage_errors(capsys):
    assert main(["score", "nope", "x.jsonl"]) == 2
    assert capsys.readouterr().err.startswith("error: unknown verifier 'nope'; available: math")
    assert main(["score", "math", "x.jsonl", "--timeout", "0"]) == 2
    assert "--timeout must be > 0" in capsys.readouterr().err
    assert main(["audit", "math", "-o", "oops"]) == 2
    assert "bad option 'oops'" in capsys.readouterr().err
    assert main([]) == 2
    assert main(["--help"]) == 0


def test_runs_as_a_module():
    proc = subprocess.run([sys.executable, "-m", "posttrain.verifiers.cli", "list"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and "math" in proc.stdout
