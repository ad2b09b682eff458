"""scripts/*.py: each imports (without running) and answers --help; bench.py uses the library's API only.

"Library API" here: bench.py imports nothing from `posttrain.trainers` (a trainer is run through the CLI,
`posttrain.cli.main` / `STAGES`, as a user runs it) and no underscore name from any posttrain module, so a
trainer's internals can change without the benchmark measuring something else.
"""
from __future__ import annotations

import ast
import json
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"
ALL = sorted(p for p in SCRIPTS.glob("*.py"))


def _load(path: Path):
    """Import a script as `python scripts/NAME.py` would see it (its folder first on sys.path), without running it."""
    spec = importlib.util.spec_from_file_location(f"_script_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while it executes
    sys.path.insert(0, str(path.parent))
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(path.parent))
    return module


def test_every_script_is_here():
    assert {p.name for p in ALL} >= {"bench.py", "bench_verifiers.py", "reproduce_e6.py", "reproduce_e7.py",
                                      "stage_runner.py"}


@pytest.mark.parametrize("path", ALL, ids=lambda p: p.name)
def test_script_imports_without_running(path):
    module = _load(path)
    assert module.__doc__ and module.__doc__.strip(), f"{path.name} has no docstring saying what it does"
    if path.name != "stage_runner.py":  # a helper module of the reproductions, not a command
        assert callable(getattr(module, "main", None)), f"{path.name} has no main()"


