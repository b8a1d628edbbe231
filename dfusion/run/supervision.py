"""How ``dfusion run`` keeps its node processes alive, and never leaves one behind.

Three mechanisms, all local to the machine that runs the launcher:

* **The launcher's liveliness lock.** The launcher holds an exclusive ``flock`` on
  ``RUN_DIR/launcher.lock`` for as long as it runs. The kernel drops the lock when
  the launcher's process ends, however it ends (SIGKILL included), and a lock is
  not fooled by a reused process id. A node started with ``--run-dir`` refuses to
  start when nobody holds the lock, and stops within :data:`WATCH_PERIOD` seconds
  once it is free (:class:`LauncherWatch`).
* **The parent-death signal.** A node whose parent is the launcher asks the kernel
  (Linux ``prctl(PR_SET_PDEATHSIG, SIGTERM)``, :func:`set_parent_death_signal`) to
  receive SIGTERM when its parent dies: it stops at once, even before its next look
  at the lock. A node started by hand has another parent; the lock alone watches it.
* **One incarnation per node.** A node holds an exclusive ``flock`` on
  ``RUN_DIR/locks/NAME.lock`` (its pid written inside) while it runs, so a second
  copy of a node (a restart by hand while the launcher's is running, or the
  launcher's restart while one started by hand runs) exits at once with
  :data:`EXIT_ALREADY_RUNNING`, and the launcher sees that a node started by hand
  is running (:func:`lock_holder`) and follows it instead of starting another.

:class:`RestartPolicy` says when the launcher restarts a node that exited before its
final estimate: after a backoff that doubles with every quick failure in a row, at
most ``max_restarts`` times per node.
"""
from __future__ import annotations

import ctypes
import fcntl
import logging
import os
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from dfusion.errors import DfusionError

log = logging.getLogger(__name__)

#: The launcher's liveliness lock, in the run directory.
LAUNCHER_LOCK = "launcher.lock"
#: Directory of the per-node locks, in the run directory.
LOCK_DIR = "locks"
#: Exit status of a node that found another incarnation of itself running.
EXIT_ALREADY_RUNNING = 3
#: Exit status of a node started with ``--run-dir`` while no launcher runs there.
EXIT_NO_LAUNCHER = 4
#: Seconds between two looks of a node at the launcher's lock.
WATCH_PERIOD = 0.1
#: ``prctl`` option number of ``PR_SET_PDEATHSIG`` (``linux/prctl.h``).
PR_SET_PDEATHSIG = 1


def node_lock_path(run_dir: str | Path, name: str) -> Path:
    return Path(run_dir) / LOCK_DIR / f"{name}.lock"


