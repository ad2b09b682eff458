"""Tests for posttrain.verifiers.code_sandbox: correctness, integrity against hostile programs, containment.

Every hostile program runs under the sandbox's own (small) limits. Runs in every mode
this machine supports: bwrap, rlimits with namespaces (root + unshare), plain rlimits.
"""
from __future__ import annotations

import json
import os
import stat
import subprocess
import tempfile
import textwrap
import time
import uuid

import pytest

from posttrain.verifiers import code_sandbox as cs
from posttrain.verifiers.code_sandbox import sandbox as sandbox_module
from posttrain.verifiers.base import AuditProblem
from posttrain.verifiers.code_sandbox import CodeVerifier, extract_code, measure_overhead, sandbox_mode

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
LIMITS = dict(time_limit_s=1.5, memory_mb=160, max_processes=12, max_file_mb=2, tmpfs_mb=8)
IS_ROOT = os.geteuid() == 0


def _variants() -> list:
    out = [pytest.param(("bwrap", {}), id="bwrap",
                        marks=pytest.mark.skipif(sandbox_mode() != "bwrap", reason="bubblewrap unavailable"))]
    out.append(pytest.param(("rlimits", {}), id="rlimits"))
    out.append(pytest.param(("rlimits", {"namespaces": False}), id="rlimits-plain",
                            marks=pytest.mark.skipif(not IS_ROOT, reason="same as rlimits when not root")))
    return out


@pytest.fixture(scope="module", params=_variants())
def verifier(request) -> CodeVerifier:
    mode, extra = request.param
    v = CodeVerifier(mode=mode, **LIMITS, **extra)
    assert v.mode == mode
    return v


def _like(verifier: CodeVerifier, **options) -> CodeVerifier:
    return CodeVerifier(mode=verifier.mode, namespaces=verifier.namespaces, **LIMITS, **options)


def _sandbox_processes() -> list[str]:
    """Live processes under one of this process's per-run sandbox uids (zombies excluded). Other processes on the
    machine may run sandboxes of their own at the same time; their uids come from other ranges."""
    return sandbox_module.uid_processes()


def _sandbox_dirs() -> list[str]:
    return [n for n in os.listdir(tempfile.gettempdir()) if n.startswith(f"posttrain-sandbox-{os.getpid()}-")]


def _wait_clean(timeout: float = 2.0) -> list[str]:
    end = time.monotonic() + timeout
    while True:
        left = _sandbox_processes()
        if not left or time.monotonic() > end:
            return left
        time.sleep(0.05)


def _fenced(code: str) -> str:
    return "Here is my solution.\n```python\n" + textwrap.dedent(code) + "```\nDone."


# ------------------------------------------------------------------ pure functions
def test_extract_code_rules():
    draft_then_fix = "```python\ndef f(x):\n    return 0\n```\ntext\n```python\ndef f(x):\n    return x\n```\n" \
                     "```python\nprint(f(3))\n```\n```python\ndef test_f():\n    assert f(1) == 1\n```"
    assert extract_code(draft_then_fix) == "def f(x):\n    return x\n"  # last defining block; examples/tests skipped
    retraction = "```python\ndef f(x):\n    return x\n```\nNo wait, that's wrong:\n```python\ndef g(x):\n    return 1\n```"
    assert extract_code(retraction) == "def g(x):\n    return 1\n"  # the retraction is the submission
    assert extract_code("```\na = 1\n```\n```py\nb = 2\n```") == "b = 2\n"  # python-tagged wins
    assert extract_code("```python\nprint(1)\n```") == "print(1)\n"  # nothing defines: the last block
    assert extract_code("```python\ndef f():\n    return 1") == "def f():\n    return 1"  # unterminated fence
    assert extract_code("<think>```python\nbad\n```</think>def f(): return 2") == "def f(): return 2"
    assert extract_code("def f(): return 1") == "def f(): return 1"  # raw text
    assert extract_code("   \n") is None
    assert extract_code("```bash\nrm -rf /\n```") is None


def test_reference_validation_raises():
    v = CodeVerifier(mode="rlimits", **LIMITS)
    for bad in ([], {"entry_point": "f"}, {"tests": "assert f(1) == 1"}, {"tests": []}, {"tests": ["assert f(("]},
                {"tests": ["assert f(1)"], "entry_point": "not an identifier"}, {"tests": [1]}):
        with pytest.raises(ValueError):
            v.check("def f(x): return x", bad)


