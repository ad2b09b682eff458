"""CodeVerifier (registry name "code"): extract the code, run it in the sandbox against the
reference's tests, turn the harness's result into a Verdict; and measure_overhead.

Reference format, integrity design, modes, reasons and threat model: the package docstring,
verifiers/code_sandbox/__init__.py.
"""
from __future__ import annotations

import ast
import marshal
import os
import secrets
import signal
import subprocess
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Literal, Sequence

from posttrain.verifiers.base import AuditProblem, Verdict, Verifier
from posttrain.verifiers.code_sandbox import sandbox as _sandbox  # _UIDS via the module: a forked child rebinds it
from posttrain.verifiers.code_sandbox.audit import _ADVERSARIAL, _PROBLEMS
from posttrain.verifiers.code_sandbox.extract import _IMPORT_LINE, _Task, _defines, _parse_reference, extract_code
from posttrain.verifiers.code_sandbox.sandbox import (
    _HARNESS, _SYSTEM_PATH, _UID_SLOTS, SandboxMode, _as_user, _bwrap_argv, _bwrap_path, _communicate,
    _count_tasks, _drain_tail, _find_interpreter, _is_root, _kill_uid, _make_workdir, _probe_bwrap, _probe_unshare,
    _remove_uid_files, _remove_workdir, _Run, _unshare_argv, _unshare_path, _view_args, _wait_exit_unreaped,
    sandbox_mode,
)


