"""scripts/*.py: each imports (without running) and answers --help; bench.py uses the library's API only.

"Library API" here: bench.py imports nothing from `posttrain.trainers` (a trainer is run through the CLI,
`posttrain.cli.main` / `STAGES`, as a user runs it) and no underscore name from any posttrain module, so a
trainer's internals can change without the benchmark measuring something else.
"""
from __future__ import annotations

import ast
import json
import importlib.util
import statistics
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


@pytest.mark.parametrize("name", ["bench.py", "bench_verifiers.py", "reproduce_e6.py", "reproduce_e7.py",
                                  "reproduce_tools.py"])
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


def test_bench_tools_template_and_parser_keep_the_calc_call_format():
    """The tools section's premise, without training: TOOL_CHAT_TEMPLATE renders a conversation as the preset's
    template does, and a tool-calling turn given as TRL's structured tool_calls exactly as our episode's text of it;
    it passes TRL's checks (supports_tool_calling, prefix-preserving) where the preset's template fails the first;
    tool_response_template parses the call format back into the call, an answer into content, and a malformed call
    into no call (TRL then ends the episode: one of the differences the section prints)."""
    pytest.importorskip("trl")
    from trl.chat_template_utils import is_chat_template_prefix_preserving, parse_response, supports_tool_calling

    from posttrain.models import train_tokenizer
    from posttrain.verifiers.envs import format_tool_call, parse_tool_calls
    from posttrain.verifiers.envs.calc import CalcEnv, calculator

    bench = _load(SCRIPTS / "bench.py")
    tok = train_tokenizer(["What is 347 * 582? calculator expression 201954"] * 20, vocab_size=300,
                          split_digits=True, chat=True)
    env, p = CalcEnv(), CalcEnv.problems(1, seed=3)[0]
    text = format_tool_call("calculator", {"expression": p["expression"]})
    call = {"type": "function", "function": {"name": "calculator", "arguments": {"expression": p["expression"]}}}
    tail = [{"role": "tool", "content": p["answer"]}, {"role": "assistant", "content": p["answer"]}]
    as_text = env.reset(p) + [{"role": "assistant", "content": text}] + tail
    as_call = env.reset(p) + [{"role": "assistant", "content": "", "tool_calls": [call]}] + tail
    preset = tok.apply_chat_template(as_text, tokenize=False)
    assert not supports_tool_calling(tok)  # the preset's template drops tool_calls: TRL refuses it
    tok.chat_template = bench.TOOL_CHAT_TEMPLATE
    assert tok.apply_chat_template(as_text, tokenize=False) == preset
    assert tok.apply_chat_template(as_call, tokenize=False) == preset
    assert supports_tool_calling(tok) and is_chat_template_prefix_preserving(tok)

    tok.response_template = bench.tool_response_template(tok.eos_token)
    prefix = tok.apply_chat_template(env.reset(p), tokenize=True, add_generation_prompt=True, return_dict=False)

    def parsed(s: str) -> dict:
        return parse_response(tok, tok(s + tok.eos_token, add_special_tokens=False)["input_ids"], prefix=prefix,
                              tools=[calculator])

    assert parsed(text)["tool_calls"] == [call]
    assert parsed(p["answer"]) == {"role": "assistant", "content": p["answer"]}
    bad = '<tool_call>{"name": "calculator", "arguments": {"expression": "1\\u00"}}</tool_call>'
    assert "tool_calls" not in parsed(bad) and parse_tool_calls(bad)[0].error.startswith("malformed")


SMOLLM2_CHATML = ("{% for message in messages %}{% if loop.first and messages[0]['role'] != 'system' %}"
                  "{{ '<|im_start|>system\nYou are a helpful AI assistant named SmolLM, trained by Hugging "
                  "Face<|im_end|>\n' }}{% endif %}{{'<|im_start|>' + message['role'] + '\n' + message['content'] + "
                  "'<|im_end|>' + '\n'}}{% endfor %}{% if add_generation_prompt %}{{ '<|im_start|>assistant\n' }}"
                  "{% endif %}")  # SmolLM2-135M-Instruct's chat template (chat_template.jinja of the import)