def test_reference_broken_inside_the_sandbox_raises():
    v = CodeVerifier(**LIMITS)
    with pytest.raises(ValueError, match="reference is broken"):
        v.check("def f(): return 1", {"tests": "import no_such_module_xyz\ndef check(c):\n    pass\n", "entry_point": "f"})


# ------------------------------------------------------------------ correctness
def test_audit_golds_pass_and_mutants_fail(verifier):
    problems = verifier.audit_problems(100, seed=1)
    assert len(problems) == len(cs._PROBLEMS) >= 10 and all(isinstance(p, AuditProblem) for p in problems)
    golds = verifier.check_many([p.gold for p in problems], [p.reference for p in problems], workers=4)
    assert [v.reason for v in golds] == ["passed"] * len(problems)
    assert all(v.score == 1.0 and v.details["mode"] == verifier.mode for v in golds)
    # A mutant: the gold with its last return replaced by `return None`.
    mutants = []
    for p in problems:
        head, _, _ = p.gold.rpartition("return ")
        mutants.append(head + "return None\n```\n")
    bad = verifier.check_many(mutants, [p.reference for p in problems], workers=4)
    assert all(v.score == 0.0 and v.reason.startswith("failed") for v in bad), [v.reason for v in bad]


def test_audit_problems_seeded():
    v = CodeVerifier(mode="rlimits", **LIMITS)
    assert [p.prompt for p in v.audit_problems(5, seed=3)] == [p.prompt for p in v.audit_problems(5, seed=3)]
    assert [p.prompt for p in v.audit_problems(5, seed=3)] != [p.prompt for p in v.audit_problems(5, seed=4)]
    assert len(v.audit_problems(3)) == 3


def test_humaneval_conventions(verifier):
    prompt = ("from typing import List\n\n\ndef poly(xs: List[float], x: float) -> float:\n"
              "    return sum(c * x ** i for i, c in enumerate(xs))\n\n\n"
              "def find_zero(xs: List[float]) -> float:\n    \"\"\"The root of a linear polynomial.\"\"\"\n")
    tests = "def check(candidate):\n    for xs in ([1.0, 2.0], [-4.0, 2.0]):\n        assert abs(poly(xs, candidate(xs))) < 1e-9\n"
    ref = {"tests": tests, "entry_point": "find_zero", "prompt": prompt}
    body_only = "    return -xs[0] / xs[1]\n"  # continuation of the prompt
    whole = _fenced("def find_zero(xs: List[float]) -> float:\n    return -xs[0] / xs[1]\n")  # needs the prompt's helper and import
    wrong = _fenced("def find_zero(xs):\n    return 0.0\n")
    rigged = _fenced("def poly(xs, x):\n    return 0.0\ndef find_zero(xs):\n    return 123.0\n")  # the tests keep the real poly
    r = verifier.check_many([body_only, whole, wrong, rigged], [ref] * 4, workers=4)
    assert [x.reason for x in r] == ["passed", "passed", "failed 1/1 tests", "failed 1/1 tests"]
    assert "tests line 3" in r[2].details["failures"][0]["error"]
    # No entry point: the last top-level function is the candidate.
    r = verifier.check("def helper(x):\n    return x\ndef main(x):\n    return helper(x) + 1\n",
                       {"tests": "def check(c):\n    assert c(1) == 2\n"})
    assert r.passed


def test_calls_values_exceptions_and_mutation(verifier):
    ref = {
        "setup": "from fractions import Fraction",
        "tests": [
            "xs = [3, 1, 2]\nsort_in_place(xs)\nassert xs == [1, 2, 3]",
            "assert pair(a=1, b=2) == (1, 2) and type(pair(1, 2)) is tuple",
            "assert values() == ({1}, frozenset({2}), [1], {'a': (1,)}, None, True, 1.5, b'x', Fraction(1, 3), 2**100)",
            "try:\n    pair(-1, 0)\nexcept ValueError as e:\n    assert 'negative' in str(e)\nelse:\n    raise AssertionError('no error')",
            "pair(1, 2) == (1, 2)",  # a bare expression is asserted
        ],
    }
    good = _fenced("""\
        from fractions import Fraction
        def sort_in_place(xs):
            xs.sort()
        def pair(a, b):
            if a < 0:
                raise ValueError('negative a')
            return (a, b)
        def values():
            return ({1}, frozenset({2}), [1], {'a': (1,)}, None, True, 1.5, b'x', Fraction(1, 3), 2**100)
        """)
    assert verifier.check(good, ref).reason == "passed"
    half = good.replace("xs.sort()", "pass").replace("return (a, b)", "return [a, b]")
    strict = verifier.check(half, ref)
    assert strict.score == 0.0 and strict.reason == "failed 3/5 tests"
    partial = _like(verifier, partial_credit=True).check(half, ref)
    assert partial.score == pytest.approx(2 / 5) and partial.details["tests_passed"] == 2