# --------------------------------------------------------------------------------------
# The verifier
# --------------------------------------------------------------------------------------
class CodeVerifier(Verifier):
    """Runs extracted Python against the reference's tests in a sandbox (package docstring).

    Options: mode ("auto" | "bwrap" | "rlimits"), partial_credit (score = passed/total),
    time_limit_s (wall clock for loading the code and running all tests), cpu_limit_s
    (per process; default int(time_limit_s) + 2), memory_mb (address space per process),
    max_processes, max_file_mb, max_open_files, tmpfs_mb (the private /tmp of bwrap and
    the fallback), python (sandbox interpreter), namespaces (rlimits mode as root: use
    `unshare` and the read-only view), bind_root (bwrap and the fallback: show all of /
    read-only instead of /usr, /etc, /lib* and the interpreter), output_tail_bytes,
    max_code_chars.
    """

    name = "code"
    description = "Python code run against unit tests (HumanEval check() or assert list) in a sandbox"

    def __init__(
        self,
        *,
        mode: Literal["auto", "bwrap", "rlimits"] = "auto",
        partial_credit: bool = False,
        time_limit_s: float = 5.0,
        cpu_limit_s: int | None = None,
        memory_mb: int = 512,
        max_processes: int = 32,
        max_file_mb: int = 16,
        max_open_files: int = 64,
        tmpfs_mb: int = 64,
        python: str | None = None,
        namespaces: bool = True,
        bind_root: bool = False,
        output_tail_bytes: int = 2000,
        max_code_chars: int = 200_000,
    ) -> None:
        if mode not in ("auto", "bwrap", "rlimits"):
            raise ValueError(f"CodeVerifier mode must be 'auto', 'bwrap' or 'rlimits', got {mode!r}")
        if time_limit_s <= 0 or memory_mb < 64 or max_processes < 4 or max_open_files < 16:
            raise ValueError("CodeVerifier limits too small: need time_limit_s > 0, memory_mb >= 64, "
                             "max_processes >= 4, max_open_files >= 16")
        self.partial_credit = partial_credit
        self.time_limit_s = float(time_limit_s)
        self.cpu_limit_s = int(cpu_limit_s if cpu_limit_s is not None else int(time_limit_s) + 2)
        self.memory_mb = memory_mb
        self.max_processes = max_processes
        self.max_file_mb = max_file_mb
        self.max_open_files = max_open_files
        self.tmpfs_mb = tmpfs_mb
        self.bind_root = bind_root
        self.namespaces = namespaces
        self.output_tail_bytes = output_tail_bytes
        self.max_code_chars = max_code_chars
        # The runner's outer limit must leave room for our own deadline and cleanup.
        self.timeout_s = self.time_limit_s + 10.0
        self._interp = _find_interpreter(python)
        self._bwrap = _bwrap_path()
        if mode == "auto":
            why_not = _probe_bwrap(self._interp, bind_root)
            self.mode: SandboxMode = "bwrap" if why_not is None else "rlimits"
        elif mode == "bwrap":
            why_not = _probe_bwrap(self._interp, bind_root)
            if why_not is not None:
                raise RuntimeError(f"code sandbox: mode='bwrap' unavailable: {why_not}")
            self.mode = "bwrap"
        else:
            self.mode = "rlimits"
        self._unshare = (_unshare_path() if (self.mode == "rlimits" and namespaces and _probe_unshare(self._interp, bind_root))
                         else None)
        if self.mode == "rlimits" and _is_root() and namespaces and not self._unshare:
            warnings.warn("code sandbox: neither bubblewrap nor the unshare fallback (util-linux unshare, mount "
                          "namespaces) works here; candidates run as a per-run uid with rlimits only and can read "
                          "world-readable host files and write world-writable ones (apt-get install bubblewrap)",
                          RuntimeWarning, stacklevel=2)
        if self.mode == "rlimits" and not _is_root():
            warnings.warn("code sandbox: rlimits mode without root runs candidates as your own user with rlimits only "
                          "(no network or filesystem isolation; setsid() daemons can outlive a run); use bubblewrap "
                          "(apt-get install bubblewrap) or run as root", RuntimeWarning, stacklevel=2)

    # -- public -----------------------------------------------------------------------
    @property
    def python(self) -> str:
        """The interpreter candidates run under, with its version."""
        return f"{self._interp.path} ({self._interp.version})"

    @property
    def sandbox(self) -> str:
        """Which sandbox runs the candidates: "bubblewrap", "fallback" (namespaces + read-only
        view, as root with util-linux unshare) or "fallback (no namespaces)" (also in details)."""
        if self.mode == "bwrap":
            return "bubblewrap"
        return "fallback" if self._unshare else "fallback (no namespaces)"

    @property
    def isolation(self) -> str:
        """What the active mode isolates, in words (also in Verdict.details)."""
        who = "per-run uid" if _is_root() else "own uid"
        view = "read-only / (bind_root)" if self.bind_root else "read-only /usr /etc /lib* + interpreter only"
        if self.mode == "bwrap":
            return f"bwrap: user+pid+net+ipc+uts+mount+cgroup namespaces, {view}, private /tmp, {who}, rlimits"
        if self._unshare:
            return f"unshare: pid+net+ipc+uts+mount namespaces, {view}, private /tmp, {who}, rlimits"
        return f"{who}, rlimits only; host filesystem writable where that uid may write"

    def check(self, completion: str, reference: Any) -> Verdict:
        task = _parse_reference(reference)
        base = {"mode": self.mode, "sandbox": self.sandbox, "isolation": self.isolation, "python": self.python,
                "tests_total": task.n_tests, "tests_passed": 0}
        if not isinstance(completion, str):
            return Verdict(0.0, "no code found", base)
        code = extract_code(completion)
        if code is None:
            return Verdict(0.0, "no code found", base)
        if task.entry_point and task.prompt:
            if not _defines(code, task.entry_point):
                code = task.prompt + code  # a continuation of the prompt (HumanEval convention)
            elif task.prompt_parses:
                # A whole function: the prompt still brings its imports and helpers; the
                # candidate's definition comes later and wins.
                code = task.prompt + "\n" + code
            else:
                imports = "\n".join(_IMPORT_LINE.findall(task.prompt))
                code = imports + "\n" + code if imports else code
        if len(code) > self.max_code_chars:
            return Verdict(0.0, "code too long", {**base, "code_chars": len(code)})
        run = self._run_sandboxed(code, task)
        return self._verdict(run, task, base)

    def check_many(self, completions: Sequence[str], references: Sequence[Any], workers: int | None = None) -> list[Verdict]:
        """check() over pairs, `workers` sandboxes at a time (default: CPU count); order kept."""
        if len(completions) != len(references):
            raise ValueError(f"check_many: {len(completions)} completions but {len(references)} references")
        workers = max(1, min(workers or os.cpu_count() or 1, _UID_SLOTS, len(completions) or 1))
        if workers == 1:
            return [self.check(c, r) for c, r in zip(completions, references)]
        with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="code-sandbox") as pool:
            return list(pool.map(self.check, completions, references))

    def audit_problems(self, n: int, seed: int = 0) -> list[AuditProblem]:
        """Up to `n` of the built-in HumanEval-style problems (12), in a seeded order."""
        import random

        order = list(range(len(_PROBLEMS)))
        random.Random(seed).shuffle(order)
        out = []
        for i in order[: max(0, n)]:
            p = _PROBLEMS[i]
            reference = {"tests": p["tests"], "entry_point": p["entry_point"], "prompt": p["prompt"]}
            out.append(AuditProblem(prompt=p["prompt"], reference=reference, gold="```python\n" + p["solution"] + "```\n"))
        return out

    def adversarial_cases(self, problem: AuditProblem) -> list[tuple[str, str, float]]:
        """Sandbox escapes and test-gaming programs; each must score 0."""
        ref = problem.reference if isinstance(problem.reference, dict) else {}
        entry = ref.get("entry_point") or "solution"
        return [(label, "```python\n" + body.replace("ENTRY", entry) + "\n```", 0.0) for label, body in _ADVERSARIAL]

    # -- internals --------------------------------------------------------------------
    def _config(self, nproc: int) -> list[str]:
        """The harness's argv: timeout, cpu, mem, fsize, nofile, nproc, max_msg, max_failures."""
        return [repr(self.time_limit_s), str(self.cpu_limit_s), str(self.memory_mb << 20), str(self.max_file_mb << 20),
                str(self.max_open_files), str(nproc), str(16 << 20), "5"]

    def _run_sandboxed(self, code: str, task: _Task) -> _Run:
        nonce = secrets.token_hex(16)
        payload = marshal.dumps({
            "nonce": nonce, "code": code, "setup": task.setup, "kind": task.kind, "tests": task.tests,
            "entry_point": task.entry_point, "proxies": list(task.proxies), "n_tests": task.n_tests,
            "prompt": task.prompt if task.prompt_parses else None,
        }, 4)  # format 4: readable by every Python 3 the sandbox may run
        if _is_root():
            with _sandbox._UIDS.lease() as uid:
                return self._launch(payload, nonce, uid)
        return self._launch(payload, nonce, None)

    def _launch(self, payload: bytes, nonce: str, uid: int | None) -> _Run:
        python = [self._interp.path, "-S", "-s", "-B", "-c", _HARNESS]
        env = {"PATH": _SYSTEM_PATH, "LANG": "C.UTF-8", "LC_ALL": "C.UTF-8", "PYTHONHASHSEED": "0",
               "PYTHONDONTWRITEBYTECODE": "1", "PYTHONIOENCODING": "utf-8"}
        workdir = None
        if self.mode == "bwrap":
            assert self._bwrap is not None
            nproc = self.max_processes + 1  # + the harness; counted per user namespace, i.e. per sandbox
            argv = _bwrap_argv(self._bwrap, self._interp, bind_root=self.bind_root, tmpfs_mb=self.tmpfs_mb)
            argv, kwargs = _as_user(argv + python + self._config(nproc), uid)
            env.update(HOME="/tmp/work", TMPDIR="/tmp/work")
            cwd = "/"
        elif self._unshare and uid is not None:
            # The harness starts as root in the new namespaces, builds the read-only view with
            # a private tmpfs /tmp (nothing of the run reaches the host disk), then becomes uid.
            nproc = self.max_processes + 1
            argv = (_unshare_argv(self._unshare) + python + self._config(nproc)
                    + _view_args(self._interp, uid, bind_root=self.bind_root, tmpfs_mb=self.tmpfs_mb))
            kwargs = {}
            env.update(HOME="/tmp/work", TMPDIR="/tmp/work")
            cwd = "/"
        else:
            workdir = _make_workdir(uid)
            env.update(HOME=workdir.path, TMPDIR=workdir.path)
            cwd = workdir.path
            if uid is None:  # the count is per uid: leave room for what the user already runs
                nproc = _count_tasks(os.getuid()) + self.max_processes + 1
            else:
                nproc = self.max_processes + 1
            argv, kwargs = _as_user(python + self._config(nproc), uid)
        deadline = time.monotonic() + self.time_limit_s + 2.0
        proc = None
        try:
            proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
                                    cwd=cwd, start_new_session=True, close_fds=True, **kwargs)
            killed = True
            try:
                out, tail, killed = _communicate(proc, payload, deadline, self.output_tail_bytes)
            finally:
                # The harness has answered (or the deadline passed): let the launcher exit by
                # itself (bwrap/unshare then reap the whole pid namespace), then kill the group
                # while the leader is still unreaped, so its id cannot be reused meanwhile.
                if not killed:
                    _wait_exit_unreaped(proc.pid, min(1.0, max(0.05, deadline - time.monotonic())))
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                except (ProcessLookupError, PermissionError):
                    pass
                proc.wait()
                if uid is not None:  # daemons that left the group or namespace: kill(-1) as the uid
                    _kill_uid(uid, self._interp.path)
            tail = _drain_tail(proc.stderr, tail, self.output_tail_bytes)
        finally:
            if proc is not None:
                for f in (proc.stdin, proc.stdout, proc.stderr):
                    if f is not None and not f.closed:
                        try:
                            f.close()
                        except OSError:
                            pass
            if workdir is not None:  # fallback without namespaces: the run could write on the host
                _remove_workdir(workdir)  # (as root, every process of uid is dead by now)
                if uid is not None:
                    _remove_uid_files(uid)
        result = None
        line = out.split(b"\n", 1)[0]
        try:
            parsed = ast.literal_eval(line.decode("utf-8")) if line else None
        except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError, UnicodeDecodeError):
            parsed = None
        if isinstance(parsed, dict):
            if parsed.get("status") == "harness_error":
                raise RuntimeError(f"code sandbox harness failed ({self.mode} mode): {parsed.get('message', '')}")
            if parsed.get("nonce") == nonce:
                result = parsed
        return _Run(result, tail.decode("utf-8", "replace"), killed)

    def _verdict(self, run: _Run, task: _Task, base: dict[str, Any]) -> Verdict:
        details = dict(base)
        details["stderr_tail"] = run.stderr_tail
        res = run.result
        if res is None:
            reason = "timeout" if run.killed_at_deadline else "harness killed (no result)"
            return Verdict(0.0, reason, details)
        status = res.get("status")
        if status == "reference_error":
            raise ValueError(f"code reference is broken: {res.get('message', '')}")
        total, passed, executed = res.get("total"), res.get("passed"), res.get("executed")
        if not (total == task.n_tests and isinstance(passed, int) and isinstance(executed, int)
                and 0 <= passed <= executed <= total):
            return Verdict(0.0, "harness result inconsistent", details)
        details.update(tests_passed=passed, failures=res.get("failures", [])[:5])
        if res.get("message"):
            details["error"] = str(res["message"])[:500]
        if res.get("traceback"):
            details["traceback"] = str(res["traceback"])[-1000:]
        if res.get("child"):
            details["candidate_exit"] = res["child"]
        fraction = passed / total if total else 0.0
        score = fraction if self.partial_credit else (1.0 if passed == total else 0.0)
        child = res.get("child") or {}
        if status == "done" and passed == total and executed == total:
            return Verdict(1.0, "passed", details)
        if status == "syntax_error":
            return Verdict(0.0, "syntax error", details)
        if status == "timeout_load" or res.get("timeout"):
            return Verdict(score, "timeout", details)
        if res.get("memory"):
            return Verdict(score, "killed (memory)", details)
        if status == "exited_load":
            gone = str(res.get("gone", ""))
            return Verdict(0.0, _death_reason(child, "exited early" if "exited" in gone else "protocol violation"), details)
        if status == "load_error":
            if res.get("error_type") in ("SystemExit", "KeyboardInterrupt"):
                return Verdict(0.0, f"exited early ({res['error_type']})", details)
            return Verdict(0.0, f"error on load ({res.get('error_type', 'Exception')})", details)
        if status == "protocol_error":
            return Verdict(0.0, "protocol violation", details)
        if status != "done":
            return Verdict(0.0, f"harness status {status!r}", details)
        if res.get("gone") and child:
            return Verdict(score, _death_reason(child, f"failed {total - passed}/{total} tests"), details)
        return Verdict(score, f"failed {total - passed}/{total} tests", details)


