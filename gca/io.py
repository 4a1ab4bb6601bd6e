"""Atomic output helpers: every stage writes to a temporary path and renames, so a failure never
leaves a half-written or corrupted output in place of a good one.

Temporaries are hidden siblings of their output named ``.<name>.tmp<pid>.<random>`` (a directory being
replaced is parked as ``.<name>.old<pid>`` for the instant of the swap). They are removed on an exception
(a stage's SIGTERM is one: ``gca.pipeline.cli``) and, after a SIGKILL, by :func:`sweep`, which every atomic write
and every stage start run on their folders: a temporary whose process is gone is litter. Outputs get the
permissions of an ordinary file or folder under the process's umask (``tempfile`` makes 0600 / 0700).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator, Mapping

# .<name>.tmp<pid>.<random>[<suffix>] | .<name>.old<pid> | before issue 24: .<name>.<8 chars>[<suffix>] | .<name>.old
_TEMPORARY = re.compile(r"^\.(?P<name>.+?)\.(?:tmp(?P<pid>\d+)\.[A-Za-z0-9_]+|old(?P<old>\d+)|(?P<legacy>[a-z0-9_]{8})|(?P<legacy_old>old))"
                        r"(?P<suffix>\.[A-Za-z0-9]+)?$")


def _umask() -> int:
    """The process's umask (read, not set, where Linux allows: setting it races with other threads)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def sweep(folder: str | os.PathLike, name: str | None = None) -> list[Path]:
    """Remove the stale temporaries in ``folder``: those of a process that no longer runs (killed with
    SIGKILL, or a machine reset). With ``name`` (an output about to be written), only that output's, and
    also the untagged ones older versions left (``.<name>.<8 random chars>``, ``.<name>.old``: without a
    known name that pattern could match a user's own hidden file). A parked ``.<name>.old<pid>`` whose
    output is missing is put back (the swap was cut in the middle). Returns what was removed or restored."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    done = []
    for entry in sorted(folder.iterdir()):
        match = _TEMPORARY.match(entry.name) if entry.name.startswith(".") else None
        if match is None or (name is not None and match["name"] != name):
            continue
        if name is None and (match["legacy"] or match["legacy_old"]):
            continue
        pid = match["pid"] or match["old"]
        if pid is not None and _alive(int(pid)):
            continue
        if match["suffix"] and (match["old"] or match["legacy_old"]):
            continue
        if match["old"] or match["legacy_old"]:
            target = folder / match["name"]
            if not target.exists():
                entry.rename(target)
                done.append(entry)
                continue
        _remove(entry)
        done.append(entry)
    return done


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, is_dir: bool = False) -> Iterator[Path]:
    """Yield a temporary sibling of ``path``; on success rename it onto ``path``.

    Works for files and (``is_dir=True``) whole directories. On an exception (SIGTERM included, under
    ``gca.pipeline.cli``) the temporary is removed and ``path`` is untouched. The result's mode follows the umask.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sweep(path.parent, path.name)
    prefix = f".{path.name}.tmp{os.getpid()}."
    mask = _umask()
    if is_dir:
        tmp = Path(tempfile.mkdtemp(prefix=prefix, dir=path.parent))
        os.chmod(tmp, 0o777 & ~mask)
    else:
        fd, name = tempfile.mkstemp(prefix=prefix, suffix=path.suffix, dir=path.parent)
        os.close(fd)
        tmp = Path(name)
        os.chmod(tmp, 0o666 & ~mask)
    old = None
    try:
        yield tmp
        if is_dir:
            if path.exists():
                old = path.with_name(f".{path.name}.old{os.getpid()}")
                _remove(old)
                path.rename(old)
            tmp.rename(path)
        else:
            os.replace(tmp, path)
    except BaseException:  # the previous version stays (or is put back when the swap was cut between its renames)
        _remove(tmp)
        if old is not None and old.exists():
            if path.exists():
                _remove(old)
            else:
                old.rename(path)
        raise
    if old is not None:
        try:
            _remove(old)
        except BaseException:  # SIGTERM while the previous version is deleted: finish deleting it, then stop
            _remove(old)
            raise


class InputError(ValueError):
    """An input file exists but cannot be read as what it should be (truncated, corrupt, wrong format)."""


@contextlib.contextmanager
def reading(path: str | os.PathLike, what: str = "file") -> Iterator[None]:
    """Errors raised while reading ``path`` become one :class:`InputError` naming the file."""
    import zipfile

    try:
        yield
    except InputError:
        raise
    except FileNotFoundError as exc:
        raise InputError(f"{path}: {what} not found") from exc
    except (OSError, ValueError, EOFError, KeyError, IndexError, zipfile.BadZipFile, SyntaxError) as exc:
        detail = " ".join(str(exc).split()) or type(exc).__name__
        raise InputError(f"{path}: unreadable {what} ({type(exc).__name__}: {detail})") from exc