def test_bad_outputs_are_zero_with_reasons(verifier):
    ref = {"tests": ["assert f(1) == 2"], "entry_point": "f"}
    cases = {
        "": "no code found",
        "I cannot solve this.": "syntax error",
        "```python\ndef f(x) return x\n```": "syntax error",
        "```python\nraise RuntimeError('boom')\n```": "error on load (RuntimeError)",
        "```python\ndef g(x):\n    return x + 1\n```": "failed 1/1 tests",
        "```python\ndef f(x):\n    return 'x' * (32 << 20)\n```": "failed 1/1 tests",  # reply over the message limit
    }
    verdicts = verifier.check_many(list(cases), [ref] * len(cases), workers=4)
    for (completion, reason), verdict in zip(cases.items(), verdicts):
        assert verdict.score == 0.0 and verdict.reason == reason, (completion, verdict)
        json.dumps(verdict.to_dict())  # details are JSON-serialisable
    assert verifier.check("x" * 300_000, ref).reason == "code too long"


def test_deterministic(verifier):
    p = verifier.audit_problems(1, seed=5)[0]
    wrong = p.gold.replace("return", "return None and", 1)
    assert verifier.check(wrong, p.reference) == verifier.check(wrong, p.reference)
    # set iteration order of strings is fixed (PYTHONHASHSEED=0), so this is stable too
    ref = {"tests": ["assert order() == order()"], "entry_point": "order"}
    assert verifier.check("def order():\n    return list({'a', 'b', 'c', 'd'})\n", ref).passed


# ------------------------------------------------------------------ integrity and containment
def test_adversarial_cases_all_score_zero(verifier):
    problems = verifier.audit_problems(2, seed=0)
    completions, refs, labels = [], [], []
    for p in problems:
        for label, completion, expected in verifier.adversarial_cases(p):
            assert expected == 0.0
            completions.append(completion)
            refs.append(p.reference)
            labels.append(label)
    verdicts = verifier.check_many(completions, refs, workers=4)
    scored = {label: v for label, v in zip(labels, verdicts)}
    assert all(v.score == 0.0 for v in verdicts), [(lb, v.reason) for lb, v in zip(labels, verdicts) if v.score]
    assert scored["infinite loop"].reason == "timeout"
    assert scored["fork bomb"].reason == "timeout"
    assert scored["memory bomb"].reason == "killed (memory)"
    assert scored["early sys.exit(0)"].reason.startswith("exited early")
    assert scored["os._exit(0) at import"].reason.startswith("exited early")
    assert "File too large" in scored["huge file"].details.get("error", "")
    assert _wait_clean() == []
    assert _sandbox_dirs() == []


def test_sandbox_properties(verifier, monkeypatch):
    monkeypatch.setenv("POSTTRAIN_TEST_SECRET", "hunter2")
    probe = _fenced("""\
        import os, socket
        def probe():
            def writable(path):
                try:
                    with open(path, 'w') as f:
                        f.write('x')
                    return True
                except OSError:
                    return False
            def readable(path):
                try:
                    with open(path, 'rb') as f:
                        f.read(16)
                    return True
                except OSError:
                    return False
            try:
                socket.create_connection(('1.1.1.1', 53), timeout=1).close()
                net = True
            except OSError:
                net = False
            ppid = os.getppid()
            return {
                'uid': os.getuid(), 'cwd_writable': writable('scratch.txt'), 'home_is_cwd': os.environ.get('HOME') == os.getcwd(),
                'etc_writable': writable('/etc/posttrain-escape'), 'usr_writable': writable('/usr/posttrain-escape'),
                'env': sorted(os.environ), 'net': net,
                'parent_mem': readable('/proc/%d/mem' % ppid), 'parent_environ': readable('/proc/%d/environ' % ppid),
                'parent_fd': readable('/proc/%d/fd/0' % ppid),
                'repo_visible': os.path.exists(REPO_PATH),
            }
        """).replace("REPO_PATH", repr(REPO))
    tests = [
        "assert probe()['uid'] != 0",
        "assert probe()['cwd_writable'] and probe()['home_is_cwd']",
        "assert not probe()['etc_writable'] and not probe()['usr_writable']",
        "assert 'POSTTRAIN_TEST_SECRET' not in probe()['env'] and set(probe()['env']) <= {'PATH', 'HOME', 'TMPDIR', "
        "'LANG', 'LC_ALL', 'PWD', 'PYTHONHASHSEED', 'PYTHONDONTWRITEBYTECODE', 'PYTHONIOENCODING'}",
        "assert not probe()['parent_mem'] and not probe()['parent_environ'] and not probe()['parent_fd']",
    ]
    if verifier.mode == "bwrap" or "unshare" in verifier.isolation:
        tests.append("assert not probe()['net']")
    if verifier.mode == "bwrap" or "unshare" in verifier.isolation:  # the checkout is not in the view
        tests.append("assert not probe()['repo_visible']")
    v = verifier.check(probe, {"tests": tests, "entry_point": "probe"})
    assert v.passed, v.details
    assert v.details["mode"] == verifier.mode and v.details["isolation"] == verifier.isolation
    assert v.details["sandbox"] == verifier.sandbox == {
        "bwrap": "bubblewrap", "unshare": "fallback"}.get(verifier.isolation.split(":")[0], "fallback (no namespaces)")
    interpreter = v.details["python"].split(" (")[0]
    assert os.access(interpreter, os.X_OK) and os.stat(interpreter).st_mode & 0o001  # runnable by other users
    assert not os.path.exists("/etc/posttrain-escape")


