"""The rasterizer choice is said, never silent; `make setup` installs and compiles gsplat on CUDA.

- :func:`gca.render.backend.choose` for each (request, CUDA, gsplat installed): the backend, its
  reason, one stderr line per distinct choice (not one per call).
- scripts/setup.sh with a stub python: with CUDA it installs ``.[dev,gpu]`` and builds gsplat's
  extension before anything else can import it; without CUDA (or SKIP_GSPLAT=1) it does neither.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from gca.render import backend as rb

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def fresh(monkeypatch):
    monkeypatch.setattr(rb, "_said", set())
    return rb


def _installed(monkeypatch, version):
    monkeypatch.setattr(rb, "gsplat_version", lambda: version)


def test_auto_without_cuda_says_torch_once(fresh, capsys, monkeypatch):
    _installed(monkeypatch, "1.5.3")
    assert fresh.choose("auto", on_cuda=False) == ("torch", "auto: no CUDA device")
    fresh.choose("auto", on_cuda=False)
    err = capsys.readouterr().err
    assert err.count("gca.render: rasterizer torch (auto: no CUDA device)") == 1


def test_auto_on_cuda_without_gsplat_is_not_silent(fresh, capsys, monkeypatch):
    _installed(monkeypatch, None)
    backend, reason = fresh.choose("auto", on_cuda=True)
    assert backend == "torch" and "gsplat not installed" in reason and "gca[gpu]" in reason
    assert "rasterizer torch (auto: gsplat not installed" in capsys.readouterr().err


def test_auto_on_cuda_with_gsplat(fresh, capsys, monkeypatch):
    _installed(monkeypatch, "1.5.3")
    assert fresh.choose("auto", on_cuda=True) == ("gsplat", "auto: CUDA device and gsplat 1.5.3 installed")
    assert "rasterizer gsplat" in capsys.readouterr().err


def test_explicit_choices(fresh, monkeypatch):
    _installed(monkeypatch, None)
    assert fresh.choose("torch", on_cuda=True)[0] == "torch"
    with pytest.warns(RuntimeWarning, match="needs CUDA"):
        assert fresh.choose("gsplat", on_cuda=False)[0] == "torch"
    assert fresh.choose("gsplat", on_cuda=True) == ("gsplat", f"render.backend=gsplat, gsplat NOT installed: {rb.INSTALL_HINT}")
    with pytest.raises(ValueError, match="opengl"):
        fresh.choose("opengl", on_cuda=True)


def test_build_without_gsplat_fails_loudly(fresh, capsys, monkeypatch):
    _installed(monkeypatch, None)
    assert fresh.build_gsplat() == 1
    assert "gsplat is not installed" in capsys.readouterr().err


STUB_PY = """#!/usr/bin/env bash
echo "python $*" >> "$STUB_LOG"
case "$*" in
  *"sys.exit(0 if torch.cuda.is_available()"*) exit "$STUB_CUDA" ;;
  *"weights_dir"*) echo "${STUB_WEIGHTS:-}" ;;
  *"[interp]"*) exit "${STUB_INTERP_RC:-0}" ;;