def _death_reason(child: dict[str, Any], default: str) -> str:
    sig = child.get("signal")
    if sig is not None:
        if sig == signal.SIGXCPU:
            return "timeout (cpu limit)"
        if sig == signal.SIGXFSZ:
            return "killed (file size limit)"
        try:
            return f"crashed ({signal.Signals(sig).name})"
        except ValueError:
            return f"crashed (signal {sig})"
    if "exit" in child:
        return f"exited early (code {child['exit']})"
    return default


# --------------------------------------------------------------------------------------
# Overhead measurement (scripts/bench_verifiers.py calls this when present)
# --------------------------------------------------------------------------------------
def measure_overhead(n: int = 20) -> dict[str, Any]:
    """Wall ms per candidate for a trivial program, per available mode, run one at a time.

    The trivial candidate's own run time is ~0, so this is the sandbox's overhead:
    interpreter start-up, bwrap/unshare, the harness, the fork and cleanup.
    """
    import statistics

    reference = {"tests": ["assert add(1, 2) == 3"], "entry_point": "add"}
    completion = "def add(a, b):\n    return a + b\n"
    interp = _find_interpreter(None)
    bare = []
    for _ in range(max(3, n // 2)):
        t0 = time.perf_counter()
        subprocess.run([interp.path, "-S", "-s", "-B", "-c", "pass"], check=True)
        bare.append((time.perf_counter() - t0) * 1000)
    modes: dict[str, Any] = {}
    variants: list[tuple[str, dict[str, Any]]] = [("rlimits", {"mode": "rlimits"})]
    if _probe_bwrap(interp, False) is None:
        variants.insert(0, ("bwrap", {"mode": "bwrap"}))
    if _is_root() and _probe_unshare(interp, False):
        variants.append(("rlimits-no-namespaces", {"mode": "rlimits", "namespaces": False}))
    for label, kwargs in variants:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            v = CodeVerifier(**kwargs)
        v.check(completion, reference)  # warm caches
        times = []
        for _ in range(n):
            t0 = time.perf_counter()
            verdict = v.check(completion, reference)
            times.append((time.perf_counter() - t0) * 1000)
            if not verdict.passed:
                raise RuntimeError(f"measure_overhead: trivial candidate failed in {label} mode: {verdict}")
        times.sort()
        modes[label] = {
            "sandbox": v.sandbox,
            "isolation": v.isolation,
            "mean_ms": round(statistics.fmean(times), 1),
            "median_ms": round(statistics.median(times), 1),
            "p90_ms": round(times[min(len(times) - 1, int(0.9 * len(times)))], 1),
            "max_ms": round(times[-1], 1),
        }
    active = sandbox_mode()
    return {
        "n": n,
        "python": f"{interp.path} ({interp.version})",
        "active_mode": active,
        "ms_per_candidate": modes[active]["median_ms"],
        "bare_python_ms": round(statistics.median(bare), 1),
        "modes": modes,
    }
