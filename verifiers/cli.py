"""Command line for the verifier layer: list, audit, score.

    python -m posttrain.verifiers.cli list        (the last line says which code sandbox runs: bubblewrap or fallback)
    python -m posttrain.verifiers.cli audit math --n 50 --seed 0 [--json report.json]
    python -m posttrain.verifiers.cli audit my_checks.py:grade --problems problems.jsonl
    python -m posttrain.verifiers.cli score math rollouts.jsonl --completion-field completion --reference-field answer

(`posttrain verifiers` and `posttrain verify audit|score ...` call `main` with the same arguments.)

Verifier names are registry specs: a built-in or entry-point name, `path/to/file.py:name`, or a
composition like `0.9*math+0.1*format`; `-o KEY=VALUE` (repeatable) passes options to it
(VALUE is read as JSON when it parses, else as a string: `-o rel_tol=1e-4 -o tags='["answer"]'`).

Problems files (audit --problems) are JSONL rows {"prompt": str (optional), "reference": any,
"gold": str}. Score files are JSONL rows holding the two named fields. A bad file or row is one
line naming the file, the line and the field, with exit code 2. `audit` exits 1 when it finds
false positives, false negatives or verifier errors; `score` exits 0 after printing count,
mean score, pass rate and a histogram of reasons (`--out FILE.jsonl` writes one verdict per row).
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import sys
from typing import Any

from posttrain.verifiers.base import AuditProblem


class UsageError(Exception):
    """A user error: printed as one line, exit code 2."""


def _options(pairs: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for pair in pairs or []:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip().isidentifier():
            raise UsageError(f"bad option {pair!r}; expected KEY=VALUE, e.g. -o rel_tol=1e-4")
        try:
            out[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            out[key.strip()] = value
    return out


def _verifier(name: str, options: dict[str, Any]):
    from posttrain.verifiers.registry import get_verifier

    try:
        return get_verifier(name, **options)
    except (ValueError, ImportError) as e:
        raise UsageError(str(e)) from None


def _read_jsonl(path: str) -> list[tuple[int, dict]]:
    if not os.path.isfile(path):
        raise UsageError(f"{path}: no such file")
    rows = []
    with open(path, encoding="utf-8") as f:
        for lineno, line in enumerate(f, 1):
            if not line.strip():
                continue
            try:
                row = json.loads(line)
            except json.JSONDecodeError as e:
                raise UsageError(f"{path} line {lineno}: invalid JSON ({e.msg})") from None
            if not isinstance(row, dict):
                raise UsageError(f"{path} line {lineno}: expected a JSON object, got {type(row).__name__}")
            rows.append((lineno, row))
    if not rows:
        raise UsageError(f"{path}: no rows")
    return rows


def _field(path: str, lineno: int, row: dict, name: str, want_str: bool) -> Any:
    if name not in row:
        raise UsageError(f"{path} line {lineno}: missing field {name!r} (fields: {', '.join(sorted(row)) or 'none'})")
    value = row[name]
    if want_str and not isinstance(value, str):
        raise UsageError(f"{path} line {lineno}: field {name!r} must be a string, got {type(value).__name__}")
    if value is None:
        raise UsageError(f"{path} line {lineno}: field {name!r} is null")
    return value


def _load_problems(path: str) -> list[AuditProblem]:
    problems = []
    for lineno, row in _read_jsonl(path):
        prompt = row.get("prompt", "")
        if not isinstance(prompt, str):
            raise UsageError(f"{path} line {lineno}: field 'prompt' must be a string, got {type(prompt).__name__}")
        problems.append(AuditProblem(prompt=prompt, reference=_field(path, lineno, row, "reference", False),
                                     gold=_field(path, lineno, row, "gold", True)))
    return problems


def cmd_list(args: argparse.Namespace) -> int:
    from posttrain.verifiers.registry import list_verifiers

    rows = list_verifiers()
    width = max(len(r[0]) for r in rows)
    owidth = max(len(r[2]) for r in rows)
    print(f"{'name':{width}s}  {'origin':{owidth}s}  description")
    for name, desc, origin in rows:
        print(f"{name:{width}s}  {origin:{owidth}s}  {desc}")
    if any(name == "code" and origin == "built-in" and not desc.startswith("unavailable") for name, desc, origin in rows):
        print(_code_sandbox_line())
    return 0


def _code_sandbox_line() -> str:
    """Which sandbox the `code` verifier uses here, and what it isolates (probes once, ~0.1 s)."""
    import warnings

    try:
        from posttrain.verifiers.code_sandbox import CodeVerifier

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # the no-root fallback's warning: the line says it
            v = CodeVerifier()
        return f"code sandbox: {v.sandbox} ({v.isolation}; python {v.python})"
    except Exception as e:  # a broken sandbox must not break `list`
        return f"code sandbox: unavailable ({type(e).__name__}: {e})"


def cmd_audit(args: argparse.Namespace) -> int:
    from posttrain.verifiers.audit import run_audit
    from posttrain.verifiers.runner import VerifierError

    verifier = _verifier(args.name, _options(args.option))
    if args.problems:
        problems = _load_problems(args.problems)
        source = args.problems
    else:
        try:
            problems = verifier.audit_problems(args.n, args.seed)
        except NotImplementedError as e:
            raise UsageError(str(e)) from None
        source = f"audit_problems(n={args.n}, seed={args.seed})"
    if not problems:
        raise UsageError("no audit problems")
    try:
        report = run_audit(verifier, problems, seed=args.seed, workers=args.workers, timeout_s=args.timeout)
    except VerifierError as e:
        raise UsageError(f"audit stopped: {e}") from None
    print(f"problems: {source}")
    print(report.format())
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(report.to_dict(), f, indent=2)
        print(f"wrote {args.json}")
    return 0 if report.ok else 1


def cmd_score(args: argparse.Namespace) -> int:
    from posttrain.verifiers.runner import VerifierError, score_batch

    verifier = _verifier(args.name, _options(args.option))
    rows = _read_jsonl(args.file)
    completions, references = [], []
    for n, row in rows:  # the first bad row is the one reported
        completions.append(_field(args.file, n, row, args.completion_field, True))
        references.append(_field(args.file, n, row, args.reference_field, False))
    try:
        verdicts = score_batch(verifier, completions, references, workers=args.workers, timeout_s=args.timeout)
    except VerifierError as e:
        where = f"{args.file} line {rows[e.index][0]}: " if e.index is not None else ""
        raise UsageError(f"{where}verifier {e.verifier!r} raised {e.exc_type}: {e.message}") from None
    n = len(verdicts)
    mean = sum(v.score for v in verdicts) / n
    passed = sum(1 for v in verdicts if v.passed)
    reasons = collections.Counter(v.reason for v in verdicts)
    print(f"scored {n} rows from {args.file} with {verifier.name!r}")
    print(f"  mean score  {mean:.4f}")
    print(f"  pass rate   {passed / n:.4f} ({passed}/{n})")
    print("  reasons:")
    for reason, count in reasons.most_common():
        print(f"    {count:6d}  {reason}")
    if args.out:
        with open(args.out, "w", encoding="utf-8") as f:
            for (lineno, _), v in zip(rows, verdicts):
                f.write(json.dumps({"line": lineno, **v.to_dict()}, default=repr) + "\n")
        print(f"wrote {args.out}")
    return 0


def build_parser(prog: str = "python -m posttrain.verifiers.cli") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description="List, audit and run verifiers.")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="installed verifiers: name, origin, description")

    def common(p: argparse.ArgumentParser) -> None:
        p.add_argument("-o", "--option", action="append", default=[], metavar="KEY=VALUE",
                       help="option for the verifier (repeatable; VALUE parsed as JSON when possible)")
        p.add_argument("--workers", type=int, default=None, help="worker processes (default: CPU count, max 8)")
        p.add_argument("--timeout", type=float, default=None, help="seconds per check (default: the verifier's)")

    a = sub.add_parser("audit", help="gold/garbage/reward-hack audit of a verifier")
    a.add_argument("name", help="verifier spec: name, path/to/file.py:name, or 0.9*math+0.1*format")
    a.add_argument("--problems", metavar="FILE.jsonl", help="problems with prompt/reference/gold (default: the verifier's own)")
    a.add_argument("--n", type=int, default=50, help="number of built-in problems (default 50)")
    a.add_argument("--seed", type=int, default=0)
    a.add_argument("--json", metavar="OUT", help="write the report as JSON")
    common(a)

    s = sub.add_parser("score", help="score a JSONL file of completions")
    s.add_argument("name", help="verifier spec")
    s.add_argument("file", metavar="FILE.jsonl")
    s.add_argument("--completion-field", default="completion")
    s.add_argument("--reference-field", default="answer")
    s.add_argument("--out", metavar="FILE.jsonl", help="write one verdict per row")
    common(s)
    return parser


def main(argv: list[str] | None = None, prog: str = "python -m posttrain.verifiers.cli") -> int:
    """Run a command; returns the exit code (0 ok, 1 audit found problems, 2 user error)."""
    parser = build_parser(prog)
    try:
        args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    except SystemExit as e:  # argparse already printed usage / help
        return int(e.code or 0)
    handlers = {"list": cmd_list, "audit": cmd_audit, "score": cmd_score}
    try:
        if getattr(args, "timeout", None) is not None and not args.timeout > 0:
            raise UsageError(f"--timeout must be > 0, got {args.timeout}")
        if getattr(args, "workers", None) is not None and args.workers < 0:
            raise UsageError(f"--workers must be >= 0, got {args.workers}")
        if getattr(args, "n", 1) < 1:
            raise UsageError(f"--n must be >= 1, got {args.n}")
        return handlers[args.command](args)
    except UsageError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
