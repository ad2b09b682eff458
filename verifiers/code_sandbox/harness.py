# The sandbox-side harness (processes P and C of the package docstring). It is NOT imported:
# sandbox.py reads this file's text and the sandbox runs it as
# `python -S -s -B -c <this file> <config ints>` (see CodeVerifier._config for the ints).
# It imports only C modules on the normal path (no json/re/traceback: start-up time is
# the sandbox's overhead); the task arrives as marshal data, the result leaves as a repr
# that the parent reads with ast.literal_eval.
# Standard library only, Python >= 3.8.
if __name__ != "__main__":  # importing it would fork and take over the importing process
    raise ImportError("verifiers/code_sandbox/harness.py runs only inside the sandbox (python -c); do not import it")
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


# ------------------------------------------------------- fallback filesystem view (root)
# Only in the fallback with namespaces: the parent starts us as root in fresh mount, pid,
# net, ipc and uts namespaces (`unshare ... --mount-proc`, no --setuid); argv[9:] is
# `view UID TMP_BYTES SHM_BYTES (min|root) (auto|remount) ITEMS...` (sandbox.py, _view_args).
MS_RDONLY, MS_NOSUID, MS_NODEV, MS_REMOUNT, MS_BIND, MS_REC, MS_PRIVATE = 1, 2, 4, 32, 4096, 16384, 1 << 18
# statvfs flags a bind remount must keep (same values as MS_NOSUID, MS_NODEV, MS_NOEXEC,
# MS_NOATIME, MS_NODIRATIME; the kernel keeps relatime/strictatime on a remount by itself).
KEEP_FLAGS = 2 | 4 | 8 | 1024 | 2048
# pivot_root's syscall number; mount_setattr is 442 on all of these (the unified table).
PIVOT_ROOT = {"x86_64": 155, "aarch64": 41, "riscv64": 41, "ppc64le": 203, "ppc64": 203, "s390x": 217}