def test_bench_chatml_tool_template_renders_episodes_as_smollm2_does():
    """The real tools rows' premise: CHATML_TOOL_TEMPLATE renders a calc-words conversation (with and without a
    system message) exactly as SmolLM2's ChatML does, and TRL's structured tool-calling turn as our episode's text;
    TRL accepts it; the ChatML response template parses a call and an answer back."""
    pytest.importorskip("trl")
    from trl.chat_template_utils import is_chat_template_prefix_preserving, parse_response, supports_tool_calling

    from posttrain.models import train_tokenizer
    from posttrain.tasks import wordcalc
    from posttrain.verifiers.envs import format_tool_call
    from posttrain.verifiers.envs.calc import calculator

    bench = _load(SCRIPTS / "bench.py")
    tok = train_tokenizer(["Nora collected 1068 pencils. calculator expression 1743"] * 20, vocab_size=300,
                          split_digits=True, chat=True)
    tok.add_special_tokens({"additional_special_tokens": ["<|im_start|>", "<|im_end|>"]})
    tok.eos_token = "<|im_end|>"
    row = wordcalc.make_examples(1, 0, "eval")[0]
    messages = row["messages"]  # system (tools), user, assistant call, tool, assistant answer
    expr = row["meta"]["expression"]
    call = {"type": "function", "function": {"name": "calculator", "arguments": {"expression": expr}}}
    as_call = messages[:2] + [{"role": "assistant", "content": "", "tool_calls": [call]}] + messages[3:]
    tok.chat_template = SMOLLM2_CHATML
    own = [tok.apply_chat_template(m, tokenize=False) for m in (messages, messages[1:])]
    assert not supports_tool_calling(tok)
    tok.chat_template = bench.CHATML_TOOL_TEMPLATE
    assert [tok.apply_chat_template(m, tokenize=False) for m in (messages, messages[1:])] == own
    assert tok.apply_chat_template(as_call, tokenize=False) == own[0]
    assert supports_tool_calling(tok) and is_chat_template_prefix_preserving(tok)
    tok.response_template = bench.tool_response_template(tok.eos_token, "<|im_start|>assistant\n")
    prefix = tok.apply_chat_template(messages[:2], tokenize=True, add_generation_prompt=True, return_dict=False)

    def parsed(s: str) -> dict:
        return parse_response(tok, tok(s + tok.eos_token, add_special_tokens=False)["input_ids"], prefix=prefix,
                              tools=[calculator])

    assert parsed(format_tool_call("calculator", {"expression": expr}))["tool_calls"] == [call]
    assert parsed("The answer is 1743.") == {"role": "assistant", "content": "The answer is 1743."}


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
    """scripts/gpu_check.py --dry: the GPU check's code on the tiny preset in fp32 (static cache and FSDP need CUDA:
    skipped), with a subset of the stage rows to stay near 40 s on 2 cores (`--dry` alone runs all of them, ~85 s).
    A real check: every row that is not skipped is ok, and the figures are there."""
    check = _load(SCRIPTS / "gpu_check.py")
    out = tmp_path / "check.json"
    rc = check.main(["--dry", "--json", str(out), "--stages", "sft,dpo,grpo,sft-lora,fsdp"])
    printed = capsys.readouterr().out
    assert rc == 0, printed
    rows = json.loads(out.read_text())["rows"]
    assert {k: r["status"] for k, r in rows.items() if r["status"] != "ok"} == {
        "static-cache generate fp32 B=16": "skipped: needs CUDA",
        "sft FSDP2 1 process (fp32 weights, bf16)": "skipped: needs CUDA"}
    assert set(rows) == {"greedy agreement fp32 B=16", "engine vs generate fp32 B=16", "static-cache generate fp32 B=16",
                         "sft (fp32)", "dpo (fp32)", "grpo (fp32)", "sft LoRA (fp32)",
                         "sft FSDP2 1 process (fp32 weights, bf16)"}
    assert rows["greedy agreement fp32 B=16"]["greedy agreement"] == "16/16 rows"
    engine = rows["engine vs generate fp32 B=16"]
    assert float(engine["logprob max abs diff"]) < 1e-3 and engine["engine tok/s"] > 0 and engine["generate tok/s"] > 0
    for name in ("sft (fp32)", "dpo (fp32)", "sft LoRA (fp32)"):
        assert rows[name]["steps"] == 2 and rows[name]["loss"] > 0 and rows[name]["peak_rss_mb"] > 0
    assert rows["grpo (fp32)"]["steps"] == 1 and "reward/mean" in rows["grpo (fp32)"]
    assert "| grpo (fp32) | ok |" in printed and "| row | status | figures | peak memory |" in printed


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
    assert "load not recorded" in text and "shared" not in text.split("\n\n")[1]  # no load measured: no claim about it
    res.update(load_average=(0.1, 2.0), cpu="AMD EPYC (family 25 model 1)")
    assert "(AMD EPYC (family 25 model 1), " in e7.report_md(res)
    assert "load average 0.1 at the start, 2.0 at the end" in e7.report_md(res)
    if mode == "real":
        assert "--model real" in text and "**met**" in text and "instruct greedy accuracy" in text
        assert "Where the gain comes from" not in text and "a sample showing a counted behaviour" in text
    else:
        assert "Where the gain comes from" in text and "SFT greedy accuracy" in text and "**met**" not in text


