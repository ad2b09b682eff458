"""Code verifier: run model-written Python against unit tests in a sandboxed process.

    CodeVerifier().check(completion, {"tests": "def check(candidate): ...", "entry_point": "f"})
    CodeVerifier(partial_credit=True).check(completion, {"tests": ["assert f(1) == 2", ...]})
    python -c "from verifiers.code_sandbox import measure_overhead; print(measure_overhead())"

Reference format
----------------
A dict with
- ``tests``: either a string in HumanEval style that defines ``check(candidate)`` (one
  test: the harness calls ``check(<entry_point>)``), or a list of statement strings,
  usually ``assert f(1) == 2``; each item is one test (partial credit counts them). An
  item that is a single bare expression is asserted truthy.
- ``entry_point`` (optional): the function handed to ``check``. Default: the last
  function the candidate defines at top level.
- ``setup`` (optional): code run before the candidate's code and before the tests
  (imports, helpers).
- ``prompt`` (optional, HumanEval's convention): when the extracted code does not define
  ``entry_point`` it is taken as the continuation of ``prompt`` (a body); when it does, the
  prompt still goes first (its imports and helpers such as HumanEval/32's ``poly`` stay
  available; the candidate's later definition wins), or only its import lines if the prompt
  is not valid Python on its own. A prompt that is valid Python also runs on the tests'
  side, so the helpers the tests call are the reference's own: a candidate that redefines
  ``poly`` to make ``check`` pass changes nothing.

Names the tests use must come from ``setup``, the prompt, the tests themselves, or be
functions the candidate defines (those become proxies to the candidate process).

Code extraction: fenced blocks tagged python/py/python3 (else untagged fences; an
unterminated last fence counts); the submission is the *last* block that defines something
at top level (``def``/``class``), skipping blocks that only call or print (usage examples)
or only define ``test_*``/``check`` (the model's own tests). So a corrected version after a
draft wins, and so does a retraction: "no wait, here is the right one" followed by other
code submits that other code. Without fences: the raw text after any ``</think>``.
Candidate code runs with ``__name__ == "candidate"``, so ``if __name__ == "__main__":``
demos do not run.

How a run works (integrity)
---------------------------
The candidate never shares an interpreter with the tests. The harness process P starts
in the sandbox, sets its rlimits, makes itself non-dumpable (no ptrace, no
/proc/P/mem or /proc/P/fd by same-uid processes) and forks the candidate process C
*before* it reads its task from stdin, so C's memory never holds the tests or the
per-run nonce. C closes P's stdin and stdout (the result channel), then loads the
candidate code and serves calls over a private pipe pair. P runs the reference tests
in its own interpreter, with each candidate function replaced by a proxy: arguments go
to C, and C's return value comes back as a pickle that P loads with an unpickler which
accepts only plain data (builtins, OrderedDict, Counter, deque, defaultdict, Fraction,
Decimal, datetime). In-place changes to list/dict/set/bytearray arguments are copied
back. P counts the tests it ran and passed, and writes one result line (a Python literal,
read with ``ast.literal_eval``) with the parent's nonce to its stdout; the parent accepts a pass only when that line carries the nonce
and ``passed == total ==`` the number of tests in the reference. So these all score 0:
``sys.exit(0)`` / ``os._exit(0)`` / ``raise SystemExit`` (no result from C), printing a
fake success line (C's output goes to the log only), redefining ``check`` / ``print`` /
builtins or patching "the harness" (that happens in C's interpreter, not P's), returning
an object whose ``__eq__`` is always true (not plain data), writing to P's result pipe
(C does not hold it), killing P (no result).

Limits of this design: tests that pass callables or other non-data values *to* the
candidate, or that call methods on candidate-defined classes, are not supported (the
call fails with a clear message); return values must be plain data.

Sandbox modes (``CodeVerifier().mode``, ``sandbox_mode()``, ``Verdict.details["mode"]``)
----------------------------------------------------------------------------------------
- ``"bwrap"`` (bubblewrap present and user namespaces allowed): new user, pid, net, ipc,
  uts, mount and cgroup namespaces; a read-only view of /usr, /etc, /bin, /lib* and the
  interpreter's prefix only (not ``/``: datasets and home directories stay invisible;
  ``bind_root=True`` binds all of ``/`` read-only instead); a fresh size-limited tmpfs
  at /tmp whose /tmp/work is cwd and HOME (nothing is written to the host disk), a
  size-limited /dev/shm, read-only /dev; ``--die-with-parent``, nested user namespaces
  disabled, no capabilities; the harness is the namespace's pid 1 (``--as-pid-1``), so the
  candidate cannot kill it and everything else dies with it. As root, bwrap itself is
  started as the per-run uid.
- ``"rlimits"`` (fallback, or ``mode="rlimits"``): a fresh host temp dir (0700, owned by
  the run's uid) as cwd/HOME/TMPDIR, rlimits, a new session. As root, also a per-run uid
  and, when util-linux ``unshare`` exists (``namespaces=True``), new net/pid/mount/ipc
  namespaces with the harness as pid 1. Afterwards every process of the run's uid is
  killed (``kill(-1)`` as that uid) and its files in /tmp, /var/tmp and /dev/shm removed.

Both modes: scrubbed environment (PATH=/usr/local/bin:/usr/bin:/bin, HOME, TMPDIR,
LANG, PYTHONHASHSEED=0 for determinism, PYTHONDONTWRITEBYTECODE); ``python -S -s -B``
with the cwd removed from ``sys.path``; rlimits set by the harness before it reads its
task: CPU seconds, address space, processes (counted per sandbox inside bwrap's user
namespace, per run uid otherwise), file size, open files, no core files;
``no_new_privs``; a wall-clock deadline enforced by P (partial results survive) and by
the parent, which kills the whole process group (``start_new_session`` + ``killpg``);
the candidate's stdout/stderr is kept as a bounded rolling tail, and after 8 MiB the pipe is
closed (further writes fail with EPIPE). Nothing is left behind: when ``check`` returns,
the sandbox's processes are gone and its files removed.

Reasons: "passed", "failed k/n tests", "syntax error", "no code found", "code too long",
"timeout", "timeout (cpu limit)", "killed (memory)", "error on load (ExcType)",
"exited early (...)", "crashed (SIGNAME)", "harness killed (no result)",
"protocol violation". Details: mode, isolation, python, tests_passed, tests_total,
failures (test, label, error with the values compared), stderr_tail, and error/traceback
for load errors. A reference that fails to load in the sandbox raises ValueError; a
harness failure (our bug or a broken machine) raises RuntimeError.

Non-root user. Linux does not enforce RLIMIT_NPROC for root, so as root every run gets
its own uid from 2**30 + (pid % 2**22) * 256 + slot (unique among live processes; never
in /etc/passwd). The switch is done by util-linux ``setpriv`` (or ``unshare --setuid``)
in the child rather than ``Popen(user=...)``, which would force a fork() of the verifier
process: tens of ms per candidate in a trainer holding GBs of memory. The project's Python may live somewhere other users cannot read (here:
/root/.pyenv), so the sandbox interpreter is the first of ``python=``, the running
interpreter, /usr/bin/python3, /usr/local/bin/python3 that the sandbox user can actually
run (probed once; ``CodeVerifier().python`` and ``details["python"]`` say which). The
harness needs only the standard library; candidates get the standard library only
(no site-packages).

Threat model
------------
Isolated: writes outside the sandbox's scratch space (bwrap: none reach the host disk),
the network (bwrap; rlimits mode as root with ``unshare``), other processes (pid
namespace or a distinct uid; P is non-dumpable), memory, CPU time, wall time, process
count, file sizes, open files; the tests and nonce (never in C's memory).
Not isolated: CPU/cache timing side channels; the kernel attack surface (no seccomp
filter); reading world-readable files in the bound directories (bwrap: /usr, /etc,
interpreter prefix; rlimits mode: the whole host); in rlimits mode, disk space in the
temp dir up to the time limit (per-file size is capped); in rlimits mode *without root*
the candidate runs as your own user, and a process that calls setsid() can outlive the
run (weak; a warning says so): install bubblewrap.
The candidate sees each test's arguments (it must, to compute the answer).
"""
from __future__ import annotations