def test_escaped_daemons_and_files_are_cleaned(verifier):
    if verifier.mode == "rlimits" and not IS_ROOT:
        pytest.skip("without root or bubblewrap, setsid() daemons can escape (documented limitation)")
    marker = f"/tmp/posttrain-escape-{uuid.uuid4().hex}"
    code = _fenced(f"""\
        import os, subprocess, time
        for _ in range(2):
            if os.fork() == 0:
                os.setsid()
                if os.fork() == 0:
                    time.sleep(60)
                os._exit(0)
        subprocess.Popen(['sleep', '60'], start_new_session=True)
        try:
            with open({marker!r}, 'w') as f:
                f.write('left behind')
        except OSError:
            pass
        def f(x):
            return x + 1
        """)
    v = verifier.check(code, {"tests": ["assert f(1) == 2"], "entry_point": "f"})
    assert v.passed, v
    assert _sandbox_processes() == []  # gone by the time check() returns
    assert not os.path.exists(marker)
    assert _sandbox_dirs() == []


def test_timeout_kills_the_process_group(verifier):
    code = _fenced("""\
        import subprocess
        children = [subprocess.Popen(['sleep', '60']) for _ in range(3)]
        def f(x):
            while True:
                pass
        """)
    t0 = time.monotonic()
    v = verifier.check(code, {"tests": ["assert f(1) == 2", "assert f(2) == 3"], "entry_point": "f"})
    assert v.reason == "timeout" and v.score == 0.0
    assert time.monotonic() - t0 < LIMITS["time_limit_s"] + 2.5
    assert _sandbox_processes() == []


def test_timeout_keeps_partial_credit(verifier):
    v = _like(verifier, partial_credit=True)
    code = "def f(x):\n    while x == 3:\n        pass\n    return x + 1\n"
    r = v.check(code, {"tests": ["assert f(1) == 2", "assert f(2) == 3", "assert f(3) == 4", "assert f(4) == 5"]})
    assert r.reason == "timeout"
    assert r.details["tests_passed"] == 2
    assert r.score == 0.5  # the two tests that ran before the hang count
    assert verifier.check(code, {"tests": ["assert f(1) == 2", "assert f(3) == 4"]}).score == 0.0


def test_parallel_check_many_keeps_order():
    v = CodeVerifier(**LIMITS)
    refs = [{"tests": [f"assert f() == {i}"], "entry_point": "f"} for i in range(12)]
    comps = [f"def f():\n    return {i if i % 3 else -1}\n" for i in range(12)]
    verdicts = v.check_many(comps, refs, workers=6)
    assert [x.passed for x in verdicts] == [bool(i % 3) for i in range(12)]
    with pytest.raises(ValueError):
        v.check_many(comps, refs[:-1])


def test_forced_modes_and_errors():
    assert CodeVerifier(mode="rlimits").mode == "rlimits"
    with pytest.raises(ValueError):
        CodeVerifier(mode="docker")
    with pytest.raises(ValueError):
        CodeVerifier(memory_mb=1)
    with pytest.raises(RuntimeError, match="no Python interpreter"):
        CodeVerifier(python="/nonexistent/python3")
    v = CodeVerifier()
    assert v.name == "code" and v.timeout_s > v.time_limit_s
    assert v.mode == sandbox_mode()