def _fake_e6_run(e6, arm: str, seed: int, gold: list[float] | None = None) -> dict:
    """One run of `arm` as reproduce_e6.py records it: a step-0 (SFT) point, 4 evaluations, the final eval."""
    dpo = e6.ARMS[arm].stage == "dpo"
    steps = [0, 20, 40, 60, 80] if dpo else [0, 5, 10, 15, 20]
    gold = gold or [-1.0, 0.3 + 0.01 * seed, 0.6, 0.5, 0.55 - 0.02 * seed]  # peak 0.6 mid-run
    n = len(steps)
    curves = {"progress": [s / steps[-1] for s in steps], "step": steps, "gold/reward": gold,
              "gold/win_rate": [0.5] + [0.6 + 0.01 * k for k in range(n - 1)],
              "gold/quality": [0.3] * n, "gold/in_band": [0.4] + [0.8] * (n - 1),
              "proxy/reward": [0.0] + [1.0 + 0.2 * k for k in range(n - 1)],
              "kl": [0.0] + [2.0 * k for k in range(1, n)]}
    final = {"win_rate": 0.7 - 0.01 * seed - (0.05 if "ppo" in arm else 0.0), "gold_reward": gold[-1],
             "mean_quality": 0.5, "frac_in_band": 0.9, "kl": 6.0, "proxy_reward": 1.8 if "ppo" in arm else 1.5}
    return {"seed": seed, "seconds": 60.0 + seed, "run_dir": f"runs/{arm}-seed{seed}", "final": final,
            "curves": curves}


def _fake_e6_results(e6, tmp_path, arms=None) -> dict:
    arms = list(e6.ARMS) if arms is None else arms
    return {"mode": "quick", "seeds": [0, 1], "threads": 1, "recipe": "e6-quick.yaml",
            "model": {"preset": "tiny", "parameters": 1_234_567}, "sft": {"mean_quality": 0.2, "frac_in_band": 0.4},
            "rm": {"eval/accuracy": 0.8}, "shared_seconds": {"base+sft+prefs+rm": 120.0}, "runs_dir": str(tmp_path),
            "arm_table": {a: e6.ARMS[a]._asdict() for a in arms},
            "runs": {a: [_fake_e6_run(e6, a, s) for s in (0, 1)] for a in arms},
            "total_seconds": 600.0, "pipeline_seconds": 900.0, "load_end": "1.00 1.00 1.00"}


def test_e6_stability_leaves_out_step_0():
    """Give-back, worst fall and monotonicity are on the evaluations after step 0, by hand on small curves."""
    e6 = _load(SCRIPTS / "reproduce_e6.py")
    # the first evaluation after step 0 dips far below the SFT point, then the run climbs to its peak at the end
    dip = {"step": [0, 20, 40, 60, 80], "gold/reward": [0.2, -1.5, 0.1, 0.4, 0.6]}
    st = e6.stability(dip)
    assert st["give_back"] == 0.0 and st["evaluations"] == 4
    assert st["worst_fall"] == 0.0 and st["monotonicity"] == 1.0
    # by hand: after step 0 the curve is 0.5, 0.8, 0.6, 0.7, 0.3: peak 0.8, final 0.3 -> give-back 0.5; falls 0.2
    # (0.8 -> 0.6) and 0.4 (0.7 -> 0.3) -> worst fall 0.4; 2 of 4 steps fall by more than 0.01 -> monotonicity 0.5
    small = {"step": [0, 1, 2, 3, 4, 5], "gold/reward": [5.0, 0.5, 0.8, 0.6, 0.7, 0.3]}
    st = e6.stability(small)
    assert st["give_back"] == pytest.approx(0.5) and st["worst_fall"] == pytest.approx(0.4)
    assert st["monotonicity"] == pytest.approx(0.5) and st["evaluations"] == 5
    assert not hasattr(e6, "max_drawdown")  # the measure from the running best at step 0 is gone
    # without a step-0 point every evaluation counts
    assert e6.give_back(e6.after_start({"step": [10, 20], "gold/reward": [1.0, 0.25]})) == pytest.approx(0.75)


