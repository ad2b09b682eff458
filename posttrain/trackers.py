"""Experiment trackers: `run.report_to` streams every row of metrics.jsonl to TensorBoard, wandb, trackio or MLflow.

Built on accelerate's tracker classes (`accelerate.tracking.*Tracker`), never on a hand-written client: each is
started, given the resolved config once, sent every logged metric, and finished by `Trackers`, which
`loop.MetricsLog` owns (so no trainer holds tracker code). Only the main process reports.

Where each writes (nothing outside the run directory unless the tracker's own environment says so):
- tensorboard: `<run_dir>/tensorboard/<recipe>-<stage>/` (event files; the config as hparams and a yaml file).
  A resumed run purges the events after its checkpoint's step (`SummaryWriter(purge_step=...)`), as metrics.jsonl
  drops its rows after that step, so the curve has no duplicated tail.
- wandb: `<run_dir>/wandb/` (`dir=`), project `posttrain-<recipe>`, run `<recipe>-<stage>`; online or offline as
  the user's wandb settings say (`WANDB_MODE=offline` for no network); wandb's own debug logs go to its cache dir
  (`WANDB_CACHE_DIR`, default `~/.cache/wandb`). The run id is kept in
  `<run_dir>/wandb-run-id`, so a resumed stage continues the same wandb run (`resume="allow"`).
- trackio: its own local store (`TRACKIO_DIR`, default `~/.cache/huggingface/trackio`, where `trackio show` reads),
  project `posttrain-<recipe>`, run `<recipe>-<stage>`.
- mlflow: `MLFLOW_TRACKING_URI` when set, else the SQLite store `<run_dir>/mlflow.db` (mlflow's own default
  would be `./mlflow.db` in the working directory; `mlflow ui --backend-store-uri sqlite:///<run_dir>/mlflow.db`); experiment `posttrain-<recipe>`, run `<recipe>-<stage>`.

Tables (saved rollouts, `log_table`) go to the trackers that take them (wandb); the others have the JSONL files.

Each tracker is an optional extra: `pip install "posttrain[tensorboard]"` (or wandb, trackio, mlflow). Asking for
one that is not installed, or for an unknown name, is a one-line ConfigError when the config resolves (so
`posttrain validate` catches it too), before any model loads.
"""

from __future__ import annotations

import importlib.util
import json
import os
import uuid
from pathlib import Path
from typing import Any

from posttrain.errors import ConfigError

# name -> (module that must import, the pip command that installs it)
KNOWN: dict[str, tuple[str, str]] = {
    "tensorboard": ("tensorboard", 'pip install "posttrain[tensorboard]"'),
    "wandb": ("wandb", 'pip install "posttrain[wandb]"'),
    "trackio": ("trackio", 'pip install "posttrain[trackio]"'),
    "mlflow": ("mlflow", 'pip install "posttrain[mlflow]"'),
}


def parse_report_to(value: Any) -> list[str]:
    """`run.report_to` as a list of tracker names: "none" / "" / [] -> [], "tensorboard" -> ["tensorboard"],
    "tensorboard,wandb" or a YAML list -> both. Unknown or uninstalled names are a ConfigError."""
    if value is None:
        return []
    if isinstance(value, str):
        items = [v.strip() for v in value.split(",")]
    elif isinstance(value, (list, tuple)):
        items = [str(v).strip() for v in value]
    else:
        raise ConfigError(f"config key 'run.report_to': expected tracker names (none, {', '.join(KNOWN)}), got {value!r}")
    names = [v for v in items if v and v != "none"]
    if "none" in items and names:
        raise ConfigError(f"config key 'run.report_to': 'none' cannot be combined with {names}")
    out: list[str] = []
    for name in names:
        if name not in KNOWN:
            raise ConfigError(f"config key 'run.report_to': unknown tracker {name!r}; choose from none, {', '.join(KNOWN)}")
        module, pip = KNOWN[name]
        if importlib.util.find_spec(module) is None:
            raise ConfigError(f"config key 'run.report_to': {name} is not installed ({pip})")
        if name not in out:
            out.append(name)
    return out