def enter_view(args):
    """Build the run's filesystem in this (private) mount namespace, then drop root.

    "min": a new root holding read-only binds of the ITEMS (/usr, /etc, /lib*, the
    interpreter's prefix), this pid namespace's /proc (read-only), /dev with null, zero,
    full, random, urandom and tty only, and fresh size-limited tmpfs at /tmp and /dev/shm;
    pivot_root into it and detach the host's tree (chroot where pivot_root is unknown).
    "root": every mount of the host read-only, fresh tmpfs over /tmp and /dev/shm.
    Then /tmp/work (0700, the run's uid) is cwd, and all of uid/gid/groups become UID.
    """
    uid, tmp_bytes, shm_bytes, view, how = int(args[0]), int(args[1]), int(args[2]), args[3], args[4]
    items = args[5:]
    libc = ctypes.CDLL(None, use_errno=True)

    def enc(x):
        return x.encode("utf-8", "surrogateescape") if isinstance(x, str) else x

    def mount(src, dst, fstype, flags, data=None):
        if libc.mount(enc(src), enc(dst), enc(fstype), ctypes.c_ulong(flags), enc(data)) != 0:
            e = ctypes.get_errno()
            raise OSError(e, "mount(%r, %r): %s" % (src, dst, os.strerror(e)))

    def mounts_under(top):
        out = []
        with open("/proc/self/mountinfo", "rb") as f:
            for line in f:
                point = line.split(b" ")[4]
                for code in (b"\\040", b"\\011", b"\\012", b"\\134"):  # escapes: space, tab, newline, \\ last
                    point = point.replace(code, bytes([int(code[1:], 8)]))
                point = point.decode("utf-8", "surrogateescape")
                if top == "/" or point == top or point.startswith(top + "/"):
                    out.append(point)
        return out

    def readonly(top):
        if how == "auto" and os.uname().machine in PIVOT_ROOT:
            class MountAttr(ctypes.Structure):
                _fields_ = [("attr_set", ctypes.c_uint64), ("attr_clr", ctypes.c_uint64),
                            ("propagation", ctypes.c_uint64), ("userns_fd", ctypes.c_uint64)]
            attr = MountAttr(MS_RDONLY | MS_NOSUID, 0, 0, 0)  # MOUNT_ATTR_RDONLY | MOUNT_ATTR_NOSUID
            # mount_setattr(AT_FDCWD, top, AT_RECURSIVE, &attr, sizeof attr): one call, all or nothing.
            if libc.syscall(442, -100, enc(top), 0x8000, ctypes.byref(attr), ctypes.c_size_t(32)) == 0:
                return
        for point in mounts_under(top):  # older kernels: one bind remount per mount, keeping its flags
            try:
                keep = os.statvfs(point).f_flag & KEEP_FLAGS
            except OSError:
                continue  # shadowed by a later mount, or not reachable by root (FUSE): not visible either
            mount(None, point, None, MS_REMOUNT | MS_BIND | MS_RDONLY | MS_NOSUID | keep)

    mount(None, "/", None, MS_REC | MS_PRIVATE)  # nothing we mount propagates to the host
    if view == "min":
        new = "/tmp"  # a mount point in this namespace only; the host's /tmp is not touched
        mount("tmpfs", new, "tmpfs", MS_NOSUID | MS_NODEV, "size=1m,nr_inodes=4096,mode=755")
        i = 0
        while i < len(items):
            if items[i] == "b":
                path = items[i + 1]
                os.makedirs(new + path, exist_ok=True)
                mount(path, new + path, None, MS_BIND | MS_REC)
                i += 2
            else:
                path, target = items[i + 1], items[i + 2]
                os.makedirs(new + os.path.dirname(path), exist_ok=True)
                os.symlink(target, new + path)
                i += 3
        os.mkdir(new + "/proc")
        mount("/proc", new + "/proc", None, MS_BIND | MS_REC)  # this pid namespace's proc
        os.mkdir(new + "/dev")
        for name in ("null", "zero", "full", "random", "urandom", "tty"):
            if os.path.exists("/dev/" + name):
                os.close(os.open(new + "/dev/" + name, os.O_CREAT | os.O_WRONLY, 0o644))
                mount("/dev/" + name, new + "/dev/" + name, None, MS_BIND)
        for name, target in (("fd", "/proc/self/fd"), ("stdin", "/proc/self/fd/0"), ("stdout", "/proc/self/fd/1"),
                             ("stderr", "/proc/self/fd/2")):
            os.symlink(target, new + "/dev/" + name)
        os.mkdir(new + "/dev/shm")
        os.mkdir(new + "/tmp")
        readonly(new)
        tmp, shm = new + "/tmp", new + "/dev/shm"
    else:
        new = None
        readonly("/")
        tmp, shm = "/tmp", "/dev/shm"
    mount("tmpfs", tmp, "tmpfs", MS_NOSUID | MS_NODEV, "size=%d,nr_inodes=16384,mode=1777" % tmp_bytes)
    if os.path.isdir(shm):
        mount("tmpfs", shm, "tmpfs", MS_NOSUID | MS_NODEV, "size=%d,nr_inodes=1024,mode=1777" % shm_bytes)
    os.mkdir(tmp + "/work", 0o700)
    os.chown(tmp + "/work", uid, uid)
    if new is not None:
        os.chdir(new)
        number = PIVOT_ROOT.get(os.uname().machine)
        # pivot_root(".", "."), then detach the old root stacked on top (pivot_root(2), NOTES).
        if number is not None and libc.syscall(number, b".", b".") == 0:
            if libc.umount2(b".", 2) != 0:  # MNT_DETACH
                e = ctypes.get_errno()
                raise OSError(e, "umount2(old root): %s" % os.strerror(e))
        else:
            os.chroot(".")  # no pivot_root here: chroot (the uid cannot undo it: no CAP_SYS_CHROOT)
    os.chdir("/tmp/work")
    os.setgroups([])
    os.setresgid(uid, uid, uid)
    os.setresuid(uid, uid, uid)
    with open("/proc/self/status", "rb") as f:
        caps = [line.split()[1] for line in f if line.startswith((b"CapPrm:", b"CapEff:"))]
    if os.getuid() != uid or os.getgid() != uid or any(int(c, 16) for c in caps):
        raise OSError("the harness did not drop root (uid %d, caps %r)" % (os.getuid(), caps))


def probe_view():
    """The answer to the parent's probe (sandbox.py, _probe_unshare)."""
    def writable(path):
        try:
            os.close(os.open(path, os.O_CREAT | os.O_WRONLY | os.O_EXCL, 0o600))
            os.unlink(path)
            return True
        except OSError:
            return False
    return {"status": "probe", "uid": os.getuid(), "root_writable": writable("/.posttrain-probe"),
            "work_writable": writable("/tmp/work/.posttrain-probe")}


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
    if len(sys.argv) > 9 and sys.argv[9] == "view":
        enter_view(sys.argv[10:])
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
    if task.get("probe"):
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        out = probe_view()
        out["nonce"] = nonce
        return out

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
