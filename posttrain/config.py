"""Typed configs, recipes and strict merging.

Precedence: dataclass defaults < recipe YAML < `key=value` on the command line.
A recipe has shared sections (`task:`, `model:`, `run:`, `lora:`, `rollout:`) and one section per stage
(`sft:`, `rm:`, `dpo:`, `ppo:`, `grpo:`, `eval:`). An unknown key or a value of the
wrong type is a `ConfigError` naming the key and the valid ones, raised before any
model loads.

Command-line keys: `lr=1e-3` sets a field of the stage being run; dotted keys reach
any section (`model.preset=small`, `task.n_train=500`, `sft.lr=1e-3`).
"""
from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any, Literal

import yaml

from posttrain.errors import ConfigError
from posttrain import trackers
from posttrain.runtime import dtype_problem


# ----------------------------------------------------------------------------- shared sections
@dataclass
class ColumnsConfig:
    """Columns of the recipe's data files named otherwise than posttrain's fields (`task.columns.prompt=question`).
    Every data file of the recipe (task., grpo., dpo., rm., prefs. train and eval files) is read with them."""

    prompt: str | None = None
    """Column holding the prompt (text or a list of messages); null: `prompt`."""
    completion: str | None = None
    """Column holding the SFT completion (or KTO's unpaired completion); null: `completion`."""
    messages: str | None = None
    """Column holding a whole conversation for SFT (e.g. `conversations`); null: `messages`."""
    chosen: str | None = None
    """Column holding the preferred side of a pair; null: `chosen`."""
    rejected: str | None = None
    """Column holding the other side of a pair; null: `rejected`."""
    answer: str | None = None
    """Column holding the reference answer of a verifiable problem (e.g. `solution`); null: `answer`."""
    label: str | None = None
    """Column holding KTO's desirable/undesirable label; null: `label`."""

    def mapping(self) -> dict[str, str]:
        """{posttrain's field: the data's column} for the columns that are renamed."""
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name)}


@dataclass
class TaskConfig:
    name: str = "tiny-summarize"
    """Task generator (posttrain/tasks): tiny-summarize, ..."""
    n_train: int = 4000
    """Number of generated training examples."""
    n_eval: int = 200
    """Number of generated held-out examples."""
    seed: int = 0
    """Seed of the task generator (train and eval streams are derived from it)."""
    difficulty: int = 0
    """Difficulty level of a task that has levels (word-math: 1-3); 0: the task's default."""
    options: dict[str, Any] = field(default_factory=dict)
    """Options of the task's generator, each task's own (its OPTIONS; tiny-calc: `task.options.tool_rate=0.4`)."""
    train_file: str | None = None
    """Optional JSONL/Parquet/dataset dir replacing the generated training set."""
    eval_file: str | None = None
    """Optional JSONL/Parquet/dataset dir replacing the generated held-out set."""
    columns: ColumnsConfig = field(default_factory=ColumnsConfig)
    """Data columns named otherwise than posttrain's fields (`task.columns.prompt=question`)."""


@dataclass
class ModelConfig:
    path: str = "tiny"
    """A preset (tiny, small, base) built from scratch, a local Hugging Face model directory, or a .gguf file
    (dequantized once into <run.output_dir>/models/; `posttrain models --help`)."""
    start_from: Literal["sft", "base"] = "sft"
    """What the stages after SFT (prefs, rm, dpo, ppo, grpo, eval) start from: sft (this recipe's SFT model,
    trained first if missing) or base (model.path as it is: an instruct model that needs no SFT)."""
    vocab_size: int = 1024
    """Tokenizer vocabulary size when a preset is built from scratch."""
    max_length: int = 256
    """Longest prompt + completion in tokens; longer rows are dropped with a count."""
    seed: int = 0
    """Seed of the random init of a preset."""
    split_digits: bool = False
    """Tokenizer built from scratch: every digit its own token (arithmetic tasks such as tiny-math)."""
    chat_template: Literal["auto", "on", "off"] = "auto"
    """Prompts through the tokenizer's chat template: auto (when it has one), on (error if none; a preset gets one), off."""
    system_prompt: str | None = None
    """System message put before every prompt (needs a chat template); null: what the model's template says."""
    dtype: Literal["float32", "bfloat16", "float16"] = "float32"
    """Weights dtype of every model a stage loads; bfloat16 / float16 need a GPU (on CPU: float32 weights, and
    `run.mixed_precision=bf16` / `auto` for bf16 compute)."""
    gradient_checkpointing: bool = False
    """Recompute activations in the backward pass of trained models (less memory, slower; same losses)."""


