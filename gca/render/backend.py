"""Which rasterizer runs, and why: said once per process, never a silent fallback.

``render.backend: auto`` picks gsplat on a CUDA device when the package is installed, else the
pure-torch rasterizer (10-50x slower on CUDA, `benchmarks/render.md`). :func:`choose` returns the
backend with its reason and prints one line to stderr the first time a (backend, reason) is chosen,
e.g. ``gca.render: rasterizer torch (gsplat not installed: ...)``.

``python -m gca.render.backend --build`` compiles gsplat's CUDA extension once (gsplat JIT-compiles
on first import, ~100 s on an H100), printing what it does; ``scripts/setup.sh`` runs it on a CUDA
machine before the pipeline starts. gsplat's first build deletes and refills its build directory, so
two processes building at once corrupt it: :func:`load_gsplat` (used by the rasterizer and by
``--build``) imports the extension under an exclusive file lock (:func:`build_lock`), so processes
started together on a fresh machine wait for one build instead.
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import importlib.metadata
import importlib.util
import os
import sys
import time
import warnings

_WHERE = "gca/render/backend.py"
CHOICES = ("auto", "torch", "gsplat")
INSTALL_HINT = "pip install 'gca[gpu]', which `make setup` does on a CUDA machine"
_said: set[tuple[str, str]] = set()


def lock_path() -> str:
    """The lock file serialising gsplat's first build: ``$GCA_GSPLAT_LOCK``, else ``gca-gsplat-build.lock`` in
    ``$XDG_CACHE_HOME`` (default ``~/.cache``), one per user like gsplat's build directory."""
    if os.environ.get("GCA_GSPLAT_LOCK"):
        return os.environ["GCA_GSPLAT_LOCK"]
    cache = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(cache, "gca-gsplat-build.lock")


@contextlib.contextmanager
def build_lock(path: str | None = None):
    """Hold the exclusive ``flock`` on ``path`` (default :func:`lock_path`) for the block; blocks while another
    process holds it. Released when the block ends or the process dies."""
    path = path or lock_path()
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    with open(path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def load_gsplat():
    """Import gsplat's CUDA extension (JIT-compiling it the first time) under :func:`build_lock`, once per process;
    returns ``gsplat.cuda._backend._C`` (None when it did not load). Raises ImportError when gsplat is absent."""
    if "gsplat.cuda._backend" not in sys.modules:  # imported once: later calls take no lock
        with build_lock():
            from gsplat.cuda._backend import _C  # the first import is the build
            return _C
    from gsplat.cuda._backend import _C
    return _C


def gsplat_version() -> str | None:
    """gsplat's installed version, or None when it cannot be imported (it is not imported here)."""
    if importlib.util.find_spec("gsplat") is None:
        return None
    try:
        return importlib.metadata.version("gsplat")
    except importlib.metadata.PackageNotFoundError:
        return "unknown version"


def choose(requested: str, on_cuda: bool, announce: bool = True) -> tuple[str, str]:
    """The rasterizer for ``render.backend = requested`` on a CUDA (``on_cuda``) or CPU device.

    Returns:
        ``(backend, reason)``, backend ``"torch"`` or ``"gsplat"``. An explicit ``gsplat`` off CUDA
        falls back to torch with a RuntimeWarning; ``auto`` never falls back without saying so.
    """
    if requested not in CHOICES:
        raise ValueError(f"params: render.backend={requested!r} is not one of {CHOICES}")
    version = gsplat_version()
    if requested == "torch":
        backend, reason = "torch", "render.backend=torch"
    elif requested == "gsplat":
        if on_cuda:
            backend, reason = "gsplat", f"render.backend=gsplat, gsplat {version or 'NOT installed: ' + INSTALL_HINT}"
        else:
            backend, reason = "torch", "render.backend=gsplat needs CUDA, no CUDA device here"
            warnings.warn(f"{_WHERE}: {reason}: using the torch rasterizer", RuntimeWarning, stacklevel=2)
    elif not on_cuda:
        backend, reason = "torch", "auto: no CUDA device"
    elif version is None:
        backend, reason = "torch", f"auto: gsplat not installed ({INSTALL_HINT}); the torch rasterizer is 10-50x slower"
    else:
        backend, reason = "gsplat", f"auto: CUDA device and gsplat {version} installed"
    if announce and (backend, reason) not in _said:
        _said.add((backend, reason))
        print(f"gca.render: rasterizer {backend} ({reason})", file=sys.stderr, flush=True)
    return backend, reason


def build_gsplat() -> int:
    """Import gsplat's CUDA extension once (JIT-compiling it if needed); 0 when it loaded."""
    if gsplat_version() is None:
        print(f"gca.render: gsplat is not installed ({INSTALL_HINT})", file=sys.stderr, flush=True)
        return 1
    print("gca.render: loading gsplat's CUDA extension (the first time it compiles: ~100 s on an H100) ...",
          flush=True)
    t0 = time.perf_counter()
    try:
        _C = load_gsplat()
    except Exception as exc:  # noqa: BLE001 - any failure of the build is reported, with its type
        print(f"gca.render: gsplat's extension failed to build: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    if _C is None:
        print("gca.render: gsplat's extension did not load (no CUDA toolkit?); the torch rasterizer will run",
              file=sys.stderr)
        return 1
    print(f"gca.render: gsplat's CUDA extension ready in {time.perf_counter() - t0:.0f} s", flush=True)
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--build", action="store_true", help="compile/load gsplat's CUDA extension once")
    args = parser.parse_args(argv)
    if args.build:
        return build_gsplat()
    import torch
    print(choose("auto", torch.cuda.is_available(), announce=False)[1])
    return 0


if __name__ == "__main__":
    sys.exit(main())
