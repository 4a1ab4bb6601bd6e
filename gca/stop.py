"""Stopping a stage cleanly: SIGTERM, a stop file, a deadline or its parent's end.

SIGTERM becomes :class:`Terminated`, an exception every ``finally`` and atomic write (``gca.io.atomic_path``) unwinds
through, so no temporary is left behind. Inside :func:`deferred` (training) the signal only sets a flag: the training
loop saves its checkpoint at the end of the iteration in progress (:func:`requested`) and then stops (:func:`check`),
so a stopped run resumes where it was. ``benchmarks/grid.py`` sends SIGKILL 20 s after SIGTERM; the periodic
checkpoints bound what a SIGKILL loses.

**A stop without a signal** (session 42): under CUDA MPS, a SIGTERM or kill that reached a process with GPU work in
flight ended every process on the GPU three times (an MMU fault, Xid 31, then CUDA error 700 in all MPS clients;
NOTES sessions 41-42), while the same stops without MPS were clean; eight SIGTERMs earlier in training did not
(session 43: the trigger is not settled). So a packed process is asked to stop without a signal:

- ``GCA_STOP_FILE`` (a path): the stop is requested once that file exists (the grid's deadline stop writes
  ``.grid/<job>.stop`` and sends SIGTERM only to a job that has not ended ``STOP_REQUEST_S`` later);
- ``GCA_STOP_AT`` (Unix time [s]): the stop is requested once the clock passes it (the device bundles set it some
  seconds before their ``timeout``, which stays the backstop);
- ``GCA_STOP_PARENT`` (a process id): the stop is requested once this process's parent is no longer that process
  (session 44). The grid's job process sets it for its stage, which runs in a session of its own, so a user's Ctrl-C
  reaches the job (which asks the stage to stop by its file) but not the stage. When the job process dies, the stage
  stops by this check, not by the parent-death SIGTERM it had before: :func:`install` clears that signal
  (``PR_SET_PDEATHSIG``, ``gca.pipeline.dispatch``), which stays only for a command that never installs the watcher.

All three are read where the flag is (:func:`requested`, latched: once seen, the stop stands), i.e. at a training
iteration's end and between stages' runs, and by a watcher thread (:func:`install`) that raises the stop in the main
thread as the signal's handler would, but without a signal, so a stage that never reads the flag stops too; they end
the stage like a SIGTERM (exit 143). :func:`quiesce` waits for the GPU's queued work before a stopped process exits.
"""

from __future__ import annotations

import _thread
import contextlib
import os
import signal
import sys
import threading
import time
from typing import Iterator

_state = {"requested": False, "deferring": 0, "reason": "stopped by SIGTERM", "watcher": None, "parent": None}


STOP_FILE_ENV, STOP_AT_ENV, STOP_PARENT_ENV = "GCA_STOP_FILE", "GCA_STOP_AT", "GCA_STOP_PARENT"


class Terminated(SystemExit):
    """The process received SIGTERM, found its stop file or deadline, or lost its parent (exit status 143, as the
    signal's default)."""

    def __init__(self, message: str = "stopped by SIGTERM"):
        super().__init__(143)
        self.message = message

    def __str__(self) -> str:
        return self.message


WATCH_S = 0.5  # the watcher's poll of the stop file, the deadline and the parent [s]
ORPHAN_GRACE_S = 60.0  # a stop asked because the parent ended: SIGTERM to itself if still running this long after [s]
_LOCK = threading.Lock()  # the watcher's act against unwatch()


def _handler(signum, frame) -> None:
    """SIGTERM's handler, also run by the watcher's :func:`_thread.interrupt_main` (then with its reason set)."""
    if not _state["requested"]:
        _state["requested"], _state["reason"] = True, "stopped by SIGTERM"
    if not _state["deferring"]:
        raise Terminated(_state["reason"])


def install() -> None:
    """Turn SIGTERM into :class:`Terminated` in this process (main thread only; a no-op elsewhere), and with
    ``GCA_STOP_FILE``, ``GCA_STOP_AT`` or ``GCA_STOP_PARENT`` set, start the watcher (:func:`_watch`). The parent is
    this process's alone: it is taken out of the environment (a child's parent is this process)."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _handler)
        path, deadline, parent = _settings()
        parent = _state["parent"] if parent is None else parent  # installed again (the variable was taken already)
        if parent is not None:  # this process's own: taken out of the environment its children inherit
            os.environ.pop(STOP_PARENT_ENV, None)
            _state["parent"] = parent
            parent_death_signal(0)  # the watcher checks the parent instead, with no signal
        _watch(path, deadline, parent)


def parent_death_signal(signum: int) -> None:
    """Linux: the signal this process gets when its parent dies (``prctl(PR_SET_PDEATHSIG)``; 0: none). A no-op
    elsewhere. The grid's stage process sets SIGTERM (``gca.pipeline.dispatch``), :func:`install` clears it."""
    if sys.platform.startswith("linux"):
        import ctypes

        try:
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signum), 0, 0, 0)  # PR_SET_PDEATHSIG = 1
        except (OSError, AttributeError):
            pass