@dataclass
class RunConfig:
    output_dir: str = "runs"
    """Root of run directories: <output_dir>/<recipe>/<stage>/."""
    threads: int = 0
    """torch CPU threads (0: leave torch's default)."""
    quiet: bool = False
    """No per-step console lines and no progress lines of long phases; metrics still go to metrics.jsonl."""
    mixed_precision: Literal["no", "bf16", "auto"] = "no"
    """bf16 autocast over fp32 weights in every stage's training forward and backward (the weights, optimizer state,
    losses and advantages stay fp32; log-probs are taken in fp32 from the bf16 forward's logits, so PPO / GRPO
    ratios to the fp32 sampler are no longer exactly 1; the frozen reference's and teacher's log-probs are taken
    under the same autocast; generation is not autocast: `rollout.dtype` sets it): no (what `accelerate launch`
    says, else none), bf16, or auto (bf16 where the hardware has native bf16: a GPU, or a CPU with AVX512-BF16
    or AMX; on other CPUs bf16 is emulated and slower)."""
    report_to: str | list[str] = "none"
    """Experiment trackers that get every metric of metrics.jsonl and the resolved config (posttrain.trackers):
    none, or one or more of tensorboard, wandb, trackio, mlflow (`run.report_to=tensorboard,wandb`); each is an
    extra (`pip install "posttrain[wandb]"`). Resolved to a list; an unknown or uninstalled name is a config error."""
    micro_batch_tokens: int = 0
    """Padded tokens per forward / backward in every stage, a bound on activation memory (each stage's
    micro_batch_size still caps the rows); 0: auto, the tokens whose activations take ~2 GiB for this model
    (posttrain.models.token_budget; its values for a tiny and a 135M model: docs/results-archive.md, "Figures once
    kept in code comments")."""


@dataclass
class LoRAConfig:
    enabled: bool = False
    """Train LoRA adapters (peft) instead of every weight; the reference is the base with adapters off."""
    stages: list[str] = field(default_factory=list)
    """Stages that use LoRA when enabled; empty: only the stage being run (stages it builds first train fully)."""
    r: int = 16
    """Adapter rank."""
    alpha: float = 32.0
    """Scaling numerator: the update is (alpha / r) * B @ A."""
    dropout: float = 0.0
    """Dropout on the adapter input during training."""
    target_modules: list[str] = field(default_factory=lambda: ["q_proj", "k_proj", "v_proj", "o_proj", "gate_proj",
                                                                "up_proj", "down_proj"])
    """Module names that get adapters (Llama-family names by default; "all-linear" is peft's shorthand)."""


@dataclass
class RolloutConfig:
    backend: Literal["auto", "lean", "hf", "vllm"] = "auto"
    """Generator of every stage: built-in engine (auto: lean forward if supported; lean; hf) or vllm (GPU)."""
    dtype: Literal["float32", "bfloat16", "auto"] = "float32"
    """Weights of the built-in engine's matmuls: float32, or bfloat16 (a bf16 copy of the policy, refreshed after every
    update: faster sampling where the CPU or GPU has native bf16; the sampler's log-probs then differ slightly from
    the trainer's, logged as mismatch/kl; GRPO's pi_old is then recomputed by the trainer), or auto (bfloat16 where bf16 is native, float32 elsewhere: emulated bf16
    is slower than fp32). The HF forward and vLLM (vllm_dtype) ignore it."""
    vllm_gpu_memory_utilization: float = 0.3
    """backend=vllm: fraction of the GPU's memory vLLM takes (weights + KV cache); the rest is left to training."""
    vllm_dtype: str = "auto"
    """backend=vllm: dtype of vLLM's copy of the policy (auto: vLLM's choice from the config; float16, bfloat16)."""
    vllm_enforce_eager: bool = False
    """backend=vllm: no CUDA graphs (faster start, less memory, slower decoding)."""


SHARED_SECTIONS: dict[str, type] = {"task": TaskConfig, "model": ModelConfig, "run": RunConfig, "lora": LoRAConfig,
                                    "rollout": RolloutConfig}
STAGE_SECTIONS = ("sft", "prefs", "rm", "dpo", "ppo", "grpo", "distill", "eval")


# ----------------------------------------------------------------------------- type checking
def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(tp))
    if origin in (list, tuple):
        args = typing.get_args(tp)
        return f"list of {_type_name(args[0])}" if args else "list"
    if origin is dict:
        return "mapping"
    if tp is type(None):
        return "null"
    return getattr(tp, "__name__", str(tp))


