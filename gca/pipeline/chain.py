"""Several stage commands run one after the other in one process: a grid's chain of a scene's inputs.

    python -m gca.pipeline.chain [--stamp S] NAME 'python stages/a.py ...' NAME 'python stages/b.py ...' ...

Each ``(NAME, CMD)`` pair is one job of ``gca.pipeline.grid`` (``assets@ball``, ...), run in the order given. A
``python stages/<stage>.py <argv>`` command runs here, in this interpreter, as its script's ``__main__`` would run it
(``cli.run(main, argv)``: its stop handling, its sweep of stale temporaries, its one-line user errors); any other
command runs as a subprocess. So the chain pays one process start and one import of torch, warp and the library
instead of one per stage: on the H200 a data stage spent ~10 s starting for 1.4-11.4 s of work (NOTES session 47),
and the scene's four input stages (assets -> particles -> ground_truth -> preprocess) sit one after the other on the
path to its trainings.

Each member that ends well writes its own ``.grid/<NAME>.done`` marker with ``--stamp`` (``dispatch.write_done``), so
a chain stopped or failed midway starts next time at its first member not done; a member already done (its marker
with the stamp) is passed over. The first member that fails or is stopped ends the chain with its exit status
(2: a user error, 143: stopped, 1: an internal error), the members after it not run.

What a stage leaves in the process is shared with the next: the imported modules, warp's loaded kernels, torch's
cached GPU memory. The stages seed their own generators (``torch.Generator().manual_seed``) and set no global
state a later stage reads, so each member's outputs are the ones its own process would write
(``tests/test_pipeline_chain.py`` compares them byte for byte at the CI profile).
"""

from __future__ import annotations

import argparse
import importlib.util
import shlex
import subprocess
import sys
import time
from pathlib import Path

from gca.pipeline.dispatch import PYTHON, is_done, python_argv, write_done


def stage_script(cmd: str) -> tuple[Path, list[str]] | None:
    """``(script, argv)`` of a ``python stages/<stage>.py <argv>`` command (any ``*.py`` script run by python); None
    for any other command (it runs as a subprocess)."""
    argv = shlex.split(cmd)
    if len(argv) >= 2 and argv[0] in PYTHON and argv[1].endswith(".py") and not argv[1].startswith("-"):
        return Path(argv[1]), argv[2:]
    return None


def run_here(script: Path, argv: list[str]) -> int:
    """Run stage ``script``'s ``main(argv)`` in this process through ``cli.run`` (as its ``__main__`` does); its exit
    status. The script's folder goes first on ``sys.path`` (``stages/common.py``, as for ``python stages/x.py``)."""
    from gca.pipeline import cli

    folder = str(script.resolve().parent)
    if folder not in sys.path:
        sys.path.insert(0, folder)
    spec = importlib.util.spec_from_file_location(f"_gca_stage_{script.stem}", script)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # as an import would (a dataclass or pickle in the script looks its module up)
    spec.loader.exec_module(module)  # its `if __name__ == "__main__"` does not run: the module is not __main__
    saved = sys.argv
    sys.argv = [str(script), *argv]  # what a stage reads of its own command line (its name, argparse's prog)
    try:
        return cli.run(module.main, argv, name=script.stem)
    finally:
        sys.argv = saved


def run_one(cmd: str) -> int:
    """One member's exit status: a stage script here (:func:`run_here`), anything else as a subprocess."""
    found = stage_script(cmd)
    if found is None:
        return subprocess.run(python_argv(cmd)).returncode
    return run_here(*found)


def pairs(items: list[str]) -> list[tuple[str, str]]:
    """``[NAME, CMD, NAME, CMD, ...]`` -> ``[(NAME, CMD), ...]``; a ValueError for an odd count or no pair."""
    if not items or len(items) % 2:
        raise ValueError(f"expected NAME CMD pairs, got {len(items)} argument(s)")
    return list(zip(items[::2], items[1::2]))


def command(members: list[tuple[str, str]], stamp: str = "") -> str:
    """The shell command that runs ``members`` (``(name, cmd)``) as one chain: what a grid job's ``cmd`` holds."""
    head = ["python", "-m", "gca.pipeline.chain"] + (["--stamp", stamp] if stamp else [])
    return " ".join(shlex.quote(a) for a in head + [x for pair in members for x in pair])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stamp", default="", help="what each member's .done marker holds (the grid's inputs stamp)")
    ap.add_argument("members", nargs="+", metavar="NAME CMD", help="pairs: a job name and its stage command")
    args = ap.parse_args(argv)
    try:
        members = pairs(args.members)
    except ValueError as exc:
        ap.error(str(exc))
    work = Path.cwd()
    for name, cmd in members:
        if is_done(work, name, args.stamp):
            print(f"[chain] {name}: done already", flush=True)
            continue
        print(f"[chain] {name}: {cmd}", flush=True)
        t0 = time.monotonic()
        rc = run_one(cmd)
        sys.stdout.flush()
        sys.stderr.flush()
        if rc != 0:
            print(f"[chain] {name}: exit {rc}; the members after it not run", file=sys.stderr, flush=True)
            return rc
        took = time.monotonic() - t0
        write_done(work, name, took, args.stamp)
        print(f"[chain] {name}: done in {took:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
