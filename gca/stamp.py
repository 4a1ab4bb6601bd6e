"""Stamps on reused intermediate files: a hash of the params and inputs a file was made from.

A training checkpoint (``<run>/checkpoint.pt``) and a launch-velocity estimate (``velocity.json``) are
reused by a later process of the same stage (an interrupted run resumes; ``benchmarks/grid.py`` shares
one velocity between processes). Reused after the params or the inputs changed, they would silently
carry the old setup into the new run. :func:`fingerprint` hashes the params sections a file depends on
and the content of its input files; a file whose stamp differs is not reused, and the stage says so in
one line.

- the checkpoint's stamp is a sidecar, ``checkpoint.pt.stamp`` (:func:`guard_checkpoint`, removed with
  the checkpoint by :func:`clear_checkpoint`);
- ``velocity.json`` carries its stamp under the key ``"stamp"`` (:func:`stamped`, :func:`matches`).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

from gca.config import section
from gca.io import write_text

KEY = "stamp"
_CHUNK = 1 << 20


def _files(path: Path, skip: Callable[[Path], bool] | None = None) -> list[Path]:
    if path.is_dir():  # hidden names are temporaries or litter, never inputs
        return sorted(p for p in path.rglob("*") if p.is_file()
                      and not any(part.startswith(".") for part in p.relative_to(path).parts)
                      and not (skip and skip(p.relative_to(path))))
    return [path] if path.is_file() else []


def fingerprint(params: Mapping, keys: Iterable[str], inputs: Iterable[str | os.PathLike] = (),
                extra: Any = None, skip: Callable[[Path], bool] | None = None) -> str:
    """A 16-hex-digit hash of params sections ``keys`` (dotted), the content of ``inputs`` (files or
    folders; a missing one hashes as missing) and the JSON-able ``extra``. ``skip``: files of a folder (their
    path relative to it) that are not part of the input (e.g. other seeds' observations nested in seed 0's)."""
    digest = hashlib.sha256()
    digest.update(json.dumps({k: section(params, k) for k in keys}, sort_keys=True, default=str).encode())
    digest.update(json.dumps(extra, sort_keys=True, default=str).encode())
    for root in map(Path, inputs):
        files = _files(root, skip)
        digest.update(f"\0{root.name}:{len(files)}".encode())
        for path in files:
            digest.update(f"\0{path.relative_to(root) if path != root else path.name}\0".encode())
            with open(path, "rb") as handle:
                for block in iter(lambda: handle.read(_CHUNK), b""):
                    digest.update(block)
    return digest.hexdigest()[:16]


def _sidecar(checkpoint: Path) -> Path:
    return checkpoint.with_name(checkpoint.name + ".stamp")


def guard_checkpoint(checkpoint: str | os.PathLike, stamp: str, say: Callable[[str], None] = print) -> bool:
    """Before training: keep ``checkpoint`` only if it was made under ``stamp``; returns whether one is
    kept (the run resumes from it). A stale or unstamped checkpoint is deleted, with one line said."""
    checkpoint = Path(checkpoint)
    sidecar = _sidecar(checkpoint)
    kept = checkpoint.is_file()
    if kept:
        old = sidecar.read_text().strip() if sidecar.is_file() else None
        if old != stamp:
            why = "has no stamp" if old is None else "was made with other params or inputs"
            say(f"{checkpoint}: not resumed: the checkpoint {why} (stamp {old} != {stamp}); training afresh")
            checkpoint.unlink()
            kept = False
    write_text(sidecar, stamp + "\n")
    return kept


def clear_checkpoint(checkpoint: str | os.PathLike) -> None:
    """After training: the checkpoint and its stamp go."""
    checkpoint = Path(checkpoint)
    checkpoint.unlink(missing_ok=True)
    _sidecar(checkpoint).unlink(missing_ok=True)


def matches(record: Mapping, stamp: str) -> bool:
    """Whether a stamped JSON record (``velocity.json``) was made under ``stamp``."""
    return isinstance(record, Mapping) and record.get(KEY) == stamp
