"""What every stage's ``__main__`` shares: ``sys.exit(cli.run(main))``.

- A **user error** (bad params, an unknown scene or method, a missing or unreadable input file: the
  classes in :data:`USER_ERRORS`) prints one line, ``<stage>: error: <message>``, and exits 2; ``--debug``
  shows the traceback. Anything else is an internal error: its traceback is printed and the exit status
  is 1.
- **SIGTERM**, the stop file ``GCA_STOP_FILE``, the deadline ``GCA_STOP_AT`` or the end of the parent named by
  ``GCA_STOP_PARENT`` ends the stage cleanly (``gca.stop``: temporaries removed, training checkpointed first, the
  GPU's queued work waited for), exit status 143.
- At start, the stale temporaries a killed run left beside this stage's outputs are swept
  (``gca.io.sweep`` on the folders of its path arguments).
- Progress bars (tqdm) are quiet under CI (``CI=true``) or when stderr is not a terminal.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import os
import sys
import time
import traceback
from pathlib import Path
from typing import Callable, Iterator, Sequence

from gca import stop
from gca.config import ConfigError
from gca.io import InputError, sweep

DEBUG_HELP = "show the traceback of a user error (bad params, unknown names, unreadable inputs)"


def user_errors() -> tuple[type[BaseException], ...]:
    """The exception classes that describe a user's mistake, not a bug (imported lazily)."""
    from gca.assets.ply import PlyFormatError
    from gca.laws.checkpoint import CheckpointError
    from gca.scenes.store import SceneDataError
    from gca.sim.cfl import CFLError
    from gca.train.methods import UnknownMethodError

    return (ConfigError, InputError, PlyFormatError, SceneDataError, CheckpointError, CFLError,
            UnknownMethodError, FileNotFoundError, NotADirectoryError, IsADirectoryError)


def quiet() -> bool:
    """Whether progress bars stay off: under CI, or with stderr not a terminal (logs, pipes)."""
    return os.environ.get("CI", "").lower() in ("1", "true", "yes") or not sys.stderr.isatty()


def quiet_progress() -> None:
    """Turn every tqdm bar of this process off. ``TQDM_DISABLE`` alone does not do it: tqdm reads its environment
    variables when it is imported, and a stage script has imported it (through the library) before :func:`run`;
    so ``disable`` defaults to True on the class as well (a bar that passes ``disable`` itself still decides)."""
    import tqdm.std

    os.environ.setdefault("TQDM_DISABLE", "1")
    cls = tqdm.std.tqdm
    init = cls.__init__
    if getattr(init, "_gca_quiet", False):
        return

    @functools.wraps(init)
    def quiet_init(self, *args, **kwargs):
        kwargs.setdefault("disable", True)
        init(self, *args, **kwargs)

    quiet_init._gca_quiet = True
    cls.__init__ = quiet_init


def _message(exc: BaseException) -> str:
    text = exc.args[0] if isinstance(exc, KeyError) and exc.args else str(exc)
    return " ".join(str(text).split()) or type(exc).__name__


def _output_folders(argv: Sequence[str]) -> list[Path]:
    """Folders of the stage's path arguments (each ``--x value`` with a ``/`` in the value)."""
    folders = []
    for value in argv:
        if not value.startswith("-") and "/" in value:
            path = Path(value)
            folders += [path.parent, path] if path.is_dir() else [path.parent]
    return folders


def run(main: Callable[[list[str]], object], argv: Sequence[str] | None = None, name: str | None = None) -> int:
    """Run a stage's ``main(argv)``; returns the exit status (0 ok, 2 user error, 143 SIGTERM)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    name = name or Path(sys.argv[0]).stem
    debug = "--debug" in argv
    try:
        stop.install()
    except ValueError as exc:  # GCA_STOP_AT that is no time
        print(f"{name}: error: {exc}", file=sys.stderr)
        return 2
    if quiet():
        quiet_progress()
    try:
        for folder in _output_folders(argv):  # inside: a SIGTERM that comes while it sweeps is a clean stop too
            for path in sweep(folder):
                print(f"{name}: removed the stale temporary {path} (an earlier run was killed)", file=sys.stderr)
        main(argv)
    except stop.Terminated as exc:
        stopped = f"{name}: {exc}"
    except user_errors() as exc:
        if debug:
            traceback.print_exc()
        print(f"{name}: error: {_message(exc)}", file=sys.stderr)
        return 2
    else:
        return 0
    finally:  # done, failed or stopped: a stop file written as the stage exits cuts none of its exit hooks
        stop.unwatch()
    # Out of the except block the stopped frames are garbage: collected now, an object the signal caught half-built
    # (inside third-party code: GitPython's config parser under MLflow, session 18) complains from its __del__ here,
    # visibly, and not after the stop line at interpreter exit. The stop line stays the last (a job log's reason).
    gc.collect()
    stop.quiesce()
    print(stopped, file=sys.stderr)
    return 143


PARAMS_HELP = "params file (default: params.yaml; under `dvc repro`, DVC's view of it)"
DEVICE_HELP = "torch device (default: cuda when a GPU is visible, else cpu)"


def add_common(parser, device: str | None = None) -> None:
    """``--params``, ``--debug`` and (``device`` given: its default) ``--device``, each with its help."""
    from pathlib import Path as _Path

    parser.add_argument("--params", type=_Path, default=_Path("params.yaml"), help=PARAMS_HELP)
    if device is not None:
        parser.add_argument("--device", default=device, help=DEVICE_HELP)
    parser.add_argument("--debug", action="store_true", help=DEBUG_HELP)


@contextlib.contextmanager
def phase(stage: str, what: str) -> Iterator[None]:
    """One line when a long step starts and one with its time when it ends (stderr; kept under CI)."""
    start = time.perf_counter()
    print(f"{stage}: {what} ...", file=sys.stderr, flush=True)
    yield
    print(f"{stage}: {what}: done in {time.perf_counter() - start:.1f} s", file=sys.stderr, flush=True)
