"""Find a verifier from a spec string: built-in name, entry point, `path/to/file.py:name`, or a composition.

    get_verifier("math", rel_tol=1e-4)          # built-in (lazy table below)
    get_verifier("my_plugin")                   # entry point in group "posttrain.verifiers"
    get_verifier("checks/mine.py:score")        # a Verifier subclass, an instance or a function there
    get_verifier("0.9*math + 0.1*format")       # weighted composition (see verifiers/combine.py)
    list_verifiers()                            # [(name, description, origin), ...]

Resolution order for a bare name: built-ins first, then entry points, so an installed package
cannot silently replace "math" (a shadowed entry point is still listed, marked as such).
A function `(completion, reference) -> Verdict | float | bool` is wrapped in `FunctionVerifier`;
extra keyword options are passed to the class constructor, or to the function on each call.

Errors a user can cause are one line: an unknown name is ValueError listing the available
names; a missing file, a file that fails to import, or a missing attribute is ValueError
naming the file; options a class does not take are ValueError naming the verifier. A broken
built-in (its module fails to import) is ImportError naming the module; `list_verifiers`
reports it as "unavailable: ..." rather than failing.

Modules loaded from files are registered in sys.modules under a name derived from their path
(`loaded_file_modules()`); worker processes load the same files before unpickling a verifier,
so file-defined verifiers work with every start method. A file is imported once per process.
"""
from __future__ import annotations

import hashlib
import importlib
import importlib.metadata
import importlib.util
import inspect
import math
import os
import re
import sys
from typing import Any, Callable

from posttrain.verifiers.base import Verdict, Verifier
from posttrain.verifiers.combine import WeightedVerifier

ENTRY_POINT_GROUP = "posttrain.verifiers"

BUILTINS: dict[str, str] = {
    "math": "posttrain.verifiers.math_answer:MathVerifier",
    "format": "posttrain.verifiers.format:FormatVerifier",
    "length": "posttrain.verifiers.format:LengthVerifier",
    "code": "posttrain.verifiers.code_sandbox:CodeVerifier",
    "countdown": "posttrain.verifiers.logic:CountdownVerifier",
    "knights_knaves": "posttrain.verifiers.logic:KnightsKnavesVerifier",
    "sudoku": "posttrain.verifiers.logic:SudokuVerifier",
    "logic": "posttrain.verifiers.logic:LogicVerifier",
    "gym": "posttrain.verifiers.gym:GymVerifier",  # reasoning-gym's scorers (optional extra posttrain[gym])
}

_FILE_MODULES: dict[str, str] = {}  # module name -> absolute path


class FunctionVerifier(Verifier):
    """Wrap `fn(completion, reference, **options) -> Verdict | float | bool` as a Verifier.

    A float must lie in [0, 1] (reason "score"); a bool becomes 1.0 "pass" / 0.0 "fail".
    Anything else is a bug in the function and raises. The function must be defined at module
    level to run in worker processes.
    """

    def __init__(self, fn: Callable[..., Any], name: str | None = None, description: str | None = None,
                 timeout_s: float | None = None, **options: Any):
        if not callable(fn):
            raise TypeError(f"FunctionVerifier needs a callable, got {type(fn).__name__}")
        self.fn = fn
        self.options = options
        self.name = name or getattr(fn, "__name__", "function")
        self.description = description or _doc_line(fn) or f"function {getattr(fn, '__qualname__', fn)!s}"
        if timeout_s is not None:
            self.timeout_s = float(timeout_s)

    def check(self, completion: str, reference: Any) -> Verdict:
        out = self.fn(completion, reference, **self.options)
        if isinstance(out, Verdict):
            return out
        if isinstance(out, bool):
            return Verdict(1.0 if out else 0.0, "pass" if out else "fail")
        if isinstance(out, (int, float)):
            if isinstance(out, float) and math.isnan(out) or not 0.0 <= out <= 1.0:
                raise ValueError(f"function verifier {self.name!r} returned {out!r}, outside [0, 1]")
            return Verdict(float(out), "score")
        raise TypeError(f"function verifier {self.name!r} returned {type(out).__name__}; "
                        "expected a Verdict, a float in [0, 1] or a bool")