def flat_config(obj: Any, prefix: str = "", sep: str = ".") -> dict[str, bool | int | float | str]:
    """A nested mapping as one level of `sep`-joined keys with scalar values (lists and None as JSON text), what every
    tracker's hyperparameter view takes."""
    out: dict[str, bool | int | float | str] = {}
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.update(flat_config(v, f"{prefix}{k}{sep}", sep))
        return out
    key = prefix[: -len(sep)] if prefix else prefix
    out[key] = obj if isinstance(obj, (bool, int, float, str)) else json.dumps(obj)
    return out


def numeric(values: dict[str, Any]) -> dict[str, float]:
    """The numeric entries of a metrics row (text and lists stay in metrics.jsonl only)."""
    return {k: float(v) for k, v in values.items()
            if isinstance(v, (int, float)) and not isinstance(v, bool) and v == v}


class Trackers:
    """The trackers of one stage's run, started lazily at the first log (so a resumed run knows its step)."""

    def __init__(self, names: list[str], run_dir: Path, recipe: str, stage: str, config: dict[str, Any]):
        self.names = list(names)
        self.run_dir = Path(run_dir)
        self.project = f"posttrain-{recipe}"
        self.run_name = f"{recipe}-{stage}"
        self.config = flat_config(config)
        self.resume_step = 0
        self.open: list[Any] = []
        self.started = False

    def _make(self, name: str):
        from accelerate import tracking

        if name == "tensorboard":
            kwargs = {"purge_step": self.resume_step + 1} if self.resume_step else {}
            return tracking.TensorBoardTracker(self.run_name, self.run_dir / "tensorboard", **kwargs)
        if name == "wandb":
            id_file = self.run_dir / "wandb-run-id"
            if id_file.is_file():
                run_id = id_file.read_text().strip()
            else:
                run_id = uuid.uuid4().hex[:12]  # wandb ids: lower-case letters and digits
                id_file.write_text(run_id + "\n")
            (self.run_dir / "wandb").mkdir(parents=True, exist_ok=True)
            import wandb

            # console="off": wandb must not wrap this process's stdout (the console line is ours); quiet: no banner.
            return tracking.WandBTracker(self.project, name=self.run_name, dir=str(self.run_dir), id=run_id,
                                         resume="allow", settings=wandb.Settings(console="off", quiet=True))
        if name == "trackio":
            return tracking.TrackioTracker(self.project, name=self.run_name, resume="allow")
        if name == "mlflow":
            import mlflow

            if not os.environ.get("MLFLOW_TRACKING_URI"):  # else mlflow's default: ./mlflow.db in the working dir
                mlflow.set_tracking_uri(f"sqlite:///{(self.run_dir / 'mlflow.db').resolve()}")
            return tracking.MLflowTracker(self.project, run_name=self.run_name)
        raise ConfigError(f"unknown tracker {name!r}")  # parse_report_to refuses it first

    def start(self) -> None:
        if self.started:
            return
        self.started = True
        self.run_dir.mkdir(parents=True, exist_ok=True)
        for name in self.names:
            tracker = self._make(name)
            tracker.start()
            tracker.store_init_configuration(self.config)
            self.open.append(tracker)

    def log(self, values: dict[str, Any], step: int) -> None:
        self.start()
        row = numeric(values)
        if row:
            for tracker in self.open:
                tracker.log(row, step=step)

    def log_table(self, name: str, rows: list[dict[str, Any]], step: int) -> None:
        """Rows of one table (e.g. a step's saved rollouts) to the trackers that show tables."""
        if not rows:
            return
        self.start()
        columns = list(rows[0])
        cell = lambda v: v if v is None or isinstance(v, (int, float, str, bool)) else json.dumps(v)  # noqa: E731
        data = [[cell(r.get(c)) for c in columns] for r in rows]
        for tracker in self.open:
            if hasattr(tracker, "log_table"):
                tracker.log_table(name, columns=columns, data=data, step=step)

    def finish(self) -> None:
        for tracker in self.open:
            tracker.finish()
        self.open = []