import ast
import builtins
import collections
import marshal
import os
import re
import secrets
import selectors
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Iterator, Literal, Sequence

from verifiers.base import AuditProblem, Verdict, Verifier

__all__ = ["CodeVerifier", "sandbox_mode", "measure_overhead", "extract_code"]

SandboxMode = Literal["bwrap", "rlimits"]

_SYSTEM_PATH = "/usr/local/bin:/usr/bin:/bin"
_UID_BASE = 1 << 30
_UID_SLOTS = 256
_RESULT_CAP = 1 << 20  # bytes of harness stdout we accept
_DRAIN_CAP = 8 << 20  # bytes of candidate output we read before closing the pipe


# --------------------------------------------------------------------------------------
# The harness: runs inside the sandbox as `python -S -s -B -c _HARNESS <config ints>`.
# It imports only C modules on the normal path (no json/re/traceback: start-up time is
# the sandbox's overhead); the task arrives as marshal data, the result leaves as a repr
# that the parent reads with ast.literal_eval.
# Standard library only, Python >= 3.8.
# --------------------------------------------------------------------------------------
_HARNESS = r'''
import os, sys
sys.path[:] = [p for p in sys.path if p not in ("", ".")]
import _pickle as pickle, _signal as signal, builtins, ctypes, io, marshal, resource, select, struct, time

CFG = dict(zip(("timeout", "cpu", "mem", "fsize", "nofile", "nproc", "max_msg", "max_failures"),
               [float(sys.argv[1])] + [int(x) for x in sys.argv[2:9]]))
DEADLINE = time.monotonic() + CFG["timeout"]
HEADER = struct.Struct(">I")
SAFE_GLOBALS = {
    ("builtins", n) for n in ("bool", "bytearray", "bytes", "complex", "dict", "float",
                              "frozenset", "int", "list", "range", "set", "slice", "str", "tuple")
} | {("collections", n) for n in ("OrderedDict", "Counter", "deque", "defaultdict")} | {
    ("fractions", "Fraction"), ("decimal", "Decimal"), ("datetime", "date"), ("datetime", "datetime"),
    ("datetime", "time"), ("datetime", "timedelta"), ("datetime", "timezone"),
}
MUTABLE = (list, dict, set, bytearray)


class Deadline(BaseException):
    pass


class Gone(BaseException):
    """The candidate process died, hung up or broke the protocol: every later call fails."""


class CandidateError(Exception):
    pass


def limit(res, soft, hard):
    cur = resource.getrlimit(res)[1]
    if cur != resource.RLIM_INFINITY:
        hard = min(hard, cur)
        soft = min(soft, hard)
    resource.setrlimit(res, (soft, hard))


def harden():
    limit(resource.RLIMIT_CORE, 0, 0)
    limit(resource.RLIMIT_CPU, CFG["cpu"], CFG["cpu"] + 1)
    limit(resource.RLIMIT_AS, CFG["mem"], CFG["mem"])
    limit(resource.RLIMIT_FSIZE, CFG["fsize"], CFG["fsize"])
    limit(resource.RLIMIT_NOFILE, CFG["nofile"], CFG["nofile"])
    if CFG["nproc"]:
        limit(resource.RLIMIT_NPROC, CFG["nproc"], CFG["nproc"])
    libc = ctypes.CDLL(None, use_errno=True)
    # PR_SET_NO_NEW_PRIVS=1, PR_SET_DUMPABLE=0 (no ptrace or /proc/P/{mem,fd} by the
    # candidate), PR_SET_PDEATHSIG=SIGKILL (die with the verifier).
    for option, value in ((38, 1), (4, 0), (1, int(signal.SIGKILL))):
        if libc.prctl(option, ctypes.c_ulong(value), ctypes.c_ulong(0), ctypes.c_ulong(0), ctypes.c_ulong(0)):
            raise OSError(ctypes.get_errno(), "prctl(%d) failed" % option)


def write_all(fd, data):
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def send(fd, obj):
    data = pickle.dumps(obj, protocol=4)
    write_all(fd, HEADER.pack(len(data)) + data)


def read_exact(fd, n, deadline):
    chunks = []
    while n:
        if deadline is not None:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                raise Deadline()
        chunk = os.read(fd, min(n, 1 << 20))
        if not chunk:
            raise EOFError("pipe closed")
        chunks.append(chunk)
        n -= len(chunk)
    return b"".join(chunks)


def recv_frame(fd, deadline):
    (size,) = HEADER.unpack(read_exact(fd, HEADER.size, deadline))
    if size > CFG["max_msg"]:
        raise Gone("the candidate sent %d bytes (limit %d)" % (size, CFG["max_msg"]))
    return read_exact(fd, size, deadline)


def describe(exc):
    try:
        text = str(exc)
    except BaseException:
        text = "<unprintable>"
    name = type(exc).__name__
    return (name + ": " + text if text else name)[:400]


def test_line(exc, source):
    """ "line N: <source line>" of the innermost test frame, for failure reports."""
    tb, found = exc.__traceback__, None
    while tb is not None:
        if tb.tb_frame.f_code.co_filename == "<tests>":
            found = tb.tb_lineno
        tb = tb.tb_next
    if found is None:
        return ""
    lines = source.splitlines()
    return " (tests line %d: %s)" % (found, lines[found - 1].strip()[:160] if 0 < found <= len(lines) else "?")


# ---------------------------------------------------------------- candidate process (C)
def child_main(rfd, wfd):
    null = os.open(os.devnull, os.O_RDWR)
    os.dup2(null, 0)  # the task (tests, nonce) is still unread in P's stdin
    os.dup2(2, 1)  # fd 1 is P's result channel; candidate output goes to the log
    os.close(null)
    for fd in range(3, CFG["nofile"]):
        if fd not in (rfd, wfd):
            try:
                os.close(fd)
            except OSError:
                pass
    try:
        sys.stdout.reconfigure(line_buffering=True)
    except Exception:
        pass
    _, setup, code = pickle.loads(recv_frame(rfd, None))
    ns = {"__name__": "candidate", "__builtins__": builtins}
    try:
        exec(compile(setup, "<setup>", "exec"), ns)
    except BaseException as exc:
        send(wfd, ("setup_error", describe(exc)))
        os._exit(0)
    try:
        compiled = compile(code, "<candidate>", "exec")
    except BaseException as exc:
        send(wfd, ("syntax_error", describe(exc)))
        os._exit(0)
    try:
        exec(compiled, ns)
    except BaseException as exc:
        try:
            import traceback
            tb = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))[-1500:]
        except BaseException:
            tb = ""
        send(wfd, ("load_error", type(exc).__name__, describe(exc), tb))
        os._exit(0)
    send(wfd, ("loaded", [k for k, v in list(ns.items()) if type(v).__name__ == "function"]))
    while True:
        _, seq, name, args, kwargs = pickle.loads(recv_frame(rfd, None))
        try:
            if name not in ns:
                raise NameError("name %r is not defined" % name)
            result = ns[name](*args, **kwargs)
            mutated = [(i, a) for i, a in enumerate(args) if type(a) in MUTABLE]
            data = pickle.dumps(("ok", seq, result, mutated), protocol=4)
        except BaseException as exc:
            try:
                text = str(exc)[:400]
            except BaseException:
                text = "<unprintable>"
            data = pickle.dumps(("exc", seq, type(exc).__name__, text), protocol=4)
        write_all(wfd, HEADER.pack(len(data)) + data)


# ------------------------------------------------------------------- harness process (P)
class SafeUnpickler(pickle.Unpickler):
    def find_class(self, module, name):
        if (module, name) in SAFE_GLOBALS:
            return super().find_class(module, name)
        raise pickle.UnpicklingError("the candidate returned a non-data value (%s.%s)" % (module, name))


class Link:
    def __init__(self, pid, wfd, rfd):
        self.pid, self.wfd, self.rfd = pid, wfd, rfd
        self.seq = 0
        self.gone = None  # why the candidate process is unusable
        self.timeout = False
        self.memory = False
        self.status = None  # C's wait status once reaped

    def mark_gone(self, why):
        if self.gone is None:
            self.gone = why
        self.reap(0.2)

    def reap(self, grace):
        if self.status is not None:
            return
        end = time.monotonic() + grace
        while True:
            try:
                pid, status = os.waitpid(self.pid, os.WNOHANG)
            except ChildProcessError:
                return
            if pid:
                self.status = status
                return
            if time.monotonic() >= end:
                return
            time.sleep(0.005)

    def receive(self):
        try:
            frame = recv_frame(self.rfd, DEADLINE)
        except Deadline:
            self.timeout = True
            raise
        except (EOFError, OSError) as exc:
            self.mark_gone("the candidate process exited")
            raise Gone(self.gone)
        except Gone as exc:
            self.mark_gone(str(exc))
            raise
        try:
            return SafeUnpickler(io.BytesIO(frame)).load()
        except MemoryError:
            self.memory = True
            raise
        except Exception as exc:
            return ("undecodable", describe(exc))

    def call(self, name, args, kwargs):
        if self.timeout:
            raise Deadline()
        if self.gone:
            raise Gone(self.gone)
        self.seq += 1
        try:
            data = pickle.dumps(("call", self.seq, name, args, kwargs), protocol=4)
        except Exception as exc:
            raise TypeError("a test argument cannot be sent to the sandboxed candidate: " + describe(exc))
        try:
            write_all(self.wfd, HEADER.pack(len(data)) + data)
        except OSError:
            self.mark_gone("the candidate process exited")
            raise Gone(self.gone)
        reply = self.receive()
        if not isinstance(reply, tuple) or not reply:
            self.mark_gone("protocol violation")
            raise Gone(self.gone)
        if reply[0] == "undecodable":
            # The frame was read, so the channel is still in sync: this call alone fails.
            raise CandidateError(reply[1])
        if len(reply) != 4 or reply[1] != self.seq or reply[0] not in ("ok", "exc"):
            self.mark_gone("protocol violation")
            raise Gone(self.gone)
        if reply[0] == "exc":
            tname, message = reply[2], reply[3]
            if tname == "MemoryError":
                self.memory = True
            cls = getattr(builtins, tname, None) if isinstance(tname, str) else None
            if isinstance(cls, type) and issubclass(cls, Exception):
                try:
                    raise cls(message)
                except TypeError:
                    pass
            raise CandidateError("%s: %s" % (tname, message))
        mutated = reply[3]
        if isinstance(mutated, list):
            for item in mutated:
                if not (isinstance(item, tuple) and len(item) == 2 and type(item[0]) is int):
                    continue
                i, new = item
                if 0 <= i < len(args) and type(args[i]) is type(new) and type(new) in MUTABLE and args[i] != new:
                    old = args[i]
                    if type(old) in (list, bytearray):
                        old[:] = new
                    else:
                        old.clear()
                        old.update(new)
        return reply[2]


class Candidate:
    """Stands for a candidate function inside the tests: every call runs in C."""

    def __init__(self, link, name):
        self._link = link
        self.__name__ = self.__qualname__ = name

    def __call__(self, *args, **kwargs):
        return self._link.call(self.__name__, args, kwargs)

    def __repr__(self):
        return "<candidate %s>" % self.__name__


def format_exc():
    import traceback
    return traceback.format_exc()


def run(task, link, out):
    try:
        send(link.wfd, ("load", task["setup"], task["code"]))
        reply = link.receive()
    except Deadline:
        out["status"] = "timeout_load"
        return out
    except (Gone, OSError):
        link.mark_gone("the candidate process exited")
        out["status"] = "exited_load"
        return out
    except MemoryError:
        link.memory = True
        out["status"] = "load_error"
        return out
    # C's reply is untrusted (the candidate may have written into the pipe): check its shape.
    kind = reply[0] if isinstance(reply, tuple) and len(reply) >= 2 else None
    if kind == "syntax_error":
        out.update(status="syntax_error", message=str(reply[1]))
        return out
    if kind == "setup_error":
        out.update(status="reference_error", message="setup failed in the sandbox: " + str(reply[1]))
        return out
    if kind == "load_error" and len(reply) == 4:
        if reply[1] == "MemoryError":
            link.memory = True
        out.update(status="load_error", error_type=str(reply[1]), message=str(reply[2]), traceback=str(reply[3]))
        return out
    if kind != "loaded" or not isinstance(reply[1], list):
        out["status"] = "protocol_error"
        link.mark_gone("protocol violation")
        return out
    functions = [f for f in reply[1] if isinstance(f, str)]
    out["functions"] = functions[:50]

    ns = {"__name__": "tests", "__builtins__": builtins}
    for label, source in (("setup", task["setup"]), ("prompt", task["prompt"] or "")):
        # Reference code runs here, in P: helpers the tests use (HumanEval/32's poly) are
        # the reference's own, not whatever the candidate redefined them to.
        try:
            exec(compile(source, "<%s>" % label, "exec"), ns)
        except Exception:
            out.update(status="reference_error", message=label + " failed: " + format_exc()[-800:])
            return out
    if task["entry_point"]:
        ns[task["entry_point"]] = Candidate(link, task["entry_point"])  # replaces the prompt's stub
    for name in task["proxies"]:
        if name not in ns:
            ns[name] = Candidate(link, name)
    units = []
    if task["kind"] == "check":
        try:
            exec(compile(task["tests"], "<tests>", "exec"), ns)
        except (Deadline, Gone):
            raise
        except Exception:
            if link.seq == 0:
                out.update(status="reference_error", message="tests failed to load: " + format_exc()[-800:])
                return out
            out["failures"].append({"test": 0, "error": "the test module failed: " + format_exc()[-300:]})
            out["executed"] = out["total"]
            return out
        entry = task["entry_point"] or (functions[-1] if functions else None)
        if entry is None:
            out["failures"].append({"test": 0, "error": "the candidate defines no function"})
            out["executed"] = out["total"]
            return out
        check = ns.get("check")
        units.append(("check(%s)" % entry, lambda: check(Candidate(link, entry))))
    else:
        for source, runnable in task["tests"]:
            code = compile(runnable, "<test>", "exec")
            units.append((source, lambda code=code: exec(code, ns)))
    for index, (label, unit) in enumerate(units):
        if link.timeout or link.gone:
            why = "timeout" if link.timeout else link.gone
            if len(out["failures"]) < CFG["max_failures"]:
                out["failures"].append({"test": index, "error": "not run: " + why})
            continue
        out["executed"] += 1
        error = None
        try:
            unit()
        except Deadline:
            link.timeout = True
            error = "timeout"
        except Gone as exc:
            error = str(exc)
        except MemoryError:
            link.memory = True
            error = "MemoryError"
        except BaseException as exc:
            error = describe(exc)
            if task["kind"] == "check":
                error += test_line(exc, task["tests"])
        if error is None and (link.timeout or link.gone):
            error = "timeout" if link.timeout else link.gone  # swallowed by the test code
        if error is None:
            out["passed"] += 1
        elif len(out["failures"]) < CFG["max_failures"]:
            out["failures"].append({"test": index, "label": label[:200], "error": error})
    return out


def main():
    harden()
    c_in_r, p_out_w = os.pipe()  # P -> C
    p_in_r, c_out_w = os.pipe()  # C -> P
    pid = os.fork()  # before reading the task: C never holds the tests or the nonce
    if pid == 0:
        try:
            os.close(p_out_w)
            os.close(p_in_r)
            child_main(c_in_r, c_out_w)
        finally:
            os._exit(0)
    os.close(c_in_r)
    os.close(c_out_w)
    chunks = []
    while True:
        chunk = os.read(0, 1 << 16)
        if not chunk:
            break
        chunks.append(chunk)
    task = marshal.loads(b"".join(chunks))
    nonce = task.pop("nonce")

    def on_alarm(signum, frame):
        raise Deadline()

    link = Link(pid, p_out_w, p_in_r)
    out = {"status": "done", "total": task["n_tests"], "executed": 0, "passed": 0, "failures": []}
    # One-shot backstop for time spent in P itself (the tests' own code); the pipe reads
    # have their own deadline. The timer fires at most once, and every place it can fire
    # is inside this try, so partial counts in `out` survive.
    signal.signal(signal.SIGALRM, on_alarm)
    try:
        try:
            signal.setitimer(signal.ITIMER_REAL, max(DEADLINE - time.monotonic(), 0.001))
            run(task, link, out)
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
    except Deadline:
        link.timeout = True
    except Gone:
        pass
    if link.timeout:
        out["timeout"] = True
    if link.memory:
        out["memory"] = True
    if link.gone:
        out["gone"] = link.gone
    if link.status is None:
        link.reap(0.0)
    if link.status is not None:
        st = link.status
        out["child"] = {"signal": os.WTERMSIG(st)} if os.WIFSIGNALED(st) else {"exit": os.WEXITSTATUS(st)}
    try:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)  # reap C here: an orphaned zombie would count against the uid's RLIMIT_NPROC
    except OSError:
        pass
    out["nonce"] = nonce
    return out


try:
    RESULT = main()
except BaseException:
    signal.setitimer(signal.ITIMER_REAL, 0)
    RESULT = {"status": "harness_error", "message": format_exc()[-2000:]}
write_all(1, (repr(RESULT) + "\n").encode("utf-8", "backslashreplace"))
os._exit(0)
'''