esac
exit 0
"""


STUB_DF = """#!/usr/bin/env bash
[ "${STUB_DF_RC:-0}" = 0 ] || exit "$STUB_DF_RC"
echo "Filesystem 1048576-blocks Used Available Capacity Mounted"
echo "/dev/vda 258000 20000 ${STUB_FREE_MB:-80000} 10% /"
"""


def _setup(tmp_path: Path, cuda: bool, **env) -> list[str]:
    repo = tmp_path / "repo"
    (repo / "scripts").mkdir(parents=True)
    shutil.copy2(ROOT / "scripts/setup.sh", repo / "scripts/setup.sh")
    bin_ = repo / ".venv/bin"
    bin_.mkdir(parents=True)
    (bin_ / "python").write_text(STUB_PY)
    (bin_ / "python").chmod(0o755)
    (bin_ / "df").write_text(STUB_DF)
    (bin_ / "df").chmod(0o755)
    (bin_ / "activate").write_text(f'export PATH="{bin_}:$PATH"\n')
    log = tmp_path / "calls.log"
    out = subprocess.run(["bash", "scripts/setup.sh"], cwd=repo, capture_output=True, text=True,
                         env={**os.environ, "STUB_LOG": str(log), "STUB_CUDA": "0" if cuda else "1", **env})
    assert out.returncode == 0, out.stderr
    return log.read_text().splitlines() + ["STDOUT " + out.stdout, "STDERR " + out.stderr]


def test_setup_installs_and_builds_gsplat_on_cuda(tmp_path):
    calls = _setup(tmp_path, cuda=True)
    install = calls.index('python -m pip install -q -e .[dev,gpu]')
    build = calls.index("python -m gca.render.backend --build")
    assert install < build
    assert "compiling gsplat's CUDA extension once" in calls[-2]


@pytest.mark.parametrize("cuda,env", [(False, {}), (True, {"SKIP_GSPLAT": "1"})])
def test_setup_without_cuda_skips_gsplat(tmp_path, cuda, env):
    """No CUDA: no gsplat, and triton for the fused MLP's interpreter twin (the interp extra, its own install after
    the project's); CUDA with gsplat skipped: no gsplat and no interp either (a CUDA torch brings its own triton)."""
    calls = _setup(tmp_path, cuda=cuda, **env)
    dev = calls.index('python -m pip install -q -e .[dev]')
    assert not any("gpu]" in c or "--build" in c for c in calls)
    assert ('python -m pip install -q -e .[interp]' in calls) == (not cuda)
    if not cuda:
        assert dev < calls.index('python -m pip install -q -e .[interp]')
    assert "skipped" not in calls[-1]


def test_setup_leaves_triton_out_when_the_disk_is_short(tmp_path):
    """A CI machine ran out of disk in pip (ENOSPC) with triton in the install: below INTERP_MIN_FREE_MB free, the
    project installs without it and says so in one line; the controls: 1 MB more installs it, and a failed triton
    install is undone (uninstalled) and said, never fatal."""
    limit = int(next(line.split("=")[1].split()[0] for line in (ROOT / "scripts/setup.sh").read_text().splitlines()
                     if line.startswith("INTERP_MIN_FREE_MB=")))
    short = _setup(tmp_path / "short", cuda=False, STUB_FREE_MB=str(limit - 1))
    assert 'python -m pip install -q -e .[dev]' in short and not any("[interp]" in c for c in short)
    assert f"only {limit - 1} MB free" in short[-1] and "tests will be skipped" in short[-1]
    room = _setup(tmp_path / "room", cuda=False, STUB_FREE_MB=str(limit))
    assert 'python -m pip install -q -e .[interp]' in room and "skipped" not in room[-1]
    failed = _setup(tmp_path / "failed", cuda=False, STUB_INTERP_RC="1")
    assert failed.index('python -m pip install -q -e .[interp]') < failed.index("python -m pip uninstall -q -y triton")
    assert "did not install" in failed[-1]
    broken = _setup(tmp_path / "broken", cuda=False, STUB_DF_RC="1")  # a df that fails: no triton, never fatal
    assert 'python -m pip install -q -e .[dev]' in broken and not any("[interp]" in c for c in broken)


SYSTEM_PY = """#!/usr/bin/env bash
echo "system-python $*" >> "$STUB_LOG"
case "$*" in
  "-m venv .venv") mkdir -p .venv/bin && cp "$STUB_VENV_PY" .venv/bin/python && cp "$(dirname "$0")/df" .venv/bin/df &&
                   echo "export PATH=\"$PWD/.venv/bin:\$PATH\"" > .venv/bin/activate ;;
  *) exit 1 ;;  # no torch on the system python
esac
"""


@pytest.mark.parametrize("free_mb, warned", [(2999, True), (3000, False)])
def test_a_first_install_says_when_the_disk_is_short(tmp_path, free_mb, warned):
    """No venv yet: below 3000 MB free the first install says how much it needs (one line) and goes on; at 3000 it
    says nothing (the control)."""
    repo = tmp_path / "repo"
    (repo / "scripts").mkdir(parents=True)
    shutil.copy2(ROOT / "scripts/setup.sh", repo / "scripts/setup.sh")
    stub = tmp_path / "stub"
    stub.mkdir()
    for name, text in (("python3", SYSTEM_PY), ("venv_python", STUB_PY), ("df", STUB_DF)):
        (stub / name).write_text(text)
        (stub / name).chmod(0o755)
    out = subprocess.run(["bash", "scripts/setup.sh"], cwd=repo, capture_output=True, text=True,
                         env={**os.environ, "PATH": f"{stub}:{os.environ['PATH']}", "PYTHON": str(stub / "python3"),
                              "STUB_VENV_PY": str(stub / "venv_python"), "STUB_LOG": str(tmp_path / "calls.log"),
                              "STUB_CUDA": "1", "STUB_FREE_MB": str(free_mb)})
    assert out.returncode == 0, out.stderr
    assert "system-python -m venv .venv" in (tmp_path / "calls.log").read_text()
    assert ("a CPU install takes about 2.5 GB" in out.stderr) == warned
    assert f"only {free_mb} MB free" in out.stderr if warned else "MB free" not in out.stderr


