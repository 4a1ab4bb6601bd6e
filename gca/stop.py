"""SIGTERM as a clean stop: the signal becomes :class:`Terminated`, an exception every ``finally`` and
atomic write (``gca.io.atomic_path``) unwinds through, so no temporary is left behind.

Inside :func:`deferred` (training) the signal only sets a flag: the training loop saves its checkpoint at
the end of the iteration in progress (:func:`requested`) and then stops (:func:`check`), so a stopped run
resumes where it was. ``benchmarks/grid.py`` sends SIGKILL 20 s after SIGTERM; the periodic checkpoints
bound what a SIGKILL loses.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from typing import Iterator

_state = {"requested": False, "deferring": 0}


class Terminated(SystemExit):
    """The process received SIGTERM (exit status 143, as the signal's default)."""

    def __init__(self, message: str = "stopped by SIGTERM"):
        super().__init__(143)
        self.message = message

    def __str__(self) -> str:
        return self.message


def _handler(signum, frame) -> None:
    _state["requested"] = True
    if not _state["deferring"]:
        raise Terminated()


def install() -> None:
    """Turn SIGTERM into :class:`Terminated` in this process (main thread only; a no-op elsewhere)."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _handler)


def requested() -> bool:
    """Whether SIGTERM arrived (inside :func:`deferred`: save what must be saved, then :func:`check`)."""
    return _state["requested"]


def check() -> None:
    """Raise :class:`Terminated` if SIGTERM arrived."""
    if _state["requested"]:
        raise Terminated()


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
    """Forget an earlier SIGTERM (tests)."""
    _state["requested"] = False