_PROBE = (
    "import sys, _pickle, ctypes, marshal, resource, select, struct\n"
    "print(sys.version.split()[0]); print(sys.base_prefix); print(sys.exec_prefix)\n"
)


# --------------------------------------------------------------------------------------
# Extraction and reference parsing (parent side; never executes candidate code)
# --------------------------------------------------------------------------------------
_FENCE = re.compile(r"```[ \t]*([A-Za-z0-9_+.-]*)[^\n]*\n(.*?)(?:^[ \t]*```|\Z)", re.S | re.M)
_IMPORT_LINE = re.compile(r"^(?:from[ \t]+\S+[ \t]+)?import[ \t].*$", re.M)
_PY_TAGS = {"python", "py", "python3", "py3"}


def _defines(code: str, name: str) -> bool:
    return re.search(r"^[ \t]*(?:async[ \t]+)?def[ \t]+" + re.escape(name) + r"[ \t]*\(", code, re.M) is not None


_TOP_DEF = re.compile(r"^(?:async[ \t]+)?(?:def|class)[ \t]+(\w+)", re.M)


def extract_code(completion: str) -> str | None:
    """The submitted Python code in a completion (rule in the module docstring), or None."""
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


# --------------------------------------------------------------------------------------
# Environment probes (cached per process)
# --------------------------------------------------------------------------------------
_probe_lock = threading.Lock()
_probe_cache: dict[Any, Any] = {}