@pytest.mark.parametrize("with_model", [True, False])
def test_setup_installs_the_depth_extra_only_with_a_local_model(tmp_path, with_model):
    """A configured Depth Anything folder that holds a model (config.json) brings the depth extra; an empty or
    absent one does not (the negative control)."""
    weights = tmp_path / "repo" / "models" / "depth"
    weights.mkdir(parents=True)
    if with_model:
        (weights / "config.json").write_text("{}")
    calls = _setup(tmp_path, cuda=False, STUB_WEIGHTS=str(weights))
    assert ('python -m pip install -q -e .[depth]' in calls) == with_model


_HOLDER = """
import sys, time
from pathlib import Path
from gca.render.backend import build_lock
d = Path(sys.argv[1])
with build_lock(sys.argv[2]):
    (d / "a.in").touch()
    time.sleep(1.0)
    (d / "a.out").touch()
"""
_WAITER = """
import sys, time
from pathlib import Path
from gca.render.backend import build_lock
d = Path(sys.argv[1])
while not (d / "a.in").exists():
    time.sleep(0.02)
with build_lock(sys.argv[2]):
    (d / "b.saw").write_text(str((d / "a.out").exists()))
"""


def _two_processes(tmp_path, lock_a, lock_b) -> str:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    a = subprocess.Popen([os.sys.executable, "-c", _HOLDER, str(tmp_path), lock_a], env=env)
    b = subprocess.run([os.sys.executable, "-c", _WAITER, str(tmp_path), lock_b], env=env, timeout=60)
    assert a.wait(timeout=60) == 0 and b.returncode == 0
    return (tmp_path / "b.saw").read_text()


def test_a_second_process_waits_for_the_gsplat_build_lock(tmp_path):
    """The second process enters only after the first left (it sees a.out); with two different lock files (the
    negative control) it enters while the first still holds its own."""
    assert _two_processes(tmp_path, str(tmp_path / "x.lock"), str(tmp_path / "x.lock")) == "True"
    for f in ("a.in", "a.out", "b.saw"):
        (tmp_path / f).unlink()
    assert _two_processes(tmp_path, str(tmp_path / "x.lock"), str(tmp_path / "y.lock")) == "False"


def test_load_gsplat_imports_the_extension_under_the_lock(tmp_path):
    """A stand-in gsplat whose extension module, on import, tries to take the lock itself: it must find it held
    (gsplat's build deletes and refills its build directory, so no second process may build meanwhile)."""
    pkg = tmp_path / "site" / "gsplat" / "cuda"
    pkg.mkdir(parents=True)
    (pkg.parent / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "_backend.py").write_text(
        "import fcntl, os\n"
        "with open(os.environ['GCA_GSPLAT_LOCK'], 'a') as h:\n"
        "    try:\n"
        "        fcntl.flock(h, fcntl.LOCK_EX | fcntl.LOCK_NB)\n"
        "        HELD = False\n"
        "    except BlockingIOError:\n"
        "        HELD = True\n"
        "_C = 'extension' if HELD else None\n")
    env = {**os.environ, "PYTHONPATH": f"{tmp_path / 'site'}:{ROOT}", "GCA_GSPLAT_LOCK": str(tmp_path / "g.lock")}
    code = "from gca.render.backend import load_gsplat; print(load_gsplat(), load_gsplat())"
    out = subprocess.run([os.sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["extension", "extension"]
    # the negative control: imported without load_gsplat, the stand-in finds the lock free
    plain = "from gsplat.cuda._backend import _C; print(_C)"
    out = subprocess.run([os.sys.executable, "-c", plain], env=env, capture_output=True, text=True, timeout=60)
    assert out.stdout.split() == ["None"]
