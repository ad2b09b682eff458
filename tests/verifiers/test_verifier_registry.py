"""Discovery: built-ins, entry points, file.py:name, compositions, errors that name the culprit."""
import importlib.metadata
import textwrap

import pytest

from posttrain.verifiers import FunctionVerifier, VerifierPool, WeightedVerifier, get_verifier, list_verifiers, score_batch
from posttrain.verifiers import registry
from posttrain.verifiers.base import Verdict
from posttrain.verifiers.math_answer import MathVerifier

PLUGIN = textwrap.dedent('''
    from posttrain.verifiers.base import Verdict, Verifier

    class Shouty(Verifier):
        """Scores 1 when the completion is upper case."""
        name = "shouty"
        def __init__(self, strict=False):
            self.strict = strict
        def check(self, completion, reference):
            ok = completion.isupper()
            return Verdict(1.0 if ok else 0.0, "ok" if ok else "too quiet")

    instance = Shouty(strict=True)

    def same_length(completion, reference, slack=0):
        """1 when the completion has the reference's length."""
        return abs(len(completion) - len(reference)) <= slack

    NOT_A_VERIFIER = 42
''')


@pytest.fixture
def plugin_file(tmp_path):
    path = tmp_path / "my_checks.py"
    path.write_text(PLUGIN)
    return path


def test_builtin_by_name_with_options():
    v = get_verifier("math", rel_tol=1e-3)
    assert isinstance(v, MathVerifier) and v.rel_tol == 1e-3 and v.name == "math"
    assert get_verifier("format").name == "format"
    assert get_verifier("length", max_chars=10).budget == 10


def test_builtin_bad_options_name_the_verifier():
    with pytest.raises(ValueError, match="verifier 'math'.*bad options.*no_such_option"):
        get_verifier("math", no_such_option=1)


def test_unknown_name_is_one_clear_line():
    with pytest.raises(ValueError) as info:
        get_verifier("maht")
    msg = str(info.value)
    assert "\n" not in msg
    assert msg.startswith("unknown verifier 'maht'; available: math, format, length")
    assert "file.py:name" in msg


def test_instances_pass_through():
    v = MathVerifier()
    assert get_verifier(v) is v
    with pytest.raises(ValueError, match="already an instance"):
        get_verifier(v, rel_tol=1)
    with pytest.raises(ValueError):
        get_verifier("  ")


def test_list_verifiers_reports_every_builtin():
    rows = {name: (desc, origin) for name, desc, origin in list_verifiers()}
    assert set(registry.BUILTINS) <= set(rows)
    assert rows["math"] == (MathVerifier.description, "built-in")
    for name in registry.BUILTINS:
        desc, origin = rows[name]
        assert origin == "built-in" and desc  # available, or "unavailable: ..." for modules not there yet


def test_broken_builtin_is_reported_not_raised(monkeypatch):
    monkeypatch.setitem(registry.BUILTINS, "broken", "posttrain.verifiers.no_such_module:Thing")
    rows = {name: desc for name, desc, _ in list_verifiers()}
    assert rows["broken"].startswith("unavailable: cannot import posttrain.verifiers.no_such_module:Thing (ModuleNotFoundError")
    with pytest.raises(ImportError, match="built-in verifier 'broken' is unavailable: cannot import posttrain.verifiers.no_such_module"):
        get_verifier("broken")


def test_file_spec_class_instance_function(plugin_file):
    cls_v = get_verifier(f"{plugin_file}:Shouty", strict=True)
    assert cls_v.name == "shouty" and cls_v.strict is True
    assert cls_v.check("HI", None) == Verdict(1.0, "ok")
    inst = get_verifier(f"{plugin_file}:instance")
    assert inst.strict is True and inst.check("hi", None).reason == "too quiet"
    fn = get_verifier(f"{plugin_file}:same_length", slack=1)
    assert isinstance(fn, FunctionVerifier) and fn.name == "same_length"
    assert fn.description == "1 when the completion has the reference's length."
    assert fn.check("abc", "ab") == Verdict(1.0, "pass")
    assert fn.check("abcd", "ab") == Verdict(0.0, "fail")


def test_file_spec_errors_name_the_file(tmp_path, plugin_file):
    missing = tmp_path / "nope.py"
    with pytest.raises(ValueError, match=f"verifier file not found: {missing}"):
        get_verifier(f"{missing}:x")
    with pytest.raises(ValueError, match=rf"verifier file {plugin_file} has no attribute 'Nope' \(it defines: .*Shouty.*same_length"):
        get_verifier(f"{plugin_file}:Nope")
    with pytest.raises(ValueError, match="missing ':name'"):
        get_verifier(str(plugin_file))
    with pytest.raises(ValueError, match="'NOT_A_VERIFIER' is a int, not a Verifier"):
        get_verifier(f"{plugin_file}:NOT_A_VERIFIER")
    broken = tmp_path / "broken.py"
    broken.write_text("def oops(:\n")
    with pytest.raises(ValueError, match=f"error importing verifier file {broken}: SyntaxError"):
        get_verifier(f"{broken}:oops")


