"""The host side of one sandboxed run: interpreter and bwrap/unshare probes (cached per
process), modes, per-run uids, argv builders, pipe I/O with deadlines and bounded output,
and cleanup. Modes, limits and the threat model: the package docstring,
verifiers/code_sandbox/__init__.py.
"""
from __future__ import annotations

import ast
import collections
import errno
import marshal
import os
import selectors
import shutil
import stat
import subprocess
import sys
import tempfile
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


def _system_view(interp: _Interpreter) -> list[tuple[str, str, str]]:
    """What both sandboxes show of the host by default: ("bind", path, path) read-only binds of
    /usr, /etc, /bin, /sbin, /lib* and the interpreter's prefixes, ("link", path, target) for the
    merged-/usr symlinks. Nothing else of the host filesystem (home directories, datasets, the
    checkout, /tmp, /var, /run) is visible."""
    view: list[tuple[str, str, str]] = [("bind", "/usr", "/usr"), ("bind", "/etc", "/etc")]
    for d in ("/bin", "/sbin", "/lib", "/lib32", "/lib64", "/libx32"):
        if os.path.islink(d):
            view.append(("link", d, os.readlink(d)))
        elif os.path.isdir(d):
            view.append(("bind", d, d))
    for prefix in interp.prefixes:
        if prefix not in ("/", "/usr") and not prefix.startswith(("/usr/", "/etc/")) and os.path.isdir(prefix):
            view.append(("bind", prefix, prefix))
    return view


def _bwrap_argv(bwrap: str, interp: _Interpreter, *, bind_root: bool, tmpfs_mb: int) -> list[str]:
    # --as-pid-1: the harness is the namespace's init, so the candidate cannot kill it, and
    # when it exits the kernel kills and reaps everything else before bwrap returns.
    argv = [bwrap, "--unshare-all", "--unshare-user", "--disable-userns", "--die-with-parent", "--new-session",
            "--as-pid-1", "--hostname", "sandbox"]
    if bind_root:
        argv += ["--ro-bind", "/", "/"]
    else:
        for kind, path, source in _system_view(interp):
            argv += ["--symlink", source, path] if kind == "link" else ["--ro-bind", source, path]
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


# How the fallback's harness makes its view read-only: "auto" (mount_setattr(2) with
# AT_RECURSIVE, Linux >= 5.12, else one bind remount per mount) or "remount" (always the
# latter; tests use it to exercise that path).
_VIEW_READONLY = "auto"


def _view_args(interp: _Interpreter, uid: int, *, bind_root: bool, tmpfs_mb: int) -> list[str]:
    """The harness's argv tail that makes it build the fallback's filesystem view, then drop to `uid`.

    Layout: view UID TMP_BYTES SHM_BYTES (min|root) (auto|remount) then `b PATH` (read-only
    bind) or `l PATH TARGET` (symlink) items; see harness.py, enter_view.
    """
    argv = ["view", str(uid), str(tmpfs_mb << 20), str(min(tmpfs_mb, 16) << 20), "root" if bind_root else "min",
            _VIEW_READONLY]
    if not bind_root:
        for kind, path, source in _system_view(interp):
            argv += ["l", path, source] if kind == "link" else ["b", path]
    return argv


def _unshare_argv(unshare: str) -> list[str]:
    # No --setuid: the harness starts as root inside the new namespaces, builds its
    # filesystem view (harness.py, enter_view) and then drops to the run's uid itself.
    return [unshare, "--net", "--pid", "--fork", "--kill-child", "--mount-proc", "--ipc", "--uts", "--"]


# The harness's config ints for probes: timeout, cpu, mem, fsize, nofile, nproc, max_msg, max_failures.
_PROBE_CONFIG = ["10.0", "10", str(256 << 20), str(1 << 20), "64", "16", str(1 << 20), "5"]


def _probe_unshare(interp: _Interpreter, bind_root: bool = False) -> bool:
    """Whether the fallback's namespaces work here (root only): `unshare --net --pid ...` plus
    the harness's own view (read-only root, private /tmp) and its switch to a per-run uid."""
    key = ("unshare", interp.path, bind_root)
    with _probe_lock:
        if key in _probe_cache:
            return _probe_cache[key]
    ok = False
    unshare = _unshare_path()
    if unshare and _is_root():
        argv = (_unshare_argv(unshare) + [interp.path, "-S", "-s", "-B", "-c", _HARNESS] + _PROBE_CONFIG
                + _view_args(interp, _UID_BASE, bind_root=bind_root, tmpfs_mb=8))
        payload = marshal.dumps({"nonce": "probe", "probe": True}, 4)
        try:
            r = subprocess.run(argv, input=payload, capture_output=True, timeout=30, env={"PATH": _SYSTEM_PATH},
                               cwd="/")
            line = r.stdout.split(b"\n", 1)[0].decode("utf-8", "replace")
            res = ast.literal_eval(line) if line else None
            ok = (isinstance(res, dict) and res.get("status") == "probe" and res.get("uid") == _UID_BASE
                  and res.get("root_writable") is False and res.get("work_writable") is True)
        except (OSError, subprocess.SubprocessError, ValueError, SyntaxError):
            ok = False
    with _probe_lock:
        _probe_cache[key] = ok
    return ok