def test_measure_overhead_reports_each_mode():
    report = measure_overhead(n=2)
    assert report["active_mode"] == sandbox_mode()
    assert report["ms_per_candidate"] > 0 and report["bare_python_ms"] > 0
    assert "rlimits" in report["modes"] and all(m["median_ms"] > 0 for m in report["modes"].values())


def _world_searchable_dir() -> str:
    """A fresh directory (0755, ours) whose every ancestor other users can search."""
    for parent in (tempfile.gettempdir(), "/var/tmp", "/dev/shm", "/tmp"):
        d, ok = os.path.realpath(parent), os.path.isdir(parent)
        while ok:
            ok = bool(os.stat(d).st_mode & stat.S_IXOTH)
            if os.path.dirname(d) == d:
                break
            d = os.path.dirname(d)
        if ok:
            path = tempfile.mkdtemp(prefix="posttrain-nonroot-test-", dir=parent)
            os.chmod(path, 0o755)
            return path
    raise RuntimeError("no directory here that other users can reach (/tmp, /var/tmp, /dev/shm)")


@pytest.mark.skipif(not IS_ROOT or sandbox_mode() != "bwrap", reason="needs root (to switch user) and bubblewrap")
def test_works_for_a_non_root_caller():
    """The same sandbox started by an unprivileged user (no uid switching; RLIMIT_NPROC per user namespace),
    and the non-root fallback: its work directory is removed even when the candidate locks its subdirectories."""
    python = "/usr/bin/python3"
    assert os.access(python, os.X_OK), "no system python3 (the sandbox itself needs one the sandbox user can run)"
    # The child runs as uid 65534, so it imports a copy of the package that other users can read,
    # in a directory of its own (the checkout may be under /root, a pytest tmp dir is 0700).
    import shutil
    etc_mode = os.stat("/etc").st_mode
    base = _world_searchable_dir()
    try:
        shutil.copytree(os.path.join(REPO, "verifiers"), os.path.join(base, "verifiers"),
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        scratch = os.path.join(base, "tmp")  # the child's TMPDIR: the fallback's work dirs go here
        os.mkdir(scratch)
        os.chmod(scratch, 0o1777)
        for root, dirs, files in os.walk(os.path.join(base, "verifiers")):
            os.chmod(root, 0o755)
            for name in files:
                os.chmod(os.path.join(root, name), 0o644)
        script = textwrap.dedent(f"""\
            import importlib, json, sys, types, warnings
            top = types.ModuleType('posttrain'); top.__path__ = []
            pkg = types.ModuleType('posttrain.verifiers'); pkg.__path__ = [{os.path.join(base, 'verifiers')!r}]
            sys.modules['posttrain'] = top; sys.modules['posttrain.verifiers'] = pkg
            cs = importlib.import_module('posttrain.verifiers.code_sandbox')
            v = cs.CodeVerifier(time_limit_s=1.5, memory_mb=160, max_processes=8)
            ref = {{"tests": ["assert f(2) == 4"], "entry_point": "f"}}
            bomb = "import os\\nwhile True:\\n    try:\\n        os.fork()\\n    except OSError:\\n        pass\\n"
            out = [v.mode, v.sandbox, v.check("def f(x):\\n    return x * 2\\n", ref).reason, v.check(bomb, ref).reason,
                   v.check("import os\\ndef f(x):\\n    return os.getuid() and 4\\n", ref).reason]
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                fb = cs.CodeVerifier(mode="rlimits", time_limit_s=1.5, memory_mb=160, max_processes=8)
            locked = ("import os\\nos.makedirs('a/b/c')\\nopen('a/b/c/f', 'w').close()\\n"
                      "os.symlink('/etc', 'a/etc')\\nos.chmod('a/b', 0)\\nos.chmod('a', 0o500)\\n"
                      "def f(x):\\n    return 2 * x\\n")
            out += [fb.mode, fb.sandbox, any("without root" in str(w.message) for w in caught), fb.check(locked, ref).reason]
            print(json.dumps(out))
            """)
        r = subprocess.run([python, "-S", "-c", script], user=65534, group=65534, extra_groups=[], cwd="/",
                           capture_output=True, text=True, timeout=60, env={"PATH": "/usr/bin:/bin", "TMPDIR": scratch})
        assert r.returncode == 0, r.stderr
        assert json.loads(r.stdout) == ["bwrap", "bubblewrap", "passed", "timeout", "passed",
                                        "rlimits", "fallback (no namespaces)", True, "passed"]
        assert os.listdir(scratch) == []  # the fallback's work dir is gone, locked subdirectories and all
        assert os.stat("/etc").st_mode == etc_mode
    finally:
        shutil.rmtree(base, ignore_errors=True)
