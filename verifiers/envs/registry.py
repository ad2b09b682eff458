"""Find an environment from a spec: a built-in name, an entry point, or `path/to/file.py:Name`.

    get_env("calc")                    # built-in (table below)
    get_env("my_env")                  # entry point in group "posttrain.envs" (an installed package's)
    get_env("envs/mine.py:MyEnv")      # an Environment subclass or instance defined in a file
    get_env("calc", max_turns=3)       # keyword options go to the class (or replace an instance's limits)
    list_envs()                        # [(name, description, origin), ...]

As for verifiers: built-ins first, then entry points; a bad spec is one ValueError line naming the file, the name
or the option.
"""
from __future__ import annotations

import dataclasses
import importlib
import importlib.metadata
import inspect
from typing import Any

from posttrain.verifiers.envs.base import Environment, Limits
from posttrain.verifiers.registry import import_spec_file

ENTRY_POINT_GROUP = "posttrain.envs"
BUILTINS: dict[str, str] = {
    "calc": "posttrain.verifiers.envs.calc:CalcEnv",
    "lookup": "posttrain.verifiers.envs.lookup:LookupEnv",
    "calc-words": "posttrain.verifiers.envs.calc:WordCalcEnv",
}
LIMIT_FIELDS = {f.name for f in dataclasses.fields(Limits)}


def _entry_points() -> list:
    try:
        return list(importlib.metadata.entry_points(group=ENTRY_POINT_GROUP))
    except Exception:
        return []


def _instantiate(obj: Any, where: str, options: dict[str, Any]) -> Environment:
    limits = {k: options.pop(k) for k in list(options) if k in LIMIT_FIELDS}
    if inspect.isclass(obj) and issubclass(obj, Environment):
        try:
            env = obj(**options)
        except TypeError as e:
            raise ValueError(f"environment {where}: {e}") from None
    elif isinstance(obj, Environment):
        if options:
            raise ValueError(f"environment {where} is an instance: options {sorted(options)} cannot be applied")
        env = obj
    else:
        raise ValueError(f"environment {where} is not an Environment subclass or instance (got {type(obj).__name__})")
    if limits:
        try:
            env.limits = dataclasses.replace(env.limits, **limits)
        except (TypeError, ValueError) as e:
            raise ValueError(f"environment {where}: {e}") from None
    return env


def _load_file(path: str, attr: str) -> Any:
    module, modname = import_spec_file(path, attr, "environment", "MyEnv")
    if not hasattr(module, attr):
        defined = sorted(k for k, v in vars(module).items() if inspect.isclass(v) and issubclass(v, Environment)
                         and v.__module__ == modname)
        raise ValueError(f"environment file {path} has no attribute {attr!r} (it defines: "
                         f"{', '.join(defined) or 'no Environment subclass'})")
    return getattr(module, attr)


def get_env(spec: str | Environment, **options: Any) -> Environment:
    """The environment named by `spec` (module docstring), built with `options`."""
    if isinstance(spec, Environment):
        return _instantiate(spec, repr(spec.name), dict(options))
    if not isinstance(spec, str) or not spec.strip():
        raise ValueError(f"environment spec must be a name or path.py:Name, got {spec!r}")
    spec = spec.strip()
    path, sep, attr = spec.rpartition(":")
    if sep and path.endswith(".py"):
        return _instantiate(_load_file(path, attr), spec, dict(options))
    if spec in BUILTINS:
        module, _, name = BUILTINS[spec].partition(":")
        return _instantiate(getattr(importlib.import_module(module), name), spec, dict(options))
    for ep in _entry_points():
        if ep.name == spec:
            return _instantiate(ep.load(), f"{spec} (entry point {ep.value})", dict(options))
    names = list(BUILTINS) + [ep.name for ep in _entry_points() if ep.name not in BUILTINS]
    raise ValueError(f"unknown environment {spec!r}; available: {', '.join(names)}, or path/to/file.py:Name")


def list_envs() -> list[tuple[str, str, str]]:
    """(name, description, origin) of every built-in and installed environment."""
    out = []
    for name, target in BUILTINS.items():
        module, _, attr = target.partition(":")
        try:
            cls = getattr(importlib.import_module(module), attr)
            out.append((name, cls.description or (cls.__doc__ or "").strip().splitlines()[0], "built-in"))
        except Exception as e:
            out.append((name, f"unavailable: {type(e).__name__}: {e}", "built-in"))
    for ep in _entry_points():
        if ep.name in BUILTINS:
            out.append((ep.name, f"shadowed by the built-in {ep.name!r}", f"entry point {ep.value}"))
            continue
        try:
            obj = ep.load()
            doc = getattr(obj, "description", "") or (obj.__doc__ or "").strip().splitlines()[0]
        except Exception as e:
            doc = f"unavailable: {type(e).__name__}: {e}"
        out.append((ep.name, doc, f"entry point {ep.value}"))
    return out