def coerce(value: Any, tp: Any, key: str) -> Any:
    """Check `value` against the annotation `tp`; return it (ints are accepted for floats)."""
    origin = typing.get_origin(tp)
    if tp is Any:
        return value
    if origin is Literal:
        if isinstance(value, bool):  # YAML 1.1 reads a bare on / off / yes / no as a boolean
            word = next((w for w in (("on", "yes", "true") if value else ("off", "no", "false"))
                         if w in typing.get_args(tp)), None)
            if word is not None:
                return word
        if value in typing.get_args(tp):
            return value
        raise ConfigError(f"config key {key!r}: {value!r} is not {_type_name(tp)}")
    if origin in (typing.Union, types.UnionType):
        for arg in typing.get_args(tp):
            try:
                return coerce(value, arg, key)
            except ConfigError:
                continue
        raise ConfigError(f"config key {key!r}: expected {_type_name(tp)}, got {value!r}")
    if tp is type(None):
        if value is None:
            return None
        raise ConfigError(f"config key {key!r}: expected null, got {value!r}")
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"config key {key!r}: expected {_type_name(tp)}, got {value!r}")
        args = typing.get_args(tp)
        inner = args[0] if args else Any
        return [coerce(v, inner, f"{key}[{i}]") for i, v in enumerate(value)]
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"config key {key!r}: expected a mapping, got {value!r}")
        return dict(value)
    if is_dataclass(tp):
        raise ConfigError(f"config key {key!r} is a section; set its fields as {key}.FIELD=VALUE")
    if tp is bool:
        if isinstance(value, bool):
            return value
    elif tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    elif tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif tp is str:
        if isinstance(value, str):
            return value
    else:
        raise TypeError(f"unsupported config annotation {tp!r} for {key!r}")  # our bug
    raise ConfigError(f"config key {key!r}: expected {_type_name(tp)}, got {value!r} ({type(value).__name__})")


def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def field_docs(cls: type) -> dict[str, str]:
    """The docstrings under each dataclass field (read from the source), a base class's included: a field
    re-declared without one (a trainer's own default for `loop.TrainingConfig`'s `lr`) keeps its base's."""
    import ast
    import inspect
    import textwrap

    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not is_dataclass(klass):
            continue
        try:
            src = textwrap.dedent(inspect.getsource(klass))
        except (OSError, TypeError):
            continue
        body = ast.parse(src).body[0].body  # type: ignore[attr-defined]
        for a, b in zip(body, body[1:]):
            if isinstance(a, ast.AnnAssign) and isinstance(a.target, ast.Name) and isinstance(b, ast.Expr) \
                    and isinstance(b.value, ast.Constant) and isinstance(b.value.value, str):
                docs[a.target.id] = b.value.value.strip()
    return docs


def merge_into(obj: Any, updates: dict[str, Any], prefix: str) -> None:
    """Apply a mapping of updates to a dataclass instance, strictly."""
    if not isinstance(updates, dict):
        raise ConfigError(f"config section {prefix!r} must be a mapping, got {updates!r}")
    hints = _hints(type(obj))
    for key, value in updates.items():
        full = f"{prefix}.{key}" if prefix else str(key)
        if key not in hints:
            valid = ", ".join(f.name for f in fields(obj))
            raise ConfigError(f"unknown config key {full!r}; valid keys in {prefix or 'config'}: {valid}")
        tp = hints[key]
        if is_dataclass(tp):
            merge_into(getattr(obj, key), value, full)
        else:
            setattr(obj, key, coerce(value, tp, full))


def to_dict(obj: Any) -> dict[str, Any]:
    return dataclasses.asdict(obj)


# ----------------------------------------------------------------------------- recipes
def recipes_dir() -> Path:
    """The shipped recipes: `recipes/` in a source checkout, `posttrain/recipes` when installed."""
    src = Path(__file__).resolve().parent.parent / "recipes"
    if src.is_dir() and any(src.glob("*.yaml")):
        return src
    # Installed: `posttrain.recipes` is a package of data files without an __init__.py (a namespace
    # package), so its directory is read from __path__ (importlib.resources.files would give a
    # MultiplexedPath, not a filesystem path).
    import posttrain.recipes as shipped

    for d in getattr(shipped, "__path__", []):
        if any(Path(d).glob("*.yaml")):
            return Path(d)
    raise FileNotFoundError(f"no recipes found next to posttrain ({src}) nor in {list(shipped.__path__)}")


