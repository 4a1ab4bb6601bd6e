"""Run a snippet in a fresh Python under Triton's CPU interpreter (the CPU twin of the fused Triton kernels): Triton
reads ``TRITON_INTERPRET`` when a module's kernels are decorated, so each case needs its own process."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_interpreted(code: str, interpret: bool = True, cwd: Path = ROOT) -> str:
    """``code`` in a fresh Python in ``cwd`` (under Triton's interpreter unless ``interpret`` is False, which also
    clears an inherited ``TRITON_INTERPRET``); it must exit 0 and print "ok". Returns its stdout."""
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    if interpret:
        env["TRITON_INTERPRET"] = "1"
    out = subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0 and "ok" in out.stdout, out.stdout + out.stderr
    return out.stdout
