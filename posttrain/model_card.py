"""`final/README.md`: a Hugging Face model card (huggingface_hub's `ModelCard`) for every model a stage saves.

Written by the command line after a stage returns its `final/` directory (`posttrain.cli`), so no trainer carries
it: the card's YAML metadata (library_name, base_model, tags, datasets, pipeline_tag) is what the hub reads, and
the body holds the stage and recipe, the command that produced it, the evaluation the run wrote (`eval.json`),
the resolved config, and the library versions. `transformers` ignores README.md when it loads the directory,
so `from_pretrained` is unchanged. Nothing here pushes to the hub.
"""
from __future__ import annotations

import json
import platform
import shlex
from importlib import metadata
from pathlib import Path
from typing import Any

import yaml

STAGE_WORDS = {
    "sft": "supervised fine-tuning", "rm": "a Bradley-Terry reward model", "dpo": "preference optimisation (DPO "
    "family)", "ppo": "PPO-for-RLHF", "grpo": "GRPO with verifiable rewards", "distill": "on-policy distillation",
}
LIBRARIES = ("posttrain", "torch", "transformers", "accelerate", "peft", "datasets", "tokenizers")


def _version(name: str) -> str:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


def _flat_numbers(obj: Any, prefix: str = "") -> dict[str, float]:
    """The numbers of an eval.json, flattened to dotted keys (lists and texts left out)."""
    out: dict[str, float] = {}
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.update(_flat_numbers(v, f"{prefix}{k}."))
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        out[prefix[:-1]] = float(obj)
    return out


def _origin(config: dict[str, Any]) -> tuple[str | None, str]:
    """(the hub id of the base model, or None; the base model in words). A preset is built from scratch, a local
    directory is named by path; only an `org/name` that is not a local path is a hub id."""
    from posttrain.models import PRESETS

    path = str(config.get("model", {}).get("path", ""))
    if path in PRESETS:
        return None, f"a `{path}` preset built from scratch (tokenizer trained on the task)"
    if path.count("/") == 1 and not Path(path).exists() and not path.startswith((".", "/")):
        return path, f"`{path}`"
    return None, f"the local model `{path}`"


def card_text(config: dict[str, Any], evaluation: dict[str, Any] | None, command: list[str]) -> str:
    """The card as text: YAML metadata, then the body. `config` is a resolved stage config (`Resolved.to_dict`)."""
    from huggingface_hub import ModelCard, ModelCardData

    stage, recipe = config["stage"], config["recipe"]
    base_id, base_words = _origin(config)
    train_file = (config.get(stage) or {}).get("train_file") or (config.get("task") or {}).get("train_file")
    data = ModelCardData(library_name="transformers", pipeline_tag="text-generation" if stage != "rm" else
                         "text-classification", base_model=base_id, datasets=[str(train_file)] if train_file else None,
                         tags=["posttrain", stage, recipe])
    task = (config.get("task") or {}).get("name", "?")
    lines = [f"# {recipe} / {stage}", "",
             f"Trained with posttrain by {STAGE_WORDS.get(stage, stage)}: stage `{stage}` of the recipe `{recipe}` "
             f"(task `{task}`{f', data {train_file}' if train_file else ''}), from {base_words}.", "",
             "## How it was made", "", "```bash", shlex.join(command), "```", ""]
    numbers = _flat_numbers({k: v for k, v in (evaluation or {}).items() if k not in ("model", "samples")})
    if numbers:
        lines += ["## Evaluation (as the run reported it, eval.json)", "", "| metric | value |", "|---|---|"]
        lines += [f"| {k} | {v:.4g} |" for k, v in numbers.items()]
        lines.append("")
    lines += ["## Resolved config", "", "```yaml", yaml.safe_dump(config, sort_keys=False).rstrip(), "```", "",
              "## Versions", "", f"Python {platform.python_version()}; "
              + ", ".join(f"{name} {_version(name)}" for name in LIBRARIES), ""]
    return ModelCard.from_template(data, template_str="---\n{{ card_data }}\n---\n\n" + "\n".join(lines)).content


def write_card(final_dir: str | Path, config: dict[str, Any], command: list[str]) -> Path | None:
    """Write `final_dir/README.md` for a model directory (a file output such as prefs' is left alone); the
    evaluation comes from `final_dir/../eval.json` when the run wrote one. Returns the card's path, or None."""
    final = Path(final_dir)
    if not (final / "config.json").is_file():
        return None
    ev_path = final.parent / "eval.json"
    evaluation = json.loads(ev_path.read_text()) if ev_path.is_file() else None
    path = final / "README.md"
    tmp = path.with_suffix(".md.tmp")
    tmp.write_text(card_text(config, evaluation, command))
    tmp.replace(path)
    return path