@dataclass(frozen=True)
class _Interpreter:
    path: str
    version: str
    prefixes: tuple[str, ...]


class _UidPool:
    """Per-run uids for root: unique among live processes (the pid picks the range)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        # FIFO: a uid comes back only after all others were used, so stray zombies of
        # a run (reaped by init at its own pace) never count against the next one.
        self._free = collections.deque(range(_UID_SLOTS))
        self._sem = threading.BoundedSemaphore(_UID_SLOTS)

    @contextmanager
    def lease(self) -> Iterator[int]:
        self._sem.acquire()
        with self._lock:
            slot = self._free.popleft()
        try:
            yield _UID_BASE + (os.getpid() % (1 << 22)) * _UID_SLOTS + slot
        finally:
            with self._lock:
                self._free.append(slot)
            self._sem.release()


_UIDS = _UidPool()


def _reinit_after_fork() -> None:
    # A fork taken while another thread held a lock would leave it locked forever in the child.
    global _UIDS, _probe_lock
    _UIDS = _UidPool()
    _probe_lock = threading.Lock()


os.register_at_fork(after_in_child=_reinit_after_fork)


def _is_root() -> bool:
    return os.geteuid() == 0


def _as_user(argv: list[str], uid: int | None, fast: bool = True) -> tuple[list[str], dict[str, Any]]:
    """(argv, Popen kwargs) that run `argv` as `uid` (None: as ourselves).

    fast: util-linux `setpriv` switches the uid in the child, so Popen can still use vfork;
    with Popen(user=...) it must fork(), which costs tens of ms in a parent holding GBs of
    memory (a trainer with torch loaded). setpriv keeps its capabilities until its execve,
    so it can exec a binary the uid could not reach; probes therefore use fast=False.
    """
    if uid is None:
        return argv, {}
    setpriv = shutil.which("setpriv", path=_SYSTEM_PATH + ":/usr/sbin:/sbin") if fast else None
    if setpriv:
        return [setpriv, "--reuid", str(uid), "--regid", str(uid), "--clear-groups", "--"] + argv, {}
    return argv, {"user": uid, "group": uid, "extra_groups": []}


def _find_interpreter(explicit: str | None) -> _Interpreter:
    """The first interpreter the sandbox user can run with the harness's imports."""
    key = ("python", explicit, _is_root())
    with _probe_lock:
        if key in _probe_cache:
            return _probe_cache[key]
    candidates = [explicit] if explicit else []
    if not explicit:
        for p in (getattr(sys, "_base_executable", None), sys.executable, "/usr/bin/python3", "/usr/local/bin/python3"):
            if p and os.path.exists(p):
                real = os.path.realpath(p)
                if real not in candidates:
                    candidates.append(real)
    uid = _UID_BASE if _is_root() else None
    tried = []
    for path in candidates:
        try:
            argv, kwargs = _as_user([path, "-S", "-s", "-B", "-c", _PROBE], uid, fast=False)
            r = subprocess.run(argv, capture_output=True, text=True, timeout=30, env={"PATH": _SYSTEM_PATH}, cwd="/",
                               **kwargs)
        except (OSError, subprocess.SubprocessError) as exc:
            tried.append(f"{path} ({exc})")
            continue
        lines = r.stdout.split("\n")
        if r.returncode == 0 and len(lines) >= 3:
            prefixes = tuple(sorted({os.path.realpath(lines[1]), os.path.realpath(lines[2]),
                                     os.path.dirname(os.path.dirname(path))}))
            found = _Interpreter(path, lines[0], prefixes)
            with _probe_lock:
                _probe_cache[key] = found
            return found
        tried.append(f"{path} (exit {r.returncode}: {r.stderr.strip()[-200:]})")
    raise RuntimeError(
        "code sandbox: no Python interpreter the sandbox user can run; tried " + "; ".join(tried)
        + ". Install python3 system-wide (e.g. apt-get install python3) or pass CodeVerifier(python=PATH)"
        " pointing to an interpreter readable by all users"
    )