def _settings() -> tuple[str | None, float | None, int | None]:
    """The environment's stop file (``GCA_STOP_FILE``), deadline (``GCA_STOP_AT`` as a Unix time [s]) and parent
    (``GCA_STOP_PARENT``, a process id); None where unset or empty; a deadline or parent that is no number is
    refused."""
    at, parent = os.environ.get(STOP_AT_ENV), os.environ.get(STOP_PARENT_ENV)
    try:
        deadline = float(at) if at else None
    except ValueError:
        raise ValueError(f"gca/stop.py: {STOP_AT_ENV}={at!r} is not a Unix time in seconds") from None
    try:
        parent_pid = int(parent) if parent else None
    except ValueError:
        raise ValueError(f"gca/stop.py: {STOP_PARENT_ENV}={parent!r} is not a process id") from None
    return os.environ.get(STOP_FILE_ENV) or None, deadline, parent_pid


def deadline() -> float | None:
    """The stop deadline ``GCA_STOP_AT`` [Unix s], or None where unset (a process that plans its work around it:
    :func:`gca.pipeline.tune.no_start`)."""
    return _settings()[1]


def _asked(path: str | None, deadline: float | None, parent: int | None = None) -> str:
    """Why a stop is asked without a signal: the stop file ``path`` exists, the ``deadline`` passed or this process's
    parent is no longer ``parent`` ("" if none of them)."""
    if path and os.path.exists(path):
        return f"stopped by the stop file {path}"
    if deadline is not None and time.time() >= deadline:
        return f"stopped at the deadline {STOP_AT_ENV}={deadline:.0f}"
    if parent is not None and os.getppid() != parent:
        return f"stopped: its parent process {parent} ended ({STOP_PARENT_ENV})"
    return ""


def _watch(path: str | None, deadline: float | None, parent: int | None = None) -> None:
    """A daemon thread that polls the stop file ``path``, the ``deadline`` and the ``parent`` every ``WATCH_S`` and,
    once asked, raises the stop in the main thread as SIGTERM's handler would, **without a signal**
    (``_thread.interrupt_main``: at the main thread's next bytecode, no system call interrupted): a stage that never
    reads :func:`requested` (a data stage, an evaluation) stops too, a training at its iteration's end (:func:`deferred`). One watcher per process;
    :func:`unwatch` ends it. Limits: the main thread sees the stop only between bytecodes (a blocking call, e.g. a
    ``time.sleep`` or a child process waited for, finishes first), and not at all if SIGTERM's handler is no longer
    Python's; the grid's SIGTERM, ``dispatch.STOP_REQUEST_S`` later, is the backstop. When the stop came from the
    parent's end there is no grid left to send it, so the watcher sends its own process SIGTERM if the process still
    runs ``ORPHAN_GRACE_S`` later (a real signal interrupts a blocking call)."""
    if (path is None and deadline is None and parent is None) or _state.get("watcher") is not None:
        return
    done = threading.Event()

    def watch() -> None:
        while not done.wait(WATCH_S):
            reason = _asked(path, deadline, parent)
            with _LOCK:  # unwatch() holds it: a watcher it ended never acts after
                if done.is_set():
                    return
                if reason and not _state["requested"]:
                    _state["requested"], _state["reason"] = True, reason
                    _thread.interrupt_main(signal.SIGTERM)  # runs _handler in the main thread (no signal is sent)
                    if parent is not None and os.getppid() != parent:
                        break  # no grid is left to send the backstop SIGTERM: this thread keeps one (below)
                if _state["requested"]:
                    return
        if not done.wait(ORPHAN_GRACE_S):  # still running: a main thread blocked in a call the stop cannot reach
            os.kill(os.getpid(), signal.SIGTERM)

    _state["watcher"] = done
    threading.Thread(target=watch, name="gca-stop-watch", daemon=True).start()


def unwatch() -> None:
    """End the watcher (a stage whose work is done: a stop asked while it exits must not cut its exit hooks)."""
    with _LOCK:
        if _state.get("watcher") is not None:
            _state["watcher"].set()
        _state["watcher"] = None


def requested() -> bool:
    """Whether a stop was asked: SIGTERM arrived, the stop file exists, the deadline passed or the parent ended
    (latched; inside :func:`deferred`: save what must be saved, then :func:`check`)."""
    if not _state["requested"]:
        reason = _asked(*_settings()[:2], _state["parent"])
        if reason:
            _state["requested"], _state["reason"] = True, reason
    return _state["requested"]


def check() -> None:
    """Raise :class:`Terminated` if a stop was asked (:func:`requested`)."""
    if requested():
        raise Terminated(_state["reason"])


def quiesce() -> None:
    """Wait for the GPU work this process queued (when torch has initialised CUDA), before a stopped process exits:
    no kernel of it is still running while it tears down. An error here (a GPU already faulted) is left to the
    stop's own message."""
    torch = sys.modules.get("torch")
    if torch is None or not torch.cuda.is_initialized():
        return
    try:
        torch.cuda.synchronize()
    except RuntimeError:
        pass


@contextlib.contextmanager
def deferred(stop_at_end: bool = True) -> Iterator[None]:
    """SIGTERM inside this block waits for the next :func:`check` (or the block's end). ``stop_at_end=False``: a
    block that ends normally has finished its work, and a SIGTERM that came after its last :func:`check` waits for
    the caller's next one (a training run that wrote its results as the signal came is kept: session 25 lost a
    finished 441-s run that way, its checkpoint already removed and its stage ended 143, so no ``.done`` marker)."""
    _state["deferring"] += 1
    try:
        yield
    finally:
        _state["deferring"] -= 1
    if stop_at_end:
        check()


def reset() -> None:
    """End the watcher and forget an earlier stop (tests)."""
    unwatch()
    _state["requested"], _state["reason"], _state["parent"] = False, "stopped by SIGTERM", None
