"""A fork server for stage processes (tests/test_fault_injection.py): ``python tests/forked_stages.py``.

Importing torch, warp, MLflow and the stages takes a stage process ~5 s on the 2-core CI machine, longer than most
stages' own work at the test's sizes. This server imports them once and then forks one child per request; the
child runs ``stages/<name>.py`` as ``python stages/<name>.py <argv>`` would run it after its imports (``runpy``
with ``__name__ == "__main__"``: its ``sys.exit(cli.run(main))``, SIGTERM handler included), its stdout and stderr
to a log file. The server itself runs no torch operation (no thread pool exists to be inherited across the fork).

Protocol, one JSON object a line: the client writes ``{"script", "argv", "cwd", "log", "env"}``; the server
answers ``{"pid"}`` once the child runs (the client signals that pid directly) and ``{"pid", "returncode"}``
when it has ended (``returncode`` as :mod:`subprocess` reports it: negative for a signal). One child at a
time; end of input ends the server.
"""

from __future__ import annotations

import importlib.util
import json
import os
import runpy
import sys
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STAGES = ROOT / "stages"


def _preload() -> None:
    """Import what the stages import, and the modules they import lazily at run time."""
    sys.path.insert(0, str(STAGES))
    for script in sorted(STAGES.glob("*.py")):
        spec = importlib.util.spec_from_file_location(f"_preloaded_{script.stem}", script)
        spec.loader.exec_module(importlib.util.module_from_spec(spec))
    import matplotlib.pyplot  # noqa: F401
    import mlflow.store.tracking.sqlalchemy_store  # noqa: F401

    from gca.pipeline import schema
    for spec in schema.KNOB_SECTIONS.values():  # the sections' classes, imported on first use
        schema.dataclass_of(spec)


def _child(request: dict) -> None:
    """Run the stage script in this (forked) process, then exit with its status; never returns."""
    code = 1
    try:
        os.chdir(request["cwd"])
        os.environ.update(request.get("env", {}))
        log = os.open(request["log"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(log, 1)
        os.dup2(log, 2)
        os.close(log)
        sys.argv = [request["script"], *request["argv"]]
        sys.path[0] = str(Path(request["script"]).resolve().parent)
        try:
            runpy.run_path(request["script"], run_name="__main__")
            code = 0
        except SystemExit as exc:  # as the interpreter: None -> 0, an int, else the message to stderr and 1
            if exc.code is None or isinstance(exc.code, int):
                code = exc.code or 0
            else:
                print(exc.code, file=sys.stderr)
        except BaseException:  # noqa: BLE001 - an internal error: its traceback, status 1 (as the interpreter)
            traceback.print_exc()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:  # noqa: BLE001
                pass
        os._exit(code)


def main() -> None:
    answer = os.fdopen(os.dup(1), "w", buffering=1)  # the protocol; prints of the imports go to stderr
    os.dup2(2, 1)
    _preload()
    answer.write(json.dumps({"ready": os.getpid()}) + "\n")
    for line in sys.stdin:
        request = json.loads(line)
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            _child(request)
        answer.write(json.dumps({"pid": pid}) + "\n")
        _, status = os.waitpid(pid, 0)
        answer.write(json.dumps({"pid": pid, "returncode": os.waitstatus_to_exitcode(status)}) + "\n")
    answer.close()
    os._exit(0)  # nothing to finalise: skip the interpreter's teardown of torch and the rest (seconds)


if __name__ == "__main__":
    main()