def _bwrap_path() -> str | None:
    return shutil.which("bwrap", path=_SYSTEM_PATH + ":" + os.environ.get("PATH", ""))


def _unshare_path() -> str | None:
    return shutil.which("unshare", path=_SYSTEM_PATH + ":/usr/sbin:/sbin")


def _bwrap_argv(bwrap: str, interp: _Interpreter, *, bind_root: bool, tmpfs_mb: int) -> list[str]:
    # --as-pid-1: the harness is the namespace's init, so the candidate cannot kill it, and
    # when it exits the kernel kills and reaps everything else before bwrap returns.
    argv = [bwrap, "--unshare-all", "--unshare-user", "--disable-userns", "--die-with-parent", "--new-session",
            "--as-pid-1", "--hostname", "sandbox"]
    if bind_root:
        argv += ["--ro-bind", "/", "/"]
    else:
        argv += ["--ro-bind", "/usr", "/usr", "--ro-bind", "/etc", "/etc"]
        for d in ("/bin", "/sbin", "/lib", "/lib32", "/lib64", "/libx32"):
            if os.path.islink(d):
                argv += ["--symlink", os.readlink(d), d]
            elif os.path.isdir(d):
                argv += ["--ro-bind", d, d]
        for prefix in interp.prefixes:
            if prefix not in ("/", "/usr") and not prefix.startswith(("/usr/", "/etc/")) and os.path.isdir(prefix):
                argv += ["--ro-bind", prefix, prefix]
    size = str(tmpfs_mb << 20)
    argv += ["--dev", "/dev", "--size", str(min(tmpfs_mb, 16) << 20), "--tmpfs", "/dev/shm", "--remount-ro", "/dev",
             "--proc", "/proc", "--size", size, "--tmpfs", "/tmp", "--dir", "/tmp/work"]
    if not bind_root:
        argv += ["--remount-ro", "/"]
    return argv + ["--chdir", "/tmp/work", "--"]


def _probe_bwrap(interp: _Interpreter, bind_root: bool) -> str | None:
    """None when bwrap works here, else why not."""
    key = ("bwrap", interp.path, bind_root, _is_root())
    with _probe_lock:
        if key in _probe_cache:
            return _probe_cache[key]
    bwrap = _bwrap_path()
    if bwrap is None:
        why: str | None = "bwrap not found (apt-get install bubblewrap)"
    else:
        argv, kwargs = _as_user(_bwrap_argv(bwrap, interp, bind_root=bind_root, tmpfs_mb=8)
                                + [interp.path, "-S", "-s", "-B", "-c", _PROBE], _UID_BASE if _is_root() else None,
                                fast=False)
        try:
            r = subprocess.run(argv, capture_output=True, text=True, timeout=30, env={"PATH": _SYSTEM_PATH}, cwd="/",
                               **kwargs)
            why = None if r.returncode == 0 else f"bwrap failed (exit {r.returncode}): {r.stderr.strip()[-300:]}"
        except (OSError, subprocess.SubprocessError) as exc:
            why = f"bwrap failed: {exc}"
    with _probe_lock:
        _probe_cache[key] = why
    return why


def _probe_unshare(interp: _Interpreter) -> bool:
    """Whether `unshare --net --pid ... --setuid` works (root only)."""
    key = ("unshare", interp.path)
    with _probe_lock:
        if key in _probe_cache:
            return _probe_cache[key]
    ok = False
    unshare = _unshare_path()
    if unshare and _is_root():
        argv = _unshare_argv(unshare, _UID_BASE) + [interp.path, "-S", "-s", "-B", "-c", _PROBE]
        try:
            ok = subprocess.run(argv, capture_output=True, timeout=30, env={"PATH": _SYSTEM_PATH}, cwd="/").returncode == 0
        except (OSError, subprocess.SubprocessError):
            ok = False
    with _probe_lock:
        _probe_cache[key] = ok
    return ok


