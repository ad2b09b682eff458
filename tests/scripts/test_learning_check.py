"""scripts/learning_check.py: its runs are valid commands, its bands table parses, its verdicts follow the bands."""
from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _load(path: Path):
    spec = importlib.util.spec_from_file_location(f"_script_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while it executes
    spec.loader.exec_module(module)
    return module


LC = _load(ROOT / "scripts" / "learning_check.py")


@pytest.mark.parametrize("run", LC.RUNS, ids=lambda r: r.name)
def test_every_run_is_a_valid_command_of_its_recipe(run, tmp_path):
    from posttrain.cli import validate

    cmd = run.command(3, tmp_path, "models/smollm2-135m-instruct", "fp32")
    assert cmd[1:6] == ["-m", "posttrain", "grpo", "--recipe", run.recipe]
    overrides = cmd[6:]
    stages = {res.stage: res for res in validate(run.recipe, overrides)}
    assert stages["grpo"].run.threads == 1 and stages["grpo"].stage_cfg.seed == 3
    assert stages["grpo"].stage_cfg.final_eval_rows >= 100  # the figures are held-out accuracies on enough problems
    assert run.tier in ("quick", "full") and run.seeds


def test_the_quick_tier_is_tiny_math_and_the_full_one_adds_tiny_calc_and_the_real_model():
    assert [(r.name, r.seeds) for r in LC.RUNS if r.tier == "quick"] == [("tiny-math", (0, 1))]
    full = [r for r in LC.RUNS if r.tier == "full"]
    assert [r.name for r in full] == ["tiny-calc", "smol-math"] and [r.real for r in full] == [False, True]
    assert len(full[1].seeds) == 2


def test_bands_in_results_md_parse_and_cover_every_quick_figure_in_fp32():
    bands = LC.read_bands(ROOT / "RESULTS.md")
    for run in LC.RUNS:
        if run.tier == "quick":
            for fig in LC.FIGURES:
                low, high, seeds = bands[(run.name, fig, "fp32")]
                assert low <= high and len(LC.parse_seeds(seeds)) >= 5, (run.name, fig, seeds)


def test_read_bands_and_verdicts_by_hand(tmp_path):
    md = tmp_path / "R.md"
    md.write_text("text\n" + LC.BEGIN + "\n| run | figure | precision | seeds | per seed | band |\n|---|---|---|---|---|---|\n"
                  "| tiny-math | grpo | fp32 | 0-4 | 0.9 0.95 | 0.900-0.950 |\n" + LC.END + "\n| x | y | z | 1 | 2 | 3 |\n")
    bands = LC.read_bands(md)
    assert bands == {("tiny-math", "grpo", "fp32"): (0.9, 0.95, "0-4")}
    band = bands[("tiny-math", "grpo", "fp32")]
    assert [LC.verdict(v, band) for v in (0.89, 0.9, 0.93, 0.95, 0.96)] == ["FAIL", "pass", "pass", "pass", "above"]
    assert LC.verdict(0.5, None) == "no band"
    md.write_text(LC.BEGIN + "\n| tiny-math | grpo | fp32 | 0-4 | 0.9 | about 0.9 |\n" + LC.END)
    with pytest.raises(SystemExit, match="band 'about 0.9' of tiny-math / grpo / fp32 must read LOW-HIGH"):
        LC.read_bands(md)
    assert LC.read_bands(tmp_path / "missing.md") == {}


def test_seeds_and_band_rows():
    assert LC.parse_seeds("0-4") == (0, 1, 2, 3, 4) and LC.parse_seeds("1,3") == (1, 3)
    with pytest.raises(SystemExit, match="--seeds '4-1'"):
        LC.parse_seeds("4-1")
    rows = LC.band_rows([{"run": "r", "seed": 1, "sft": 0.5, "grpo": 0.75, "gain": 0.25, "precision": "fp32"},
                         {"run": "r", "seed": 0, "sft": 0.25, "grpo": 0.5, "gain": 0.25, "precision": "fp32"},
                         {"run": "r", "seed": 0, "sft": 0.0, "grpo": 0.5, "gain": 0.5, "precision": "bf16"},
                         {"run": "r", "seed": 2, "error": "exit 1", "precision": "fp32"}])
    assert rows[0] == "| r | sft | fp32 | 0,1 | 0.250 0.500 | 0.250-0.500 |"
    assert rows[2] == "| r | gain | fp32 | 0,1 | 0.250 0.250 | 0.250-0.250 |"
    assert rows[5] == "| r | gain | bf16 | 0 | 0.500 | 0.500-0.500 |"


def test_precisions_the_runs_compute_in(tmp_path, monkeypatch):
    from posttrain.cli import validate

    tiny = next(r for r in LC.RUNS if r.name == "tiny-math")
    assert tiny.precision("recipe") == "fp32"  # the tiny recipes train and sample in fp32 on every machine
    assert tiny.precision("bf16") == "bf16"
    cmd = tiny.command(0, tmp_path, "m", "bf16")
    grpo = next(res for res in validate(tiny.recipe, cmd[6:]) if res.stage == "grpo")
    assert (grpo.run.mixed_precision, grpo.rollout.dtype) == ("bf16", "bfloat16")
    for half, settings in (("bf16-train", ("bf16", "float32")), ("bf16-rollout", ("no", "bfloat16"))):
        cmd = tiny.command(0, tmp_path, "m", half)
        grpo = next(res for res in validate(tiny.recipe, cmd[6:]) if res.stage == "grpo")
        assert (grpo.run.mixed_precision, grpo.rollout.dtype) == settings, half
    cmd = tiny.command(0, tmp_path, "m", "bf16", ("grpo.old_logprobs=recompute",))
    assert cmd[-1] == "grpo.old_logprobs=recompute"  # --set: after the run's own overrides, so it wins
    grpo = next(res for res in validate(tiny.recipe, cmd[6:]) if res.stage == "grpo")
    assert grpo.stage_cfg.old_logprobs == "recompute"
    smol = next(r for r in LC.RUNS if r.name == "smol-math")
    # the recipe's auto, decided as a run decides it; forced here, since the probe is a timing that a loaded
    # machine can flip between two calls
    for forced, want in (("1", "bf16"), ("0", "fp32")):
        monkeypatch.setenv("POSTTRAIN_BF16", forced)
        assert smol.precision("recipe") == want


def test_bad_options_are_one_line_errors(tmp_path):
    for args, msg in ((["--only", "nope"], "unknown run(s) nope"), (["--jobs", "0"], "--jobs must be at least 1"),
                      (["--only", "smol-math", "--model", str(tmp_path)], "the real model is not at"),
                      (["--precision", "fp32,fp16"], "--precision 'fp32,fp16': choose from recipe, fp32, bf16, bf16-train, bf16-rollout")):
        out = subprocess.run([sys.executable, str(ROOT / "scripts" / "learning_check.py"), *args,
                              "--out", str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
        assert out.returncode != 0 and msg in out.stderr, out.stderr