def _doc_line(obj: Any) -> str:
    doc = inspect.getdoc(obj) or ""
    return doc.strip().splitlines()[0] if doc.strip() else ""


def _describe(obj: Any) -> str:
    if isinstance(obj, Verifier) or (isinstance(obj, type) and issubclass(obj, Verifier)):
        if getattr(obj, "description", ""):
            return obj.description
    return _doc_line(obj) or "(no description)"


def as_verifier(obj: Any, name: str, origin: str, **options: Any) -> Verifier:
    """Turn a loaded object (Verifier subclass, instance, or function) into a Verifier instance."""
    if isinstance(obj, type) and issubclass(obj, Verifier):
        try:
            inst = obj(**options)
        except TypeError as e:
            raise ValueError(f"verifier {name!r} ({origin}): bad options {sorted(options)}: {e}") from e
    elif isinstance(obj, Verifier):
        if options:
            raise ValueError(f"verifier {name!r} ({origin}) is an instance and takes no options; got {sorted(options)}")
        inst = obj
    elif isinstance(obj, type):
        raise ValueError(f"{origin}: {name!r} is a class that does not subclass posttrain.verifiers.base.Verifier")
    elif callable(obj):
        inst = FunctionVerifier(obj, name=name, **options)
    else:
        raise ValueError(f"{origin}: {name!r} is a {type(obj).__name__}, not a Verifier subclass, instance or function")
    if not inst.name:
        inst.name = name
    return inst


# -- files ---------------------------------------------------------------------------


def _module_name_for(path: str) -> str:
    stem = re.sub(r"\W", "_", os.path.splitext(os.path.basename(path))[0])
    return f"posttrain_verifier_file_{hashlib.sha1(path.encode()).hexdigest()[:12]}_{stem}"


def _import_file_module(modname: str, path: str):
    spec = importlib.util.spec_from_file_location(modname, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load {path} as a Python module")
    module = importlib.util.module_from_spec(spec)
    sys.modules[modname] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        sys.modules.pop(modname, None)
        raise
    _FILE_MODULES[modname] = path
    return module


def loaded_file_modules() -> list[tuple[str, str]]:
    """(module name, path) of every verifier file loaded in this process (for worker processes)."""
    return sorted(_FILE_MODULES.items())


def import_spec_file(path: str, attr: str, what: str = "verifier", example: str = "my_verifier"):
    """(module, its name in sys.modules) of the Python file of a `path.py:attr` spec of a `what` (a verifier, an
    environment), imported once per process; one-line ValueErrors naming the file."""
    abspath = os.path.abspath(os.path.expanduser(path))
    if not os.path.isfile(abspath):
        raise ValueError(f"{what} file not found: {path}")
    if not attr:
        raise ValueError(f"{what} spec {path}: missing ':name' (e.g. {path}:{example})")
    modname = _module_name_for(abspath)
    module = sys.modules.get(modname)
    if module is None:
        try:
            module = _import_file_module(modname, abspath)
        except Exception as e:
            raise ValueError(f"error importing {what} file {path}: {type(e).__name__}: {e}") from e
    return module, modname


def load_file(path: str, attr: str, **options: Any) -> Verifier:
    """The verifier `attr` defined in the Python file `path`."""
    module, modname = import_spec_file(path, attr)
    if not hasattr(module, attr):
        defined = sorted(k for k, v in vars(module).items()
                         if not k.startswith("_") and (callable(v) or isinstance(v, Verifier))
                         and getattr(v, "__module__", modname) == modname)
        raise ValueError(f"verifier file {path} has no attribute {attr!r} (it defines: {', '.join(defined) or 'nothing callable'})")
    return as_verifier(getattr(module, attr), attr, f"file {path}", **options)


# -- entry points and built-ins ---------------------------------------------------------


def _entry_points() -> list:
    try:
        eps = importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)
    except TypeError:  # very old importlib.metadata without selection
        eps = importlib.metadata.entry_points().get(ENTRY_POINT_GROUP, [])  # type: ignore[attr-defined]
    except Exception:
        return []
    return list(eps)


def _load_target(target: str) -> Any:
    module_name, _, attr = target.partition(":")
    module = importlib.import_module(module_name)
    return getattr(module, attr)