def _unshare_argv(unshare: str, uid: int) -> list[str]:
    return [unshare, "--net", "--pid", "--fork", "--kill-child", "--mount-proc", "--ipc", "--uts",
            "--setgid", str(uid), "--setuid", str(uid), "--"]


def sandbox_mode(python: str | None = None) -> SandboxMode:
    """The mode `CodeVerifier(mode="auto")` uses on this machine: "bwrap" or "rlimits"."""
    interp = _find_interpreter(python)
    return "bwrap" if _probe_bwrap(interp, bind_root=False) is None else "rlimits"


# --------------------------------------------------------------------------------------
# Cleanup helpers
# --------------------------------------------------------------------------------------
def _uid_has_processes(uid: int) -> bool:
    """Whether a live (non-zombie) process runs as `uid`.

    /proc/<pid> of a non-dumpable process is owned by root, so read the status lines.
    """
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(f"/proc/{entry.name}/status", "rb") as f:
                zombie = False
                for line in f:
                    if line.startswith(b"State:"):
                        zombie = line.split()[1] in (b"Z", b"X")
                    elif line.startswith(b"Uid:"):
                        if int(line.split()[1]) == uid and not zombie:
                            return True
                        break
        except (OSError, ValueError, IndexError):
            continue
    return False


def _kill_uid(uid: int, python: str) -> None:
    """Kill every process of `uid` with kill(-1) sent *as* that uid (reaches escaped daemons)."""
    if uid < _UID_BASE or uid == os.getuid():  # never as ourselves, never as root
        raise RuntimeError(f"refusing to kill all processes of uid {uid}")
    script = "import os\ntry:\n    os.kill(-1, 9)\nexcept ProcessLookupError:\n    pass\n"
    for _ in range(20):
        if not _uid_has_processes(uid):
            return
        argv, kwargs = _as_user([python, "-S", "-s", "-B", "-c", script], uid)
        subprocess.run(argv, env={"PATH": _SYSTEM_PATH}, cwd="/", capture_output=True, timeout=10, **kwargs)
        time.sleep(0.01)


def _remove_uid_files(uid: int) -> None:
    for base in ("/tmp", "/var/tmp", "/dev/shm"):
        try:
            entries = list(os.scandir(base))
        except OSError:
            continue
        for entry in entries:
            try:
                if entry.stat(follow_symlinks=False).st_uid != uid:
                    continue
                if entry.is_dir(follow_symlinks=False):
                    _rmtree(entry.path)
                else:
                    os.unlink(entry.path)
            except OSError:
                pass


def _rmtree(path: str) -> None:
    def retry(func: Any, p: str, _exc: Any) -> None:
        try:
            os.chmod(os.path.dirname(p), 0o700)
            os.chmod(p, 0o700)
            func(p)
        except OSError:
            pass

    shutil.rmtree(path, onerror=retry)


# --------------------------------------------------------------------------------------
# Running one sandboxed process
# --------------------------------------------------------------------------------------
@dataclass
class _Run:
    result: dict[str, Any] | None
    stderr_tail: str
    killed_at_deadline: bool


def _communicate(proc: subprocess.Popen, payload: bytes, deadline: float, tail_bytes: int) -> tuple[bytes, bytes, bool]:
    """Feed stdin, read stdout (capped) and a rolling stderr tail until stdout closes or the deadline."""
    assert proc.stdin and proc.stdout and proc.stderr
    sel = selectors.DefaultSelector()
    os.set_blocking(proc.stdin.fileno(), False)
    sel.register(proc.stdin, selectors.EVENT_WRITE)
    sel.register(proc.stdout, selectors.EVENT_READ)
    sel.register(proc.stderr, selectors.EVENT_READ)
    out = bytearray()
    tail = bytearray()
    drained = 0
    view = memoryview(payload)
    stdout_open = True
    timed_out = False
    try:
        while stdout_open:
            left = deadline - time.monotonic()
            if left <= 0:
                timed_out = True
                break
            for key, _ in sel.select(left):
                f = key.fileobj
                if f is proc.stdin:
                    try:
                        view = view[os.write(proc.stdin.fileno(), view[: 1 << 16]):]
                    except BlockingIOError:
                        continue
                    except OSError:  # the sandbox is gone; the missing result says so
                        view = view[:0]
                    if not view:
                        sel.unregister(proc.stdin)
                        proc.stdin.close()
                    continue
                chunk = os.read(f.fileno(), 1 << 16)
                if f is proc.stdout:
                    if not chunk:
                        sel.unregister(proc.stdout)
                        stdout_open = False
                    elif len(out) < _RESULT_CAP:
                        out += chunk
                else:
                    if not chunk:
                        sel.unregister(proc.stderr)
                        continue
                    drained += len(chunk)
                    tail += chunk
                    if len(tail) > 2 * tail_bytes:
                        del tail[:-tail_bytes]
                    if drained > _DRAIN_CAP:  # stop reading: further writes get EPIPE
                        sel.unregister(proc.stderr)
                        proc.stderr.close()
    finally:
        sel.close()
    return bytes(out), bytes(tail[-tail_bytes:]), timed_out


def _wait_exit_unreaped(pid: int, timeout: float) -> bool:
    """Wait up to `timeout` for `pid` to exit without reaping it (waitid WNOWAIT)."""
    end = time.monotonic() + timeout
    while True:
        try:
            if os.waitid(os.P_PID, pid, os.WEXITED | os.WNOHANG | os.WNOWAIT) is not None:
                return True
        except ChildProcessError:
            return True
        if time.monotonic() >= end:
            return False
        time.sleep(0.001)


def _drain_tail(f: Any, tail: bytes, tail_bytes: int) -> bytes:
    """What is left in the stderr pipe once every writer is dead (bounded)."""
    if f.closed:
        return tail
    buf = bytearray(tail)
    os.set_blocking(f.fileno(), False)
    total = 0
    try:
        while total < _DRAIN_CAP:
            chunk = os.read(f.fileno(), 1 << 16)
            if not chunk:
                break
            total += len(chunk)
            buf += chunk
            if len(buf) > 2 * tail_bytes:
                del buf[:-tail_bytes]
    except (BlockingIOError, OSError):
        pass
    return bytes(buf[-tail_bytes:])