def sandbox_mode(python: str | None = None) -> SandboxMode:
    """The mode `CodeVerifier(mode="auto")` uses on this machine: "bwrap" or "rlimits"."""
    interp = _find_interpreter(python)
    return "bwrap" if _probe_bwrap(interp, bind_root=False) is None else "rlimits"


# --------------------------------------------------------------------------------------
# Cleanup helpers
# --------------------------------------------------------------------------------------
def run_uids() -> range:
    """The per-run uids this process's sandboxes use (a range picked by the pid, so that concurrent processes
    running sandboxes never share a uid)."""
    first = _UID_BASE + (os.getpid() % (1 << 22)) * _UID_SLOTS
    return range(first, first + _UID_SLOTS)


def uid_processes(uids: range | None = None) -> list[str]:
    """Live (non-zombie) processes running as one of `uids` (default: `run_uids()`), as "pid uid=U name":
    after a check returns there must be none (the tests and diagnostics ask this)."""
    uids = run_uids() if uids is None else uids
    found = []
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(f"/proc/{entry.name}/status") as f:
                status = dict(line.split(":", 1) for line in f if ":" in line)
        except OSError:
            continue
        uid = int(status["Uid"].split()[1])
        if uid in uids and status["State"].split()[0] not in ("Z", "X"):
            found.append(f"{entry.name} uid={uid} {status['Name'].strip()}")
    return found


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


# Removal of a run's files. Rules: never follow a symlink (every name is opened relative to
# its parent's fd with O_NOFOLLOW and checked against the inode lstat saw), never leave the
# tree (no crossing onto another device, nothing above the top directory is touched), and
# never chmod anything but a directory of the run's own tree, owned by us, when we are not
# root and the candidate made it unreadable (root needs no chmod at all).
_O_DIR = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC
_MAX_DEPTH = 64  # deeper directories are moved up to the top directory and removed from there
_MAX_REMOVALS = 1_000_000


@dataclass(frozen=True)
class _WorkDir:
    """A host work directory the verifier created (fallback without namespaces): its path, and an
    fd opened at creation, so cleanup finds the same inode even if the run renamed the path."""
    path: str
    fd: int
    dev: int
    ino: int


def _make_workdir(uid: int | None) -> _WorkDir:
    path = tempfile.mkdtemp(prefix=f"posttrain-sandbox-{os.getpid()}-")
    fd = os.open(path, _O_DIR)
    try:
        if uid is not None:
            os.fchown(fd, uid, uid)
        os.fchmod(fd, 0o700)
        st = os.fstat(fd)
    except BaseException:
        os.close(fd)
        os.rmdir(path)
        raise
    return _WorkDir(path, fd, st.st_dev, st.st_ino)


