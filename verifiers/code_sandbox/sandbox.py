"""The host side of one sandboxed run: interpreter and bwrap/unshare probes (cached per
process), modes, per-run uids, argv builders, pipe I/O with deadlines and bounded output,
and cleanup. Modes, limits and the threat model: the package docstring,
verifiers/code_sandbox/__init__.py.
"""
from __future__ import annotations

import collections
import os
import selectors
import shutil
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Literal

SandboxMode = Literal["bwrap", "rlimits"]

_SYSTEM_PATH = "/usr/local/bin:/usr/bin:/bin"
_UID_BASE = 1 << 30
_UID_SLOTS = 256
_RESULT_CAP = 1 << 20  # bytes of harness stdout we accept
_DRAIN_CAP = 8 << 20  # bytes of candidate output we read before closing the pipe

# The harness (harness.py): runs inside the sandbox as `python -S -s -B -c _HARNESS <config ints>`.
# A file of this package, so it ships with a non-editable install; read once, at import.
_HARNESS = (Path(__file__).parent / "harness.py").read_text(encoding="utf-8")

_PROBE = (
    "import sys, _pickle, ctypes, marshal, resource, select, struct\n"
    "print(sys.version.split()[0]); print(sys.base_prefix); print(sys.exec_prefix)\n"
)


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