# --------------------------------------------------------------------------------------
# The verifier
# --------------------------------------------------------------------------------------
class CodeVerifier(Verifier):
    """Runs extracted Python against the reference's tests in a sandbox (module docstring).

    Options: mode ("auto" | "bwrap" | "rlimits"), partial_credit (score = passed/total),
    time_limit_s (wall clock for loading the code and running all tests), cpu_limit_s
    (per process; default int(time_limit_s) + 2), memory_mb (address space per process),
    max_processes, max_file_mb, max_open_files, tmpfs_mb (bwrap scratch space), python
    (sandbox interpreter), namespaces (rlimits mode as root: use `unshare`), bind_root
    (bwrap: bind all of / read-only), output_tail_bytes, max_code_chars.
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
        self._unshare = _unshare_path() if (self.mode == "rlimits" and namespaces and _probe_unshare(self._interp)) else None
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
    def isolation(self) -> str:
        """What the active mode isolates, in words (also in Verdict.details)."""
        who = "per-run uid" if _is_root() else "own uid"
        if self.mode == "bwrap":
            return f"bwrap: user+pid+net+ipc+uts+mount namespaces, {who}, rlimits"
        if self._unshare:
            return f"unshare: pid+net+ipc+uts+mount namespaces, {who}, rlimits"
        return f"{who}, rlimits only"

    def check(self, completion: str, reference: Any) -> Verdict:
        task = _parse_reference(reference)
        base = {"mode": self.mode, "isolation": self.isolation, "python": self.python,
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
            with _UIDS.lease() as uid:
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
        else:
            workdir = tempfile.mkdtemp(prefix=f"posttrain-sandbox-{os.getpid()}-")
            if uid is not None:
                os.chown(workdir, uid, uid)
            os.chmod(workdir, 0o700)
            env.update(HOME=workdir, TMPDIR=workdir)
            cwd = workdir
            if uid is None:  # the count is per uid: leave room for what the user already runs
                nproc = _count_tasks(os.getuid()) + self.max_processes + 1
            else:
                nproc = self.max_processes + 1
            if self._unshare and uid is not None:
                argv = _unshare_argv(self._unshare, uid) + python + self._config(nproc)
                kwargs = {}
            else:
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
                    if self.mode == "rlimits":
                        _remove_uid_files(uid)
            tail = _drain_tail(proc.stderr, tail, self.output_tail_bytes)
        finally:
            if proc is not None:
                for f in (proc.stdin, proc.stdout, proc.stderr):
                    if f is not None and not f.closed:
                        try:
                            f.close()
                        except OSError:
                            pass
            if workdir is not None:
                _rmtree(workdir)
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


def _count_tasks(uid: int) -> int:
    """Threads of `uid` (RLIMIT_NPROC counts threads); only for the non-root fallback."""
    n = 0
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(f"/proc/{entry.name}/status", "rb") as f:
                fields = dict(line.split(b":", 1) for line in f if b":" in line)
            if int(fields[b"Uid"].split()[1]) == uid:
                n += int(fields[b"Threads"])
        except (OSError, KeyError, ValueError, IndexError):
            continue
    return n


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
    if _is_root() and _probe_unshare(interp):
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


# --------------------------------------------------------------------------------------
# Audit problems (written for this project) and hostile programs
# --------------------------------------------------------------------------------------
def _problem(entry: str, signature: str, doc: str, body: str, tests: Any) -> dict[str, Any]:
    prompt = f"def {entry}{signature}:\n    \"\"\"{doc}\"\"\"\n"
    return {"entry_point": entry, "prompt": prompt, "solution": prompt + body, "tests": tests}


_PROBLEMS: list[dict[str, Any]] = [
    _problem("running_max", "(xs: list[int]) -> list[int]",
             "Return the running maximum: element i is max(xs[:i+1]). running_max([1, 3, 2]) == [1, 3, 3]",
             "    out = []\n    for x in xs:\n        out.append(x if not out else max(out[-1], x))\n    return out\n",
             "def check(candidate):\n    assert candidate([]) == []\n    assert candidate([1, 3, 2]) == [1, 3, 3]\n"
             "    assert candidate([-5, -7, -1, -9]) == [-5, -5, -1, -1]\n    assert candidate([4]) == [4]\n"),
    _problem("is_palindrome", "(s: str) -> bool",
             "True when s reads the same backwards, ignoring case and non-alphanumeric characters.",
             "    t = [c.lower() for c in s if c.isalnum()]\n    return t == t[::-1]\n",
             ["assert is_palindrome('') is True", "assert is_palindrome('A man, a plan, a canal: Panama') is True",
              "assert is_palindrome('abca') is False", "assert is_palindrome('No lemon, no melon') is True"]),
    _problem("count_vowels", "(s: str) -> int", "Number of vowels (a, e, i, o, u; either case) in s.",
             "    return sum(c in 'aeiouAEIOU' for c in s)\n",
             "def check(candidate):\n    assert candidate('') == 0\n    assert candidate('Hello World') == 3\n"
             "    assert candidate('AEIOUxyz') == 5\n    assert candidate('rhythm') == 0\n"),
    _problem("fizzbuzz", "(n: int) -> list[str]",
             "Strings for 1..n: 'Fizz' for multiples of 3, 'Buzz' of 5, 'FizzBuzz' of both, else the number.",
             "    out = []\n    for i in range(1, n + 1):\n        s = ('Fizz' if i % 3 == 0 else '') + ('Buzz' if i % 5 == 0 else '')\n"
             "        out.append(s or str(i))\n    return out\n",
             ["assert fizzbuzz(0) == []", "assert fizzbuzz(5) == ['1', '2', 'Fizz', '4', 'Buzz']",
              "assert fizzbuzz(15)[-1] == 'FizzBuzz'", "assert len(fizzbuzz(100)) == 100"]),
    _problem("run_length", "(s: str) -> list[tuple[str, int]]",
             "Run-length encoding: run_length('aaab') == [('a', 3), ('b', 1)].",
             "    out = []\n    for c in s:\n        if out and out[-1][0] == c:\n            out[-1] = (c, out[-1][1] + 1)\n"
             "        else:\n            out.append((c, 1))\n    return out\n",
             "def check(candidate):\n    assert candidate('') == []\n    assert candidate('aaab') == [('a', 3), ('b', 1)]\n"
             "    assert candidate('abba') == [('a', 1), ('b', 2), ('a', 1)]\n"),
    _problem("second_largest", "(xs: list[int]) -> int | None",
             "The second largest distinct value in xs, or None when there is none.",
             "    d = sorted(set(xs))\n    return d[-2] if len(d) >= 2 else None\n",
             ["assert second_largest([1, 2, 3]) == 2", "assert second_largest([5, 5, 5]) is None",
              "assert second_largest([]) is None", "assert second_largest([-1, -2, -2, 7]) == -1"]),
    _problem("flatten", "(nested: list) -> list",
             "Flatten arbitrarily nested lists: flatten([1, [2, [3]]]) == [1, 2, 3].",
             "    out = []\n    for x in nested:\n        if isinstance(x, list):\n            out.extend(flatten(x))\n"
             "        else:\n            out.append(x)\n    return out\n",
             "def check(candidate):\n    assert candidate([]) == []\n    assert candidate([1, [2, [3, [4]]], 5]) == [1, 2, 3, 4, 5]\n"
             "    assert candidate([[], [[]], ['a']]) == ['a']\n"),
    _problem("gcd_list", "(xs: list[int]) -> int",
             "Greatest common divisor of all numbers in xs (non-empty, non-negative); gcd_list([0]) == 0.",
             "    g = 0\n    for x in xs:\n        a, b = g, x\n        while b:\n            a, b = b, a % b\n        g = a\n    return g\n",
             ["assert gcd_list([12, 18]) == 6", "assert gcd_list([7]) == 7", "assert gcd_list([0, 0]) == 0",
              "assert gcd_list([100, 75, 50]) == 25"]),
    _problem("word_counts", "(text: str) -> dict[str, int]",
             "Count lower-cased words (split on whitespace) in text.",
             "    counts = {}\n    for w in text.lower().split():\n        counts[w] = counts.get(w, 0) + 1\n    return counts\n",
             "def check(candidate):\n    assert candidate('') == {}\n    assert candidate('a b A') == {'a': 2, 'b': 1}\n"
             "    assert candidate('  x\\ty\\nx ') == {'x': 2, 'y': 1}\n"),
    _problem("rotate", "(xs: list, k: int) -> list",
             "Rotate xs right by k places (k may be negative or larger than len(xs)).",
             "    if not xs:\n        return []\n    k %= len(xs)\n    return xs[-k:] + xs[:-k] if k else list(xs)\n",
             ["assert rotate([1, 2, 3, 4], 1) == [4, 1, 2, 3]", "assert rotate([1, 2, 3], -1) == [2, 3, 1]",
              "assert rotate([], 5) == []", "assert rotate([1, 2], 4) == [1, 2]"]),
    _problem("balanced", "(s: str) -> bool",
             "True when the brackets ()[]{} in s are balanced and properly nested; other characters are ignored.",
             "    pairs = {')': '(', ']': '[', '}': '{'}\n    stack = []\n    for c in s:\n        if c in '([{':\n"
             "            stack.append(c)\n        elif c in pairs:\n            if not stack or stack.pop() != pairs[c]:\n"
             "                return False\n    return not stack\n",
             "def check(candidate):\n    assert candidate('') is True\n    assert candidate('([]{})') is True\n"
             "    assert candidate('(]') is False\n    assert candidate('((') is False\n    assert candidate('a(b)c') is True\n"),
    _problem("digit_sum", "(n: int) -> int", "Sum of the decimal digits of n (sign ignored).",
             "    return sum(int(c) for c in str(abs(n)))\n",
             ["assert digit_sum(0) == 0", "assert digit_sum(123) == 6", "assert digit_sum(-45) == 9",
              "assert digit_sum(10**20) == 1"]),
]

# Each program below tries to score without solving the problem; ENTRY is the entry point.
_ADVERSARIAL: list[tuple[str, str]] = [
    ("early sys.exit(0)", "import sys\nsys.exit(0)\ndef ENTRY(*a, **k):\n    return None"),
    ("os._exit(0) at import", "import os\nos._exit(0)"),
    ("os._exit(0) inside the call", "import os\ndef ENTRY(*a, **k):\n    os._exit(0)"),
    ("raise SystemExit in the call", "def ENTRY(*a, **k):\n    raise SystemExit(0)"),
    ("fake success print",
     "print('All tests passed')\nprint('{\"status\": \"done\", \"total\": 1, \"executed\": 1, \"passed\": 1}')\n"
     "def ENTRY(*a, **k):\n    print('PASSED')\n    return None"),
    ("always-equal return value",
     "class _Any:\n    def __eq__(self, other):\n        return True\n    def __ne__(self, other):\n        return False\n"
     "    def __bool__(self):\n        return True\ndef ENTRY(*a, **k):\n    return _Any()"),
    ("int subclass with rigged __eq__",
     "class _I(int):\n    def __eq__(self, other):\n        return True\n    __hash__ = int.__hash__\n"
     "def ENTRY(*a, **k):\n    return _I(0)"),
    ("redefine check, print and builtins",
     "import builtins\ndef check(candidate):\n    return True\nbuiltins.print = lambda *a, **k: None\n"
     "builtins.AssertionError = type('AssertionError', (Exception,), {})\nbuiltins.isinstance = lambda *a: True\n"
     "def ENTRY(*a, **k):\n    return None"),
    ("patch the harness through gc and sys.modules",
     "import gc, sys\nmain = sys.modules.get('__main__')\n"
     "for name in ('run', 'main', 'Candidate', 'Link', 'limit', 'harden'):\n"
     "    if main is not None and hasattr(main, name):\n        setattr(main, name, lambda *a, **k: None)\n"
     "for obj in gc.get_objects():\n    if isinstance(obj, dict) and 'check' in obj:\n"
     "        obj['check'] = lambda candidate: True\n"
     "def ENTRY(*a, **k):\n    return None"),
    ("forge the result channel",
     "import os\nline = repr({'status': 'done', 'total': 1, 'executed': 1, 'passed': 1, 'failures': [],"
     " 'nonce': 'x'}) + '\\n'\nfor fd in range(0, 64):\n    try:\n        os.write(fd, line.encode())\n    except OSError:\n"
     "        pass\nfor pid in os.listdir('/proc'):\n    if pid.isdigit():\n        for fd in ('1', '3', '4'):\n"
     "            try:\n                with open('/proc/%s/fd/%s' % (pid, fd), 'w') as f:\n                    f.write(line)\n"
     "            except OSError:\n                pass\ndef ENTRY(*a, **k):\n    return None"),
    ("read the tests from the harness's memory",
     "import os\nleak = ''\nppid = os.getppid()\nfor path in ('/proc/%d/mem' % ppid, '/proc/%d/environ' % ppid):\n"
     "    try:\n        leak += open(path, 'rb').read(100).decode('latin-1')\n    except OSError:\n        pass\n"
     "def ENTRY(*a, **k):\n    return leak or None"),
    ("kill the parent", "import os, signal\ntry:\n    os.kill(os.getppid(), signal.SIGKILL)\nexcept OSError:\n    pass\n"
     "try:\n    os.killpg(0, signal.SIGKILL)\nexcept OSError:\n    pass\ndef ENTRY(*a, **k):\n    return None"),
    ("fork bomb", "import os\nwhile True:\n    try:\n        os.fork()\n    except OSError:\n        pass"),
    ("infinite loop", "def ENTRY(*a, **k):\n    while True:\n        pass"),
    ("memory bomb", "hog = []\nwhile True:\n    hog.append(bytearray(1 << 24))"),
    ("huge file", "with open('big.bin', 'wb') as f:\n    while True:\n        f.write(b'\\0' * (1 << 20))"),
    ("network", "import socket\ns = socket.create_connection(('1.1.1.1', 80), timeout=2)\n"
     "def ENTRY(*a, **k):\n    return None"),
]