def _remove_workdir(work: _WorkDir) -> None:
    """Empty the work directory through the fd taken at creation, then remove its name only if
    the name still denotes that directory (the run may have renamed it and put something else,
    e.g. a symlink, in its place; as root, the uid scan then finds the renamed directory)."""
    try:
        _clear_dir(work.fd, work.dev)
        parent = os.open(os.path.dirname(work.path), os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        try:
            name = os.path.basename(work.path)
            st = os.stat(name, dir_fd=parent, follow_symlinks=False)
            if stat.S_ISDIR(st.st_mode) and (st.st_dev, st.st_ino) == (work.dev, work.ino):
                os.rmdir(name, dir_fd=parent)
        finally:
            os.close(parent)
    except OSError:
        pass
    finally:
        os.close(work.fd)


def _open_subdir(parent: int, name: str, st: os.stat_result) -> int | None:
    """fd of directory `name` in `parent`, the very inode `st` describes; None if it is gone,
    was swapped, or cannot be opened."""
    try:
        fd = os.open(name, _O_DIR, dir_fd=parent)
    except PermissionError:
        if _is_root() or st.st_uid != os.geteuid():
            return None
        # Not root: the candidate (our own uid) made its directory unreadable. Give it back
        # u+rwx, through an O_PATH fd of that inode (never through a name that could be a link).
        try:
            pfd = os.open(name, os.O_PATH | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC, dir_fd=parent)
        except OSError:
            return None
        try:
            pst = os.fstat(pfd)
            if (pst.st_dev, pst.st_ino) != (st.st_dev, st.st_ino):
                return None
            os.chmod(f"/proc/self/fd/{pfd}", stat.S_IMODE(pst.st_mode) | stat.S_IRWXU)
        except OSError:
            return None
        finally:
            os.close(pfd)
        try:
            fd = os.open(name, _O_DIR, dir_fd=parent)
        except OSError:
            return None
    except OSError:
        return None
    fst = os.fstat(fd)
    if (fst.st_dev, fst.st_ino) != (st.st_dev, st.st_ino):
        os.close(fd)
        return None
    if not _is_root() and fst.st_uid == os.geteuid() and stat.S_IMODE(fst.st_mode) & stat.S_IRWXU != stat.S_IRWXU:
        try:
            os.fchmod(fd, stat.S_IMODE(fst.st_mode) | stat.S_IRWXU)  # needed to unlink its entries
        except OSError:
            pass
    return fd


def _clear_dir(top: int, dev: int) -> None:
    """Remove everything inside the open directory `top` (not `top` itself)."""
    budget = [_MAX_REMOVALS]
    if not _is_root():
        try:
            st = os.fstat(top)
            if st.st_uid == os.geteuid() and stat.S_IMODE(st.st_mode) & stat.S_IRWXU != stat.S_IRWXU:
                os.fchmod(top, stat.S_IMODE(st.st_mode) | stat.S_IRWXU)  # the top is ours: we created it
        except OSError:
            pass
    while budget[0] > 0:
        before = budget[0]
        _clear_level(top, top, dev, 0, budget)
        try:
            if not os.listdir(top) or budget[0] == before:
                return  # empty, or no progress (what is left cannot be removed)
        except OSError:
            return


def _clear_level(fd: int, top: int, dev: int, depth: int, budget: list[int]) -> None:
    try:
        names = os.listdir(fd)
    except OSError:
        return
    for name in names:
        if budget[0] <= 0:
            return
        try:
            st = os.stat(name, dir_fd=fd, follow_symlinks=False)
        except OSError:
            continue
        try:
            if not stat.S_ISDIR(st.st_mode):
                os.unlink(name, dir_fd=fd)  # a symlink is removed, never followed
                budget[0] -= 1
                continue
            if st.st_dev != dev:
                continue  # a mount point: not ours to empty
            try:
                os.rmdir(name, dir_fd=fd)
                budget[0] -= 1
                continue
            except OSError as exc:
                if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST, errno.EACCES, errno.EPERM):
                    continue
            if depth >= _MAX_DEPTH:
                # Bounded recursion and fds: move the deep part up; a later pass removes it.
                os.rename(name, f".posttrain-deep-{st.st_ino}-{budget[0]}", src_dir_fd=fd, dst_dir_fd=top)
                budget[0] -= 1
                continue
            sub = _open_subdir(fd, name, st)
            if sub is None:
                continue
            try:
                _clear_level(sub, top, dev, depth + 1, budget)
            finally:
                os.close(sub)
            os.rmdir(name, dir_fd=fd)
            budget[0] -= 1
        except OSError:
            continue


def _remove_entry(parent: int, name: str, uid: int | None = None) -> None:
    """Remove `name` in the open directory `parent` (a directory with its whole tree), if it is
    owned by `uid` (None: any owner). Never follows a symlink."""
    try:
        st = os.stat(name, dir_fd=parent, follow_symlinks=False)
    except OSError:
        return
    if uid is not None and st.st_uid != uid:
        return
    try:
        if not stat.S_ISDIR(st.st_mode):
            os.unlink(name, dir_fd=parent)
            return
        sub = _open_subdir(parent, name, st)
        if sub is None:
            return
        try:
            _clear_dir(sub, st.st_dev)
        finally:
            os.close(sub)
        os.rmdir(name, dir_fd=parent)
    except OSError:
        pass


def _remove_uid_files(uid: int) -> None:
    """Remove the entries of /tmp, /var/tmp and /dev/shm owned by `uid` (root, fallback
    without namespaces: the only mode where a run can write there; it is killed by now)."""
    if uid < _UID_BASE or uid == os.getuid():
        raise RuntimeError(f"refusing to remove the files of uid {uid}")
    for base in ("/tmp", "/var/tmp", "/dev/shm"):
        try:
            fd = os.open(base, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        except OSError:
            continue
        try:
            for name in os.listdir(fd):
                _remove_entry(fd, name, uid)
        except OSError:
            pass
        finally:
            os.close(fd)


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