class FileLock:
    """An exclusive ``flock`` on ``path``, with the holder's pid written in the file.

    Held until :meth:`release` or the end of the process (the kernel releases it
    then, whatever the cause). Not inherited by child processes started with
    ``close_fds`` (``subprocess``' default).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._fd: int | None = None

    def acquire(self, timeout: float = 0.0) -> bool:
        """Take the lock, retrying for ``timeout`` seconds; False if someone else holds it."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        deadline = time.monotonic() + timeout
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    os.close(fd)
                    return False
                time.sleep(0.02)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd
        return True

    @property
    def held(self) -> bool:
        return self._fd is not None

    def release(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            try:
                fcntl.flock(fd, fcntl.LOCK_UN)
            finally:
                os.close(fd)

    def __enter__(self) -> FileLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def lock_holder(path: str | Path) -> int | None:
    """The pid of the process that holds the lock ``path`` (``-1`` if unreadable), ``None`` if free.

    Tests by trying the lock for an instant: a process trying to take it at that
    very moment must retry (:meth:`FileLock.acquire` with a timeout does).
    """
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                return int(os.pread(fd, 32, 0).decode().strip() or -1)
            except ValueError:
                return -1
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


class LauncherWatch:
    """Whether the launcher of a run directory is still running (its lock is held).

    :meth:`alive` looks at most every ``period`` seconds (a non-blocking shared
    ``flock`` attempt: a few microseconds) and remembers the answer in between.
    """

    def __init__(self, run_dir: str | Path, period: float = WATCH_PERIOD) -> None:
        self.path = Path(run_dir) / LAUNCHER_LOCK
        self.period = period
        self._next = 0.0
        self._alive = True
        try:
            self._fd: int | None = os.open(self.path, os.O_RDONLY)
        except FileNotFoundError:
            self._fd = None
            self._alive = False

    def alive(self) -> bool:
        if not self._alive or self._fd is None:
            return False
        now = time.monotonic()
        if now < self._next:
            return True
        self._next = now + self.period
        try:
            fcntl.flock(self._fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return True   # the launcher holds it exclusively
        fcntl.flock(self._fd, fcntl.LOCK_UN)
        self._alive = False
        return False

    def launcher_pid(self) -> int | None:
        """The pid the launcher wrote into its lock (``None`` if unknown)."""
        try:
            return int(self.path.read_text().strip())
        except (OSError, ValueError):
            return None

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def pid_running(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie, dead but not yet reaped, does not)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        return state not in ("Z", "X")
    except (OSError, IndexError):   # no /proc (not Linux), or gone
        try:
            os.kill(pid, 0)
            return True
        except (ProcessLookupError, PermissionError):
            return False


def set_parent_death_signal(sig: int = signal.SIGTERM) -> bool:
    """Ask the kernel to send ``sig`` to this process when its parent dies (Linux only).

    ``prctl(PR_SET_PDEATHSIG, sig)`` through ``ctypes``. The signal comes when the
    *thread* that started this process ends, so a parent must start its children
    from a thread that lives as long as they should. Returns False where it is not
    available (other systems): the lock watch still stops the node there.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
            log.warning("prctl(PR_SET_PDEATHSIG) failed: %s", os.strerror(ctypes.get_errno()))
            return False
    except (OSError, AttributeError) as exc:
        log.warning("prctl not available: %s", exc)
        return False
    return True


#: Run by ``python -c`` before anything else (standard library only): the parent-death signal is
#: set before the seconds of imports, then the module runs as ``python -m`` would run it.
_BOOTSTRAP = (
    "import ctypes, os, runpy, signal, sys\n"
    "ctypes.CDLL(None).prctl({option}, int(signal.SIGTERM), 0, 0, 0)\n"
    "if os.getppid() != int(sys.argv[1]):\n"
    "    sys.exit({code})\n"
    "sys.argv = [{module!r}] + sys.argv[2:]\n"
    "runpy.run_module({module!r}, run_name='__main__', alter_sys=True)\n"
)


def child_command(python: str, module: str, args: list[str]) -> list[str]:
    """The command that runs ``python -m module args`` as a child that dies with this process.

    On Linux the child first sets its parent-death signal (SIGTERM; see
    :func:`set_parent_death_signal`) with the standard library only, then checks that
    its parent is still this process, and only then imports and runs ``module``: a
    launcher killed while its children are still importing (1-4 s on a busy machine)
    leaves nothing behind. Elsewhere it is ``python -m module args``.
    """
    if not sys.platform.startswith("linux"):
        return [python, "-m", module, *args]
    code = _BOOTSTRAP.format(option=PR_SET_PDEATHSIG, code=EXIT_NO_LAUNCHER, module=module)
    return [python, "-c", code, str(os.getpid()), *args]


@dataclass(frozen=True)
class RestartPolicy:
    """When the launcher restarts a node process that exited before its final estimate.

    Attributes
    ----------
    enabled : bool
        Restart at all (``dfusion run --no-supervise`` turns it off).
    max_restarts : int
        Restarts per node in one run; after that the node stays down (reported as a
        failure; it can still be started by hand).
    backoff : float
        Wall seconds between the exit and the restart after a first failure.
    backoff_max : float
        The backoff doubles with every failure in a row, up to this.
    stable : float
        An incarnation that ran this many wall seconds resets the doubling.
    """

    enabled: bool = True
    max_restarts: int = 10
    backoff: float = 0.5
    backoff_max: float = 8.0
    stable: float = 10.0

    def __post_init__(self) -> None:
        if self.max_restarts < 0:
            raise DfusionError(f"the restart limit must be >= 0, got {self.max_restarts}")
        if not (0 <= self.backoff <= self.backoff_max):
            raise DfusionError(f"need 0 <= backoff <= backoff_max, got {self.backoff} and {self.backoff_max}")

    def delay(self, failures_in_a_row: int) -> float:
        """``min(backoff_max, backoff * 2^(n - 1))`` for the ``n``-th quick failure in a row."""
        n = max(1, failures_in_a_row)
        return min(self.backoff_max, self.backoff * 2.0 ** (n - 1))


def exit_reason(returncode: int, finished: bool) -> str:
    """A process's exit in words (``killed by SIGKILL``, ``exit status 2``, ...)."""
    if returncode < 0:
        try:
            return f"killed by {signal.Signals(-returncode).name}"
        except ValueError:
            return f"killed by signal {-returncode}"
    if returncode == 0:
        return "finished" if finished else "exited (status 0) before its final estimate"
    if returncode == EXIT_ALREADY_RUNNING:
        return "another incarnation was running"
    return f"exit status {returncode}"
