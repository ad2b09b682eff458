"""`posttrain plot RUN_DIR`: PNGs of a stage's metrics.jsonl, one figure per family of metrics.

Every stage logs flat rows (`step`, `time`, then its metrics); `plot_run` groups the metric names into families
(loss, learning rate, KL, entropy, curriculum, evaluation (accuracy, win-rate, gold reward), reward and its
parts, lengths, throughput and timing, the rest) by name, and draws one panel per metric against the step, so a stage that logs a new metric
gets it plotted without code here. A metric logged at some steps only (held-out evaluations) is drawn with
markers at those steps. matplotlib is an optional dependency (`pip install "posttrain[plots]"`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from posttrain.errors import DataError

# (family, the words that put a metric name into it), first match wins; names are matched in lower case.
FAMILIES: list[tuple[str, tuple[str, ...]]] = [
    ("loss", ("loss",)),
    ("lr", ()),  # the exact name only (family_of): "lr" is inside too many other names
    ("kl", ("kl", "mismatch/")),
    ("entropy", ("entropy",)),
    ("curriculum", ("curriculum/",)),
    ("eval", ("acc", "win_rate", "eval", "gold/", "pass", "heldout")),
    ("reward", ("reward", "score", "parts/", "advantage", "margin")),
    ("length", ("length", "len", "tokens/", "truncat", "clip")),
    ("speed", ("time/", "tokens_per_s", "per_s", "seconds")),
]
MAX_PANELS = 12  # per figure; a family with more metrics is split into numbered figures


def family_of(name: str) -> str:
    low = name.lower()
    if low == "lr" or low.endswith("/lr"):
        return "lr"
    for family, words in FAMILIES:
        if any(w in low for w in words):
            return family
    return "other"


def read_metrics(run_dir: str | Path) -> tuple[Path, dict[str, list[tuple[int, float]]]]:
    """metrics.jsonl of a run directory (or the file itself) as {metric: [(step, value), ...]}; numbers only.
    A torn last line (a killed run) is skipped; any other malformed line is a DataError naming file and line."""
    path = Path(run_dir)
    path = path / "metrics.jsonl" if path.is_dir() else path
    if not path.is_file():
        raise DataError(f"{path}: no metrics.jsonl here (give a stage's run directory, e.g. runs/tiny-math/grpo)")
    series: dict[str, list[tuple[int, float]]] = {}
    lines = path.read_text().split("\n")  # JSON Lines: only \n ends a row (not \u2028)
    for i, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            if i == len(lines):
                continue  # torn last line
            raise DataError(f"{path}, line {i}: not JSON") from None
        if not isinstance(row, dict) or not isinstance(row.get("step"), (int, float)):
            raise DataError(f"{path}, line {i}: a metrics row needs a numeric 'step'")
        for k, v in row.items():
            if k in ("step", "time") or isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                continue
            series.setdefault(k, []).append((int(row["step"]), float(v)))
    if not series:
        raise DataError(f"{path}: no numeric metrics to plot")
    return path, series


def plot_run(run_dir: str | Path, out_dir: str | Path | None = None, title: str = "") -> list[Path]:
    """One PNG per metric family under `out_dir` (default `<run_dir>/plots/`); returns the paths written."""
    path, series = read_metrics(run_dir)
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise DataError('matplotlib is not installed (pip install "posttrain[plots]"); no plots written') from None
    out = Path(out_dir) if out_dir is not None else path.parent / "plots"
    out.mkdir(parents=True, exist_ok=True)
    title = title or f"{path.parent.parent.name}/{path.parent.name}"
    by_family: dict[str, list[str]] = {}
    for name in series:
        by_family.setdefault(family_of(name), []).append(name)
    written = []
    order = [f for f, _ in FAMILIES] + ["other"]
    for family in sorted(by_family, key=order.index):
        names = sorted(by_family[family])
        chunks = [names[i:i + MAX_PANELS] for i in range(0, len(names), MAX_PANELS)]
        for c, chunk in enumerate(chunks):
            cols = min(3, len(chunk))
            rows = math.ceil(len(chunk) / cols)
            fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.0 * rows), squeeze=False)
            for ax, name in zip(axes.flat, chunk):
                pts = series[name]
                x, y = [p[0] for p in pts], [p[1] for p in pts]
                sparse = len(pts) <= 30
                ax.plot(x, y, "o-" if sparse else "-", markersize=3, linewidth=1.2)
                ax.set_title(name, fontsize=9)
                ax.set_xlabel("step", fontsize=8)
                ax.tick_params(labelsize=7)
                ax.grid(alpha=0.3)
            for ax in list(axes.flat)[len(chunk):]:
                ax.set_visible(False)
            fig.suptitle(f"{title}: {family}" + (f" ({c + 1}/{len(chunks)})" if len(chunks) > 1 else ""), fontsize=10)
            fig.tight_layout()
            target = out / (f"{family}.png" if len(chunks) == 1 else f"{family}-{c + 1}.png")
            tmp = target.with_name(target.name + ".tmp.png")
            fig.savefig(tmp, dpi=90)
            plt.close(fig)
            tmp.replace(target)
            written.append(target)
    return written


def plot_runs(run_dirs: dict[str, str | Path], out: str | Path, say=print) -> dict[str, str]:
    """`plot_run` of each named run into `<out>/stage-plots/<name>/` (the reproductions' reports link them):
    {name: folder relative to `out`}. A run without metrics.jsonl is left out; one that cannot be plotted
    (no numeric metrics, no matplotlib) is said and left out."""
    written = {}
    for name, run_dir in run_dirs.items():
        if not (Path(run_dir) / "metrics.jsonl").is_file():
            continue  # e.g. no SFT stage (a real instruct model starts as it is)
        try:
            plot_run(run_dir, Path(out) / "stage-plots" / name, title=name)
        except DataError as e:
            say(f"no metric plots of {name}: {e}")
            continue
        written[name] = f"stage-plots/{name}"
    return written