def test_e6_report_and_plots_of_every_arm(tmp_path):
    """analyse + report_md + plot on fabricated runs of every arm x 2 seeds: the headline table lists the like-with-like
    arms first, the verdict compares dpo-offline with ppo-rm, the oracle arms get their own paragraph."""
    e6 = _load(SCRIPTS / "reproduce_e6.py")
    res = _fake_e6_results(e6, tmp_path)
    # dpo-offline seed 1 dips at its first evaluation after step 0 and recovers to its peak at the end
    res["runs"]["dpo-offline"][1] = _fake_e6_run(e6, "dpo-offline", 1, gold=[0.2, -1.5, 0.1, 0.4, 0.6])
    an = e6.analyse(res)
    assert list(an["summary"]) == list(e6.ARMS)
    assert an["summary"]["dpo-offline"]["per_seed_give_back"][1] == 0.0
    ppo = an["summary"]["ppo-rm"]  # seeds end at 0.55 and 0.53 below their 0.6 peak; both fall 0.6 -> 0.5 once
    assert ppo["give_back"][0] == pytest.approx(statistics.fmean([0.6 - 0.55, 0.6 - 0.53]))
    assert ppo["worst_fall"][0] == pytest.approx(0.1) and ppo["monotonicity"][0] == pytest.approx(2 / 3)
    assert an["claims"]["compared"] == ["dpo-offline", "ppo-rm"]
    assert set(an["claims"]["dpo_more_stable"]) == {"spread_of_final_win_rate", "spread_of_final_gold_reward",
                                                   "give_back", "monotonicity", "worst_fall"}
    assert an["models_in_memory"]["simpo-offline"]["models_in_memory"] == 1
    assert an["models_in_memory"]["ppo-rm"]["models_in_memory"] == 4
    res.update(an)
    figs = e6.plot(res, tmp_path)
    if importlib.util.find_spec("matplotlib") is not None:
        assert figs == ["win_rate.png", "kl.png", "gold_vs_proxy.png"]
        assert all((tmp_path / f).stat().st_size > 0 for f in figs)
    text = e6.report_md(res, an, figs)
    headline = text.split("## Final policies")[1].split("\n## ")[0]
    rows = [line.split("|")[1].strip().strip("`") for line in headline.splitlines() if line.startswith("| `")]
    assert rows == ["dpo-offline", "ppo-rm", "simpo-offline", "orpo-offline", "kto-offline", "dpo-online-gold",
                    "ppo-gold"]
    groups = [line.split("|")[2].strip() for line in headline.splitlines() if line.startswith("| `")]
    assert groups == ["like with like"] * 5 + ["oracle"] * 2
    claim = text.split("## Does the seed's claim hold here?")[1].split("\n## ")[0]
    assert "`dpo-offline` vs `ppo-rm`" in claim and "**DPO is more stable:" in claim and "give-back" in claim
    assert "dpo-online-gold" not in claim.split("Other preference losses")[0]
    assert "`simpo-offline`" in claim and "`orpo-offline`" in claim and "`kto-offline`" in claim
    oracle = text.split("## Oracle arms")[1].split("\n## ")[0]
    assert "`dpo-online-gold`" in oracle and "`ppo-gold`" in oracle and "not the seed's setting" in oracle
    assert "KTO beta 0.1" in text and "not implemented" not in text and "max drawdown from the running best" in text
    assert "after step 0" in text and "minus the final one" in text and "worst fall" in text
    assert "| `simpo-offline` | dpo |" in text.split("## Simplicity")[1]


def test_e6_report_without_the_headline_pair(tmp_path):
    """--arms without dpo-offline / ppo-rm: no verdict, said so; the tables still render."""
    e6 = _load(SCRIPTS / "reproduce_e6.py")
    res = _fake_e6_results(e6, tmp_path, arms=["ppo-gold", "simpo-offline"])
    an = e6.analyse(res)
    assert an["claims"] is None and list(an["summary"]) == ["simpo-offline", "ppo-gold"]
    text = e6.report_md({**res, **an}, an, [])
    assert "Not judged" in text and "Not run as a pair" in text