def list_recipes() -> list[tuple[str, str]]:
    """(name, one-line description) of each shipped recipe: the first comment line of its file."""
    out = []
    for p in sorted(recipes_dir().glob("*.yaml")):
        desc = ""
        for line in p.read_text().splitlines():
            if line.startswith("#"):
                desc = line.lstrip("# ").strip()
                break
        out.append((p.stem, desc))
    return out


def resolve_recipe(name_or_path: str) -> Path:
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        if not p.is_file():
            raise ConfigError(f"recipe file {name_or_path!r} does not exist")
        return p
    cand = recipes_dir() / f"{name_or_path}.yaml"
    if not cand.is_file():
        names = ", ".join(n for n, _ in list_recipes())
        raise ConfigError(f"unknown recipe {name_or_path!r}; shipped recipes: {names} (or give a path to a .yaml file)")
    return cand


def load_recipe(name_or_path: str) -> tuple[str, dict[str, Any]]:
    """(recipe name, raw mapping) of a recipe name or YAML path."""
    path = resolve_recipe(name_or_path)
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise ConfigError(f"recipe {str(path)!r} is not valid YAML: {str(e).splitlines()[0]}") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"recipe {str(path)!r} must be a mapping of sections (task:, model:, sft:, ...)")
    return path.stem, raw


def parse_overrides(items: list[str]) -> list[tuple[str, Any]]:
    out = []
    for item in items:
        if "=" not in item:
            raise ConfigError(f"command-line override {item!r} must look like key=value (e.g. lr=1e-3 or model.preset=small)")
        key, text = item.split("=", 1)
        key = key.strip()
        if not key:
            raise ConfigError(f"command-line override {item!r} has an empty key")
        try:
            value = yaml.safe_load(text) if text != "" else ""
        except yaml.YAMLError:
            value = text
        # YAML reads 1e-3 as a string (no dot before the exponent); accept it as a number.
        if isinstance(value, str):
            try:
                value = float(value) if any(c in value.lower() for c in ".e") and value.strip() else value
            except ValueError:
                pass
        out.append((key, value))
    return out


@dataclass
class Resolved:
    """A resolved config: shared sections plus the stage's own config."""

    recipe: str
    stage: str
    task: TaskConfig
    model: ModelConfig
    run: RunConfig
    stage_cfg: Any
    raw_recipe: dict[str, Any] = field(default_factory=dict)
    lora: LoRAConfig = field(default_factory=LoRAConfig)
    rollout: RolloutConfig = field(default_factory=RolloutConfig)

    @property
    def use_lora(self) -> bool:
        """Whether this stage trains LoRA adapters (see LoRAConfig.stages)."""
        return self.lora.enabled and (self.stage in self.lora.stages or not self.lora.stages)

    @property
    def run_root(self) -> Path:
        return Path(self.run.output_dir) / self.recipe

    def stage_dir(self, stage: str | None = None) -> Path:
        return self.run_root / (stage or self.stage)

    def to_dict(self) -> dict[str, Any]:
        return {"recipe": self.recipe, "stage": self.stage, "task": to_dict(self.task), "model": to_dict(self.model),
                "run": to_dict(self.run), "lora": to_dict(self.lora), "rollout": to_dict(self.rollout),
                self.stage: to_dict(self.stage_cfg)}

    def with_model(self, model: str) -> "Resolved":
        """This recipe with another model (model.path: a preset or a directory), in its own run tree
        <run.output_dir>/model-<name>/ so that its stages never mix with this model's."""
        from dataclasses import replace

        out = Path(self.run.output_dir) / f"model-{Path(model).name}"
        return replace(self, model=replace(self.model, path=model), run=replace(self.run, output_dir=str(out)))

    def for_stage(self, stage: str, stage_cls: type) -> "Resolved":
        """The config of another stage of the same recipe (used to build a prerequisite stage)."""
        cfg = stage_cls()
        if stage in self.raw_recipe and self.raw_recipe[stage] is not None:
            merge_into(cfg, self.raw_recipe[stage], stage)
        lora = self.lora if self.lora.enabled and stage in self.lora.stages else LoRAConfig()
        return Resolved(self.recipe, stage, self.task, self.model, self.run, cfg, self.raw_recipe, lora, self.rollout)