@pytest.mark.parametrize("name", ["bench.py", "bench_verifiers.py", "reproduce_e6.py", "reproduce_e7.py"])
def test_script_help(name):
    out = subprocess.run([sys.executable, str(SCRIPTS / name), "--help"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "usage" in out.stdout.lower()


def _posttrain_imports(path: Path) -> list[tuple[str, str | None]]:
    """(module, name) for every import of posttrain in `path` (name None for `import module`)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found += [(a.name, None) for a in node.names if a.name.split(".")[0] == "posttrain"]
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "posttrain":
            found += [(node.module, a.name) for a in node.names]
    return found


def test_bench_uses_library_api_only():
    imports = _posttrain_imports(SCRIPTS / "bench.py")
    assert imports, "bench.py imports nothing of posttrain?"
    bad = [f"{m}{'.' + n if n else ''}" for m, n in imports
           if m.startswith("posttrain.trainers") or (n or "").startswith("_") or
           any(part.startswith("_") for part in m.split("."))]
    assert not bad, f"scripts/bench.py reaches into trainer internals or private names: {bad}"
    for m, n in imports:  # and every name it imports exists (a function, class or submodule)
        module = importlib.import_module(m)
        assert n is None or hasattr(module, n) or importlib.util.find_spec(f"{m}.{n}") is not None, \
            f"bench.py imports {m}.{n}, which does not exist"


def test_test_margins_summarizes_each_check_by_its_worst_run():
    margins = _load(SCRIPTS / "test_margins.py")
    checks = [{"test": "tests/a.py::test_x", "check": "reward rise", "op": ">", "bound": 0.1, "value": v,
               "margin": v - 0.1, "seed": s, "threads": t} for v, s, t in ((0.3, 0, 1), (0.05, 1, 2), (0.5, 2, 1))]
    checks.append({"test": "tests/a.py::test_x", "check": "no eos", "op": "<", "bound": 0.3, "value": 0.2,
                   "margin": 0.1, "seed": 0, "threads": 1})
    rows = {r["check"]: r for r in margins.summarize(checks)}
    rise = rows["reward rise"]
    assert (rise["worst"], rise["median"], rise["best"]) == (0.05, 0.3, 0.5)
    assert rise["worst_margin"] == pytest.approx(-0.05) and rise["worst_at"] == "seed 1, 2 thr"
    assert (rise["runs"], rise["failed"]) == (3, 1)
    assert rows["no eos"]["best"] == 0.2 and rows["no eos"]["failed"] == 0
    assert "| test_x | reward rise | > 0.1 | 0.05 |" in margins.table(list(rows.values()))


@pytest.mark.slow
def test_gpu_check_dry_mode_runs_every_row_on_cpu(tmp_path, capsys):
    """scripts/gpu_check.py --dry: the GPU check's code on the tiny preset in fp32 (FSDP needs CUDA: skipped)."""
    check = _load(SCRIPTS / "gpu_check.py")
    assert check.main(["--dry", "--json", str(tmp_path / "check.json")]) == 0, capsys.readouterr().out
    rows = json.loads((tmp_path / "check.json").read_text())["rows"]
    assert [k for k, r in rows.items() if r["status"] != "ok"] == ["sft step (FSDP2, 1 process)"]
    assert rows["engine vs generate"]["greedy agreement"] == "16/16 rows"
    assert "| grpo step (float32) | ok |" in capsys.readouterr().out


def _fake_e7_eval(acc: float, behaviours: dict[str, float]) -> dict:
    curve = [min(1.0, acc + 0.03 * k) for k in range(16)]
    return {"greedy_accuracy": acc, "sample_accuracy": curve[0], "pass_at_k": {1: curve[0], 4: curve[3], 16: curve[15]},
            "pass_curve": curve, "maj_at_k": {1: curve[0], 4: acc, 16: acc + 0.02}, "frac_mixed_groups_of_8": 0.4,
            "frac_some_right_of_16": 0.6, "frac_all_right_of_16": 0.1, "greedy_tokens_per_problem": 30.0,
            "sample_tokens_per_sample": 32.0, "greedy_seconds": 3.0, "sample_seconds": 40.0, "greedy_truncated": 0.1,
            "behaviour_greedy": dict(behaviours), "behaviour_samples": dict(behaviours),
            "greedy_reasons": {"correct": 5, "wrong answer": 5},
            "examples": [{"prompt": "Ava has 2 apples. She gets 3 more apples. How many?", "greedy": "2 + 3 = 5",
                          "right": True}],
            "sample_examples": [{"prompt": "p", "sample": "Wait, 2 + 3 = 5", "right": True}],
            "greedy_by_question": {"direct-style question": {"n": 4, "greedy_accuracy": acc, "greedy_worked": 0.5,
                                                             "worked_accuracy": 0.9},
                                   "other questions": {"n": 6, "greedy_accuracy": acc, "greedy_worked": 1.0,
                                                       "worked_accuracy": 0.9}}}


@pytest.mark.parametrize("mode", ["tiny", "real"])
def test_e7_report_and_plots_of_each_mode(mode, tmp_path):
    """The report and the plots of reproduce_e7.py, from the numbers of a run (both modes): every section renders,
    the real mode states its verdict against the +10-point target and names the instruct model."""
    e7 = _load(SCRIPTS / "reproduce_e7.py")
    m = e7.MODES[mode]
    beh = {k: 0.1 for k, _ in m.behaviours}
    steps = list(range(1, 11))
    res = {"mode": mode, "start_label": m.start, "temperature": 0.7, "rollout_dtype": "bfloat16",
           "mixed_precision": "auto", "quick": True, "overrides": [], "threads": 2, "eval_rows": 10,
           "preset": "models/smollm2-135m-instruct", "parameters": 134_515_008, "difficulty": 1,
           "phrases": {"verification": ["check"], "self_correction": ["wait"]}, "runs_dir": str(tmp_path),
           "reused": [], "direct_prob": 0.8, "seconds": {"sft": 0.0 if mode == "real" else 60.0, "grpo": 120.0,
                                                          "eval": 30.0},
           "eval": {"sft": _fake_e7_eval(0.2, beh), "grpo": _fake_e7_eval(0.45, beh)},
           "grpo": {"prompts_per_step": 8, "group_size": 8, "steps": steps, "reward": [0.1] * 10,
                    "train_length": [40.0] * 10, "zero_var_frac": [0.3] * 10, "entropy": [0.5] * 10,
                    "cum_sampled_tokens": [100.0 * s for s in steps], "cum_step_seconds": [12.0 * s for s in steps],
                    "eval_steps": [0, 5, 10], "eval_accuracy": [0.2, 0.3, 0.45], "eval_length": [40.0, 30.0, 20.0],
                    "sampled_tokens": 1000.0, "sampled_sequences": 640.0, "trained_sequences": 400.0,
                    "config": {"eval_rows": 10, "lr": 2e-4}},
           "behaviour_over_training": {"steps": [1, 10], "length": [40.0, 20.0], **{k: [0.1, 0.0] for k, _ in m.behaviours}},
           "sft_cost": {"steps": 0, "batch_size": 0, "tokens": 0.0, "sequences": 0, "mean_row_tokens": 0.0},
           "runtime_s": 300.0}
    res["compute"] = e7.compute_table(res)
    figs = e7.plots(res, tmp_path)
    assert all((tmp_path / name).is_file() for name in figs) and len(figs) == 5
    text = e7.report_md(res)
    assert f"+{25.0:.1f} points" in text and "## Compute" in text and "## Examples" in text
    if mode == "real":
        assert "--model real" in text and "**met**" in text and "instruct greedy accuracy" in text
        assert "Where the gain comes from" not in text and "a sample showing a counted behaviour" in text
    else:
        assert "Where the gain comes from" in text and "SFT greedy accuracy" in text and "**met**" not in text