def test_e6_arms_option(capsys):
    e6 = _load(SCRIPTS / "reproduce_e6.py")
    assert e6.parse_args([]).arms == list(e6.ARMS)
    assert e6.parse_args(["--arms", "ppo-rm,dpo-offline", "ppo-rm"]).arms == ["dpo-offline", "ppo-rm"]
    with pytest.raises(SystemExit) as e:
        e6.parse_args(["--arms", "dpo-offline", "ipo-offline"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "unknown arm 'ipo-offline'" in err and "choose from: dpo-offline, ppo-rm" in err


def test_make_chat_data_rewrites_the_shipped_files_byte_for_byte(tmp_path):
    """data/chat/ is what scripts/make_chat_data.py writes (data/README.md: provenance)."""
    mod = _load(SCRIPTS / "make_chat_data.py")
    assert mod.main(["--out", str(tmp_path)]) == 0
    shipped = SCRIPTS.parent / "data" / "chat"
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == sorted(p.name for p in shipped.iterdir())
    for name in names:
        assert (tmp_path / name).read_bytes() == (shipped / name).read_bytes(), name


@pytest.mark.parametrize("script", ["reproduce_e6.py", "reproduce_e7.py", "reproduce_tools.py"])
def test_the_reproductions_plot_each_run_with_posttrain_plot(tmp_path, script):
    """The reproductions write every run's metric plots with posttrain.plots.plot_runs (`posttrain plot`)."""
    pytest.importorskip("matplotlib")
    from posttrain.plots import plot_runs

    assert "plot_runs(" in (SCRIPTS / script).read_text()
    run = tmp_path / "runs" / "x" / "grpo"
    run.mkdir(parents=True)
    (run / "metrics.jsonl").write_text("".join(json.dumps({"step": s, "loss": 1.0 / s, "reward/mean": s / 10})
                                               + "\n" for s in range(1, 6)))
    written = plot_runs({"grpo": run, "missing": tmp_path / "nothing"}, tmp_path / "report")
    assert written == {"grpo": "stage-plots/grpo"}
    pngs = sorted(p.name for p in (tmp_path / "report" / "stage-plots" / "grpo").glob("*.png"))
    assert pngs and all(n.endswith(".png") for n in pngs)


def test_bench_multiturn_section_runs_and_counts_the_tokens(capsys):
    """bench.py's multiturn section at small batches: every episode has turns, environment tokens and tool calls."""
    from types import SimpleNamespace

    bench = _load(SCRIPTS / "bench.py")
    out = bench.bench_multiturn(SimpleNamespace(presets=["tiny"], batches=[1, 4], repeats=1))
    assert [r["batch"] for r in out["rows"]] == [1, 4]
    for r in out["rows"]:
        assert r["turns"] >= 1 and r["sampled"] > 0 and r["env_tokens"] > 0 and r["ratio"] > 0
        assert r["steps_ratio"] == (r["sampled"] + r["env_tokens"]) / r["sampled"]
    assert "steps ratio" in capsys.readouterr().out


# ----------------------------------------------------------------------------- reproduce_tools.py
def _episode(turns: list[tuple[str, list[tuple[str, str | None]]]], finish: str = "answer") -> dict:
    """An Episode.to_dict(): turns of (text, [(tool result, error kind)])."""
    return {"finish": finish, "messages": [],
            "turns": [{"text": text, "reward": None, "sampled_tokens": 10, "env_tokens": 4 * len(calls),
                       "tool_calls": [{"name": "calculator", "arguments": {}, "raw": "", "content": c, "error": e,
                                       "seconds": 0.001} for c, e in calls]} for text, calls in turns]}


def test_tools_report_names_why_each_episode_failed():
    """cause() and behaviour() by hand on crafted episodes of a problem whose answer is 1743."""
    from posttrain.verifiers.math_answer import MathVerifier

    tools = _load(SCRIPTS / "reproduce_tools.py")
    check = MathVerifier().check
    call = '<tool_call>{"name": "calculator", "arguments": {"expression": "1068+806-131"}}</tool_call>'
    right = _episode([(call, [("1743", None)]), ("The answer is 1743.", [])])
    ignored = _episode([(call, [("1743", None)]), ("The answer is 1744.", [])])
    wrong_expr = _episode([(call, [("2005", None)]), ("The answer is 2005.", [])])
    recovered = _episode([(call, [("error: unexpected 'p'", "exception")]), (call, [("2005", None)]),
                          ("The answer is 2005.", [])])
    no_valid = _episode([(call, [("error: unexpected 'p'", "exception")]), ("The answer is 12.", [])])
    no_call = _episode([("The answer is 12.", [])])
    cut = _episode([(call, [("1000", None)]), (call, [("1001", None)])], finish="max_turns")
    cases = [(right, 1.0, "right"), (ignored, 0.0, "right result ignored"), (wrong_expr, 0.0, "wrong expression"),
             (recovered, 0.0, "wrong expression"), (no_valid, 0.0, "no valid call"), (no_call, 0.0, "no call"),
             (cut, 0.0, "no answer turn")]
    for ep, reward, want in cases:
        assert tools.cause(ep, "1743", reward, check) == want
    assert [tools.ignores_result(e, check) for e in (right, ignored, wrong_expr, no_call, cut)] == \
        [False, True, False, None, None]
    b = tools.behaviour([e for e, _, _ in cases], check)
    assert b["called_a_tool"] == pytest.approx(6 / 7) and b["answered"] == pytest.approx(6 / 7)
    assert b["calls_per_episode"] == pytest.approx(8 / 7)  # 1 + 1 + 1 + 2 + 1 + 0 + 2
    assert b["valid_call_rate"] == pytest.approx(6 / 8)
    assert b["episodes_with_a_tool_error"] == pytest.approx(2 / 7) and b["recovered_after_error"] == 0.5
    assert b["ignores_last_result"] == pytest.approx(1 / 4)  # right, ignored, wrong_expr, recovered have a result
    assert b["sampled_tokens"] == pytest.approx(10 * 14 / 7) and b["env_tokens"] == pytest.approx(4 * 8 / 7)
    # the K metrics: 2 problems x 4 samples; pass@1 = mean right share; maj@4 by majority of answer keys
    k = tools.k_metrics([[("5", True), ("5", True), ("6", False), (None, False)],
                          [("7", False), ("7", False), ("8", True), ("9", False)]], 4)
    assert k["pass_at_k"] == {1: pytest.approx((2 / 4 + 1 / 4) / 2), 4: 1.0} and k["maj_at_k"][4] == 0.5


def _fake_tools_eval(acc: float, tools: bool, samples: bool = True) -> dict:
    e = {"greedy_accuracy": acc, "greedy_seconds": 10.0, "greedy_tokens_per_problem": 40.0}
    if samples:
        e.update(pass_at_k={1: acc, 4: acc + 0.1, 16: acc + 0.2}, pass_curve=[acc + 0.2 * k / 15 for k in range(16)],
                 maj_at_k={1: acc, 4: acc, 16: acc + 0.05})
    if tools:
        b = {"called_a_tool": 1.0, "valid_call_rate": 0.9, "calls_per_episode": 1.1, "turns_per_episode": 2.0,
             "answered": 1.0, "episodes_with_a_tool_error": 0.1, "recovered_after_error": 1.0,
             "ignores_last_result": 0.05, "sampled_tokens": 50.0, "env_tokens": 12.0, "tool_seconds": 0.001}
        e.update(behaviour_greedy=b, greedy_causes={c: (acc if c == "right" else 0.0) for c in
                                                    ("right", "no call", "no valid call", "no answer turn",
                                                     "wrong expression", "right result ignored")},
                 examples={"right": [{"question": "Q?", "answer": "5", "transcript": "assistant: 5"}]})
    return e


def test_tools_report_and_plots(tmp_path):
    """The report of reproduce_tools.py from the numbers of a run: every table renders, the verdict follows the
    numbers, GRPO's own gain over SFT is stated."""
    tools = _load(SCRIPTS / "reproduce_tools.py")
    ev = {"instruct": _fake_tools_eval(0.0, False), "instruct_tools": _fake_tools_eval(0.0, True, samples=False),
          "sft": _fake_tools_eval(0.6, True), "grpo": _fake_tools_eval(0.65, True),
          "grpo_no_tools": _fake_tools_eval(0.1, False), "sft_own": _fake_tools_eval(0.4, True, samples=False),
          "grpo_own": _fake_tools_eval(0.5, True, samples=False)}
    steps = [1, 2, 3, 4]
    env = {k: [1.0] * 4 for k in ("env/tool_calls", "env/valid_calls", "env/called_a_tool", "env/sampled_tokens",
                                  "env/env_tokens", "env/tool_seconds")}
    run = {"steps": steps, "reward": [0.5] * 4, "step_seconds": [10.0] * 4, "eval_steps": [0, 2, 4],
           "eval_accuracy": [0.6, 0.62, 0.65], "config": {"prompts_per_step": 16, "group_size": 8}, "env": env,
           "completion_length": [30.0] * 4, "saved_behaviour": [dict(ev["sft"]["behaviour_greedy"], step=2, reward=0.5)],
           "entropy": [0.02, 0.04, 0.06, 0.08], "zero_var_frac": [0.5, 0.25, 0.25, 0.0]}
    plain = dict(run, env={k: [None] * 4 for k in env}, saved_behaviour=[])
    res = {"quick": False, "overrides": [], "threads": 2, "eval_rows": 100, "samples": 16, "temperature": 0.7,
           "own": {"file": "data/word-calc-own.jsonl", "rows": 60},
           "budget": "max_steps=4, prompts_per_step=16, group_size=8", "rollout_dtype": "auto",
           "mixed_precision": "auto", "reused": ["sft"], "seconds": {"sft": 400.0, "grpo": 900.0, "grpo_no_tools": 300.0,
                                                                      "eval": 600.0},
           "eval": ev, "grpo": run, "grpo_no_tools": plain, "sft_config": {"max_steps": 60, "batch_size": 8},
           "runtime_s": 2200.0, "load_average": (0.1, 2.0), "cpu": "AMD EPYC (family 25 model 17)"}
    res["verdict"] = tools.verdict(ev)
    res["compute"] = tools.compute(res)
    assert res["compute"]["grpo"] == {"sequences": 512, "sampled_tokens": 512.0, "env_tokens": 512.0,
                                      "tool_seconds": 512.0}
    assert res["compute"]["grpo_no_tools"]["sampled_tokens"] == 128 * 30.0 * 4
    res["figures"] = tools.plots(res, tmp_path)
    assert all((tmp_path / f).is_file() for f in res["figures"]) and len(res["figures"]) == 3
    text = tools.report_md(res)
    assert res["verdict"]["met"] and "**met**" in text and "+5.0 points greedy" in text
    for heading in ("## Held-out accuracy", "## Why the wrong greedy answers are wrong", "## Behaviour", "## Compute"):
        assert heading in text
    assert "| instruct, tool prompted | **0.0%** | n/a | n/a |" in text
    assert "| SFT + GRPO with the tool | **65.0%** | 65.0% | 75.0% | 85.0% |" in text  # one sample at T: pass@1
    assert "On 60 word problems in phrasings of our own" in text
    assert ("GRPO with tools over training: entropy (nats per sampled token) 0.020 / 0.050 / 0.080 (first step / mean "
            "/ last); groups with no reward variance 50% / 25% / 0% (first step / mean / last).") in text
    assert "| SFT + GRPO with the tool | 65.0% | **50.0%** | -15.0 points |" in text
    assert not res["verdict"]["rl_met"] and ("**Target of RL over its SFT start** (issue 49; samples at T=0.7): "
                                             "**not met**: greedy 60.0% -> 65.0% (+5.0 points; at least +10), pass@16 "
                                             "80.0% -> 85.0% (+5.0 points; at most 3 down), phrasings of our own 40.0% "
                                             "-> 50.0% (+10.0 points; at least +5).") in text
    ev["grpo"] = _fake_tools_eval(0.75, True)  # +15 points greedy, pass@16 95%
    assert tools.verdict(ev)["rl_met"]
    ev["grpo"]["pass_at_k"][16] = 0.76  # pass@16 4 points below the SFT model's
    assert not tools.verdict(ev)["rl_met"]
    ev["grpo"]["pass_at_k"][16] = 0.77  # 3 points below: within
    assert tools.verdict(ev)["rl_met"]
    ev["grpo_own"]["greedy_accuracy"] = 0.44  # the gain does not hold on the own phrasings
    assert not tools.verdict(ev)["rl_met"]
    del ev["grpo_own"]
    assert not tools.verdict(ev)["rl_met"] and "phrasings of our own not measured" in tools.verdict(ev)["rl_text"]
    ev["grpo_no_tools"]["greedy_accuracy"] = 0.7
    assert not tools.verdict(ev)["met"]