def available_names() -> list[str]:
    names = list(BUILTINS)
    for ep in _entry_points():
        if ep.name not in names:
            names.append(ep.name)
    return names


def _is_file_spec(spec: str) -> bool:
    head = spec.rpartition(":")[0] if ":" in spec else spec
    return head.endswith(".py")


_TERM_RE = re.compile(r"^\s*(?:(?P<w>\d+(?:\.\d*)?|\.\d+)\s*\*\s*)?(?P<name>[^*+]+?)\s*$")


def _is_composition(spec: str) -> bool:
    return "+" in spec or bool(re.match(r"^\s*(?:\d+(?:\.\d*)?|\.\d+)\s*\*", spec))


def get_verifier(spec: str | Verifier, **options: Any) -> Verifier:
    """Resolve a spec to a Verifier instance (see the module docstring for the forms)."""
    if isinstance(spec, Verifier):
        if options:
            raise ValueError(f"verifier {spec.name!r} is already an instance; options {sorted(options)} cannot apply")
        return spec
    if not isinstance(spec, str) or not spec.strip():
        raise ValueError(f"verifier spec must be a non-empty string, got {spec!r}")
    spec = spec.strip()
    if _is_composition(spec):
        if options:
            raise ValueError(f"options {sorted(options)} cannot be passed to a composition spec {spec!r}; "
                             "build it with posttrain.verifiers.combine() instead")
        parts = []
        for term in spec.split("+"):
            m = _TERM_RE.match(term)
            if not m:
                raise ValueError(f"bad composition term {term!r} in {spec!r}; expected WEIGHT*NAME, e.g. 0.9*math+0.1*format")
            weight = float(m.group("w")) if m.group("w") else 1.0
            parts.append((get_verifier(m.group("name")), weight))
        return WeightedVerifier(parts, name=spec.replace(" ", ""))
    if _is_file_spec(spec):
        head, _, tail = spec.rpartition(":")
        path, attr = (head, tail) if head.endswith(".py") else (spec, "")
        return load_file(path, attr, **options)
    if spec in BUILTINS:
        target = BUILTINS[spec]
        try:
            obj = _load_target(target)
        except (ImportError, AttributeError) as e:
            raise ImportError(f"built-in verifier {spec!r} is unavailable: cannot import {target} ({type(e).__name__}: {e})") from e
        return as_verifier(obj, spec, f"built-in {target}", **options)
    for ep in _entry_points():
        if ep.name == spec:
            try:
                obj = ep.load()
            except Exception as e:
                raise ImportError(f"verifier {spec!r}: entry point {ep.value} failed to load ({type(e).__name__}: {e})") from e
            return as_verifier(obj, spec, f"entry point {ep.value}", **options)
    raise ValueError(f"unknown verifier {spec!r}; available: {', '.join(available_names())} "
                     "(or path/to/file.py:name, or a composition like 0.9*math+0.1*format)")


def list_verifiers() -> list[tuple[str, str, str]]:
    """(name, description, origin) for every built-in and installed verifier; never raises on a broken one."""
    rows: list[tuple[str, str, str]] = []
    for name, target in BUILTINS.items():
        try:
            desc = _describe(_load_target(target))
        except Exception as e:
            desc = f"unavailable: cannot import {target} ({type(e).__name__}: {e})"
        rows.append((name, desc, "built-in"))
    for ep in _entry_points():
        dist = getattr(getattr(ep, "dist", None), "name", None)
        origin = f"entry point {ep.value}" + (f" (package {dist})" if dist else "")
        if ep.name in BUILTINS:
            origin += " [shadowed by the built-in]"
        try:
            desc = _describe(ep.load())
        except Exception as e:
            desc = f"unavailable: {type(e).__name__}: {e}"
        rows.append((ep.name, desc, origin))
    return rows


def combine(*parts: Verifier | str | tuple[Verifier | str, float], name: str | None = None) -> WeightedVerifier:
    """`combine((math, 0.9), (fmt, 0.1))`: a `WeightedVerifier` of verifiers or registry names (resolved with
    `get_verifier`); a bare verifier or name gets weight 1."""
    pairs = [p if isinstance(p, tuple) else (p, 1.0) for p in parts]
    return WeightedVerifier([(get_verifier(v) if isinstance(v, str) else v, w) for v, w in pairs], name=name)
