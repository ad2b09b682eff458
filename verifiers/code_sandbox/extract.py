"""Code extraction and reference parsing (parent side; never executes candidate code).

The extraction rule and the reference format: the package docstring, verifiers/code_sandbox/__init__.py.
"""
from __future__ import annotations

import ast
import builtins
import re
from dataclasses import dataclass
from typing import Any

_FENCE = re.compile(r"```[ \t]*([A-Za-z0-9_+.-]*)[^\n]*\n(.*?)(?:^[ \t]*```|\Z)", re.S | re.M)
_IMPORT_LINE = re.compile(r"^(?:from[ \t]+\S+[ \t]+)?import[ \t].*$", re.M)
_PY_TAGS = {"python", "py", "python3", "py3"}


def _defines(code: str, name: str) -> bool:
    return re.search(r"^[ \t]*(?:async[ \t]+)?def[ \t]+" + re.escape(name) + r"[ \t]*\(", code, re.M) is not None


_TOP_DEF = re.compile(r"^(?:async[ \t]+)?(?:def|class)[ \t]+(\w+)", re.M)


def extract_code(completion: str) -> str | None:
    """The submitted Python code in a completion (rule in the package docstring), or None."""
    text = completion.split("</think>")[-1]
    blocks = [(tag.lower(), body) for tag, body in _FENCE.findall(text)]
    python = [b for t, b in blocks if t in _PY_TAGS] or [b for t, b in blocks if t == ""]
    python = [b for b in python if b.strip()]
    if python:
        for block in reversed(python):
            names = _TOP_DEF.findall(block)
            if any(not (n.startswith("test") or n == "check") for n in names):
                return block
        return python[-1]
    if blocks:  # only fences in other languages
        return None
    return text if text.strip() else None


@dataclass(frozen=True)
class _Task:
    kind: str  # "check" | "asserts"
    tests: Any  # str | list[str]
    entry_point: str | None
    setup: str
    prompt: str | None
    proxies: tuple[str, ...]
    n_tests: int
    prompt_parses: bool


def _bound_and_loaded(tree: ast.AST) -> tuple[set[str], set[str]]:
    bound: set[str] = set()
    loaded: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Name):
            (loaded if isinstance(node.ctx, ast.Load) else bound).add(node.id)
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            bound.add(node.name)
        elif isinstance(node, ast.arg):
            bound.add(node.arg)
        elif isinstance(node, ast.alias):
            bound.add((node.asname or node.name).split(".")[0])
        elif isinstance(node, ast.ExceptHandler) and node.name:
            bound.add(node.name)
    return bound, loaded


def _instrument(tree: ast.Module) -> str:
    """Source of the test with a final `assert A == B` reporting both sides when it fails."""
    last = tree.body[-1]
    if (isinstance(last, ast.Assert) and last.msg is None and isinstance(last.test, ast.Compare)
            and len(last.test.ops) == 1 and isinstance(last.test.ops[0], ast.Eq)):
        got = ast.NamedExpr(target=ast.Name("_posttrain_got", ast.Store()), value=last.test.left)
        want = ast.NamedExpr(target=ast.Name("_posttrain_want", ast.Store()), value=last.test.comparators[0])
        msg = ast.parse("'got ' + repr(_posttrain_got)[:200] + ', expected ' + repr(_posttrain_want)[:200]",
                        mode="eval").body
        last = ast.Assert(test=ast.Compare(left=got, ops=[ast.Eq()], comparators=[want]), msg=msg)
        tree = ast.Module(body=tree.body[:-1] + [last], type_ignores=[])
    return ast.unparse(ast.fix_missing_locations(tree))


def _parse_reference(reference: Any) -> _Task:
    """Validate a reference; a malformed one is the problem set's bug, so this raises."""
    if not isinstance(reference, dict) or "tests" not in reference:
        raise ValueError("code reference must be a dict with 'tests' (a check(candidate) string or a list of asserts)")
    tests = reference["tests"]
    entry = reference.get("entry_point")
    setup = reference.get("setup") or ""
    prompt = reference.get("prompt")
    if entry is not None and (not isinstance(entry, str) or not entry.isidentifier()):
        raise ValueError(f"code reference 'entry_point' must be an identifier, got {entry!r}")
    if not isinstance(setup, str) or (prompt is not None and not isinstance(prompt, str)):
        raise ValueError("code reference 'setup' and 'prompt' must be strings")
    trees = []
    try:
        trees.append(ast.parse(setup))
        if isinstance(tests, str):
            tree = ast.parse(tests)
            if not any(isinstance(n, ast.FunctionDef) and n.name == "check" for n in tree.body):
                raise ValueError("code reference 'tests' string must define check(candidate)")
            trees.append(tree)
            kind, items, n_tests = "check", tests, 1
        elif isinstance(tests, (list, tuple)) and tests and all(isinstance(t, str) for t in tests):
            items = []
            for t in tests:
                tree = ast.parse(t)
                if not tree.body:
                    raise ValueError("code reference has an empty test")
                if len(tree.body) == 1 and isinstance(tree.body[0], ast.Expr):
                    tree.body[0] = ast.Assert(test=tree.body[0].value, msg=None)
                trees.append(tree)
                items.append([t, _instrument(tree)])
            kind, n_tests = "asserts", len(items)
        else:
            raise ValueError("code reference 'tests' must be a string defining check() or a non-empty list of strings")
    except SyntaxError as exc:
        raise ValueError(f"code reference does not compile: {exc}") from exc
    bound: set[str] = set()
    loaded: set[str] = set()
    for tree in trees:
        b, l = _bound_and_loaded(tree)
        bound |= b
        loaded |= l
    proxies = set(loaded - bound - set(dir(builtins)))
    if entry:
        proxies.add(entry)
    try:
        prompt_parses = prompt is not None and bool(ast.parse(prompt).body)
    except SyntaxError:
        prompt_parses = False
    return _Task(kind, items, entry, setup, prompt, tuple(sorted(proxies)), n_tests, prompt_parses)
