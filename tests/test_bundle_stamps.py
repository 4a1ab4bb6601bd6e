"""The device bundles' ``stamp`` lines print any text (session 37: an apostrophe in a stamp's text ended the
python -c string it was pasted into, and the line was lost in a paid call)."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
BUNDLES = sorted(p for p in BENCH.glob("*.sh") if re.search(r"^stamp\(\) \{", p.read_text(), re.M))


def _stamp(bundle: Path, text: str) -> subprocess.CompletedProcess:
    line = next(l for l in bundle.read_text().splitlines() if l.startswith("stamp() {"))
    shim = Path(sys.executable).parent  # the bundles call python3: this interpreter's
    return subprocess.run(["sh", "-c", f'T0=$(date +%s); {line}\nstamp "$1"', "sh", text], capture_output=True,
                          text=True, env={"PATH": f"{shim}:/usr/bin:/bin"})


def test_there_are_bundles_with_stamps():
    assert len(BUNDLES) >= 5, [p.name for p in BUNDLES]


@pytest.mark.parametrize("bundle", BUNDLES, ids=lambda p: p.name)
def test_a_stamp_prints_quotes_and_braces(bundle):
    text = "the first run's build {x} \"quoted\" $HOME"
    out = _stamp(bundle, text)
    assert out.returncode == 0, out.stderr
    assert re.fullmatch(r"\[\w+ +\d+ s\] " + re.escape(text) + "\n", out.stdout), out.stdout


def test_the_old_stamp_loses_such_a_line(tmp_path):
    """Negative control: the stamp as it was (the text pasted into the program) fails on the same text."""
    old = tmp_path / "old.sh"
    old.write_text("stamp() { python3 -c \"import time; print(f'[old {int(time.time()) - $T0:>4} s] $1', flush=True)\"; }\n")
    out = _stamp(old, "the first run's build")
    assert out.returncode != 0 and "SyntaxError" in out.stderr