def resolve(recipe: str, stage: str, stage_cls: type, overrides: list[str] | None = None) -> Resolved:
    """Defaults < recipe < overrides, strictly checked."""
    name, raw = load_recipe(recipe)
    known = set(SHARED_SECTIONS) | set(STAGE_SECTIONS) | {"description"}
    for key in raw:
        if key not in known:
            raise ConfigError(f"unknown recipe section {key!r} in {name}; valid sections: {', '.join(sorted(known))}")
    shared = {k: cls() for k, cls in SHARED_SECTIONS.items()}
    for k, obj in shared.items():
        if raw.get(k) is not None:
            merge_into(obj, raw[k], k)
    stage_cfg = stage_cls()
    if raw.get(stage) is not None:
        merge_into(stage_cfg, raw[stage], stage)
    stage_fields = {f.name for f in fields(stage_cfg)}
    for key, value in parse_overrides(overrides or []):
        head, _, rest = key.partition(".")
        if not rest and head in stage_fields:
            merge_into(stage_cfg, {head: value}, stage)
        elif head == stage and rest:
            merge_into(stage_cfg, _nest(rest, value), stage)
        elif head in shared and rest:
            merge_into(shared[head], _nest(rest, value), head)
        elif head == "model" and not rest:
            merge_into(shared["model"], {"path": value}, "model")  # `model=PATH` sugar
        elif head in STAGE_SECTIONS and rest:
            # Another stage's field (e.g. `sft.max_steps=50` while running dpo): it configures that
            # stage when this one builds it first. Checked by `check_stage_sections` before anything runs.
            raw = dict(raw)
            raw[head] = _deep_merge(raw.get(head) or {}, _nest(rest, value))
        else:
            valid = ", ".join(sorted(stage_fields))
            raise ConfigError(f"unknown config key {key!r} for stage {stage!r}; valid keys: {valid} "
                              f"(or dotted: task.*, model.*, run.*, lora.*, rollout.*, {stage}.*)")
    res = Resolved(name, stage, shared["task"], shared["model"], shared["run"], stage_cfg, raw, shared["lora"],
                   shared["rollout"])
    unknown = sorted(set(res.lora.stages) - set(STAGE_SECTIONS))
    if unknown:
        raise ConfigError(f"config key 'lora.stages': unknown stage(s) {unknown}; stages: {', '.join(STAGE_SECTIONS)}")
    if res.lora.enabled and (res.lora.r < 1 or res.lora.alpha <= 0 or not 0 <= res.lora.dropout < 1):
        raise ConfigError(f"config keys lora.r / lora.alpha / lora.dropout: need r >= 1, alpha > 0, 0 <= dropout < 1 "
                          f"(got {res.lora.r}, {res.lora.alpha}, {res.lora.dropout})")
    res.run.report_to = trackers.parse_report_to(res.run.report_to)
    if res.model.dtype != "float32":
        problem = dtype_problem(res.model.dtype)
        if problem:
            raise ConfigError(problem)
    return res


def _deep_merge(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in extra.items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def check_stage_sections(res: "Resolved", stage_classes: dict[str, type]) -> None:
    """Strictly check every stage section of the recipe (and its command-line overrides), not only the
    stage being run: a typo in `sft:` must stop `posttrain dpo` before any model loads."""
    for name, cls in stage_classes.items():
        if name != res.stage and res.raw_recipe.get(name) is not None:
            res.for_stage(name, cls)


def _nest(dotted: str, value: Any) -> dict[str, Any]:
    head, _, rest = dotted.partition(".")
    return {head: _nest(rest, value) if rest else value}


def save_resolved(res: Resolved, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(yaml.safe_dump(res.to_dict(), sort_keys=False))
    tmp.replace(path)


def describe_fields(cls: type, prefix: str = "") -> list[tuple[str, str, str, str]]:
    """(key, type, default, doc) for `--help`."""
    docs = field_docs(cls)
    hints = _hints(cls)
    rows = []
    inherited = {f.name for base in cls.__mro__[1:] if is_dataclass(base) for f in fields(base)}
    # the class's own fields first, then those of its base (a trainer's, then the training block's)
    for f in sorted(fields(cls), key=lambda f: f.name in inherited):
        tp = hints[f.name]
        key = f"{prefix}{f.name}"
        if is_dataclass(tp):
            rows.extend(describe_fields(tp, key + "."))
            continue
        default = f.default if f.default is not dataclasses.MISSING else (
            f.default_factory() if f.default_factory is not dataclasses.MISSING else "")  # type: ignore[misc]
        rows.append((key, _type_name(tp), repr(default), docs.get(f.name, "")))
    return rows