def load_array(path: str | os.PathLike, what: str = "array"):
    """``np.load`` of an ``.npy`` file, naming the file in any error."""
    import numpy as np

    with reading(path, what):
        return np.load(path, allow_pickle=False)


def load_arrays(path: str | os.PathLike, what: str = "archive") -> dict:
    """Every array of an ``.npz`` file, read eagerly, naming the file in any error (truncated, not a zip)."""
    import numpy as np

    with reading(path, what), np.load(path, allow_pickle=False) as data:
        return {key: data[key] for key in data.files}


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Atomically write ``text`` to ``path``."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return path


def _json_safe(value: Any) -> Any:
    """Convert numpy/torch scalars and non-finite floats to JSON (non-finite -> null)."""
    if isinstance(value, Mapping):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if hasattr(value, "item") and callable(value.item) and getattr(value, "ndim", 0) == 0:
        value = value.item()
    if hasattr(value, "tolist"):
        return _json_safe(value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


def write_json(path: str | os.PathLike, data: Mapping) -> Path:
    """Atomically write ``data`` as sorted, indented JSON (byte-stable for the same data)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(_json_safe(data), indent=2, sort_keys=True) + "\n")
    return path


def save_torch(obj: Any, path: str | os.PathLike) -> Path:
    """Atomically ``torch.save`` ``obj`` to ``path``, byte-stable for the same object.

    ``torch.save`` to a file *name* puts that name inside the archive, and the atomic write's temporary
    name is random: the same weights then hash differently every run, and DVC's run cache misses every
    stage downstream. Written through a file object, the archive's inner name is fixed.
    """
    import torch

    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        torch.save(obj, handle)
    return path


def read_json(path: str | os.PathLike) -> Any:
    """Read JSON, naming the file in the error."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: malformed JSON: {exc}") from exc


def pack_files(root: str | os.PathLike, files: list, archive: str | os.PathLike) -> int:
    """Write ``files`` (paths relative to ``root``, or ``(source path, name in the archive)`` pairs) to the gzipped
    tar ``archive``, atomically (an archive cut off midway never replaces the last good one); returns the file
    count."""
    import tarfile

    root, archive = Path(root), Path(archive)
    n = 0
    with atomic_path(archive) as tmp, tarfile.open(tmp, "w:gz") as tar:
        for item in files:
            src, name = item if isinstance(item, tuple) else (root / item, item)
            n += add_file(tar, src, Path(name).as_posix())
    return n


def add_file(tar, src: str | os.PathLike, name: str) -> bool:
    """Add the file ``src`` to the open ``tarfile`` ``tar`` as ``name``, its size and bytes from one open file, so a
    file that a running writer replaces meanwhile (atomically: :func:`atomic_path`) goes in whole, old or new
    (``tar.add`` takes the size from the path, then opens it: a replaced file came out cut or raised). False, and
    nothing added, when the file is gone (removed since it was listed)."""
    try:
        f = open(src, "rb")
    except FileNotFoundError:
        return False
    with f:
        tar.addfile(tar.gettarinfo(arcname=name, fileobj=f), f)
    return True


def unpack_files(archive: str | os.PathLike, root: str | os.PathLike, allowed, what: str, skip=None) -> int:
    """Unpack the gzipped tar ``archive`` into ``root``, keeping a file already there (it is at least as new) and
    leaving out the members ``skip(path) -> bool`` names; returns the count unpacked. Every member must be a plain
    file whose relative path ``allowed(path) -> bool`` accepts, or a folder entry (passed over: ``tar czf x.tgz
    runs`` writes them; session 24's records.tgz had them), or nothing is written: ``ValueError`` naming the
    archive, the member and ``what`` it should be."""
    import tarfile

    archive, root = Path(archive), Path(root)
    if not archive.is_file():
        raise FileNotFoundError(f"{archive}: no {what} there")
    n = 0
    with tarfile.open(archive, "r:gz") as tar:
        members = tar.getmembers()
        for member in members:
            if ".." in Path(member.name).parts or Path(member.name).is_absolute() \
                    or not (member.isdir() or member.isfile() and allowed(member.name)):
                raise ValueError(f"{archive}: {member.name!r} is not a {what} file")
        members = [m for m in members if m.isfile()]
        for member in members:
            target = root / member.name
            if target.exists() or (skip is not None and skip(member.name)):
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            with tar.extractfile(member) as src, atomic_path(target) as tmp:
                tmp.write_bytes(src.read())
            n += 1
    return n