@pytest.mark.parametrize("start_method", ["fork", "spawn"])
def test_file_verifier_runs_in_worker_processes(plugin_file, start_method):
    v = get_verifier(f"{plugin_file}:Shouty")
    assert registry.loaded_file_modules()
    with VerifierPool(workers=1, timeout_s=30, start_method=start_method) as pool:
        out = pool.score(v, ["YES", "no"], [None, None])
    assert [o.score for o in out] == [1.0, 0.0]
    fn = get_verifier(f"{plugin_file}:same_length")
    assert [o.score for o in score_batch(fn, ["ab", "a"], ["xy", "xy"], workers=1)] == [1.0, 0.0]


def fake_entry_points(eps):
    def entry_points(group=None, **kw):
        return [ep for ep in eps if group is None or ep.group == group]
    return entry_points


def test_entry_points(monkeypatch, tmp_path, plugin_file):
    monkeypatch.syspath_prepend(str(tmp_path))
    group = registry.ENTRY_POINT_GROUP
    eps = [
        importlib.metadata.EntryPoint(name="shouty", value="my_checks:Shouty", group=group),
        importlib.metadata.EntryPoint(name="same_length", value="my_checks:same_length", group=group),
        importlib.metadata.EntryPoint(name="math", value="my_checks:Shouty", group=group),
        importlib.metadata.EntryPoint(name="ghost", value="no_such_plugin_module:Thing", group=group),
        importlib.metadata.EntryPoint(name="other", value="my_checks:Shouty", group="some.other.group"),
    ]
    monkeypatch.setattr(importlib.metadata, "entry_points", fake_entry_points(eps))
    v = get_verifier("shouty", strict=True)
    assert v.name == "shouty" and v.strict is True
    assert get_verifier("same_length").check("ab", "cd").score == 1.0
    assert isinstance(get_verifier("math"), MathVerifier)  # built-ins win
    with pytest.raises(ImportError, match="entry point no_such_plugin_module:Thing failed to load"):
        get_verifier("ghost")
    with pytest.raises(ValueError, match="available: math, format, length, .*shouty, same_length, ghost"):
        get_verifier("other")
    rows = {(name, origin): desc for name, desc, origin in list_verifiers()}
    assert rows[("shouty", "entry point my_checks:Shouty")] == "Scores 1 when the completion is upper case."
    assert rows[("math", "entry point my_checks:Shouty [shadowed by the built-in]")]
    assert rows[("ghost", "entry point no_such_plugin_module:Thing")].startswith("unavailable: ModuleNotFoundError")


def test_composition_spec():
    v = get_verifier("0.9*math + 0.1*format")
    assert isinstance(v, WeightedVerifier)
    assert [(label, w) for label, _, w in v.parts] == [("math", 0.9), ("format", 0.1)]
    assert v.name == "0.9*math+0.1*format"
    assert v.check(r"\boxed{3}", "3").score == 1.0
    assert get_verifier("math + format").parts[1][2] == 1.0
    with pytest.raises(ValueError, match="bad composition term"):
        get_verifier("0.9*math + ")
    with pytest.raises(ValueError, match="cannot be passed to a composition"):
        get_verifier("math+format", rel_tol=1)
    with pytest.raises(ValueError, match="unknown verifier 'nope'"):
        get_verifier("0.5*math+0.5*nope")


def test_function_verifier_results():
    assert FunctionVerifier(lambda c, r: 0.25).check("", "") == Verdict(0.25, "score")
    assert FunctionVerifier(lambda c, r: Verdict(0.5, "half")).check("", "") == Verdict(0.5, "half")
    with pytest.raises(ValueError, match="outside"):
        FunctionVerifier(lambda c, r: 1.5, name="big").check("", "")
    with pytest.raises(ValueError, match="outside"):
        FunctionVerifier(lambda c, r: float("nan"), name="nan").check("", "")
    with pytest.raises(TypeError, match="expected a Verdict"):
        FunctionVerifier(lambda c, r: None, name="none").check("", "")


def test_name_defaults_to_the_spec_name(tmp_path):
    path = tmp_path / "unnamed.py"
    path.write_text("from posttrain.verifiers.base import Verifier, Verdict\n"
                    "class Anon(Verifier):\n    def check(self, c, r):\n        return Verdict(1.0, 'ok')\n")
    assert get_verifier(f"{path}:Anon").name == "Anon"
