"""Give the runs of a grid state made before session 20 the launch velocity they trained with (a script, run once).

Before session 20 ``train.json`` did not keep its run's launch velocity; evaluation read the seed's shared
``runs/<scene>/velocity[@seed<k>].json``. A grid that goes on on another machine remakes the inputs, which differ
there in float32 noise (the ground truth's MPM atomics), so the next job of that seed estimates the velocity again
and overwrites the shared file (session 20: bottle seed 0's v0_x 2.587, 2.540, 2.530 m/s on three machines). The
run was trained with the file of the machine where it was trained, which the state saved on that machine still
holds. For every finished run without ``velocity`` in its ``train.json``, this takes that file from the first of
``--history`` (the states saved after each call, in order) that holds the run's ``train.json``, writes it into the
``train.json`` (with ``velocity_recovered_from``), drops the run's evaluation made since (its marker and JSON:
it read another machine's estimate; the grid evaluates it again) and writes the state back.

    python benchmarks/recover_velocities.py --state STATE.tgz --history m1.tgz m2.tgz m3.tgz
"""

from __future__ import annotations

import argparse
import io
import json
import re
import tarfile
from pathlib import Path

RUN_RE = re.compile(r"^runs/([^/]+)/([^/]+)/train\.json$")


def _members(archive: Path) -> dict[str, bytes]:
    with tarfile.open(archive, "r:gz") as tar:
        return {m.name: tar.extractfile(m).read() for m in tar.getmembers() if m.isfile()}


def velocity_file(scene: str, run: str) -> str:
    """The shared launch-velocity file of ``run``'s seed (``gca@seed2`` -> ``velocity@seed2.json``)."""
    seed = run.split("@", 1)[1] if "@" in run else ""
    return f"runs/{scene}/velocity{'@' + seed if seed else ''}.json"


def recover(state: Path, history: list[Path]) -> dict[str, str]:
    """Rewrite ``state`` as the module doc says; returns {run: the archive its velocity came from}."""
    files = _members(state)
    earlier = [(path, _members(path)) for path in history]
    done = {}
    for name in sorted(files):
        m = RUN_RE.match(name)
        if not m:
            continue
        train = json.loads(files[name])
        if "velocity" in train:
            continue
        scene, run = m.groups()
        source = next(((p, f) for p, f in earlier if name in f and velocity_file(scene, run) in f), None)
        if source is None:
            raise SystemExit(f"{state}: no state of --history holds {name} with its velocity file")
        raw = json.loads(source[1][velocity_file(scene, run)])
        train["velocity"] = {"v0": raw["v0"], "w0": raw["w0"]}
        train["velocity_recovered_from"] = f"{source[0].name}:{velocity_file(scene, run)}"
        files[name] = (json.dumps(train, indent=2, sort_keys=True) + "\n").encode()
        for stale in (f".grid/evaluate@{scene}:{run}.done", f"metrics/eval/{scene}/{run}.json"):
            files.pop(stale, None)
        done[f"{scene}/{run}"] = source[0].name
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        for name in sorted(files):
            info = tarfile.TarInfo(name)
            info.size = len(files[name])
            tar.addfile(info, io.BytesIO(files[name]))
    state.write_bytes(buf.getvalue())
    return done


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--state", type=Path, required=True)
    ap.add_argument("--history", type=Path, nargs="+", required=True, help="earlier states, oldest first")
    args = ap.parse_args(argv)
    done = recover(args.state, args.history)
    for run, source in done.items():
        print(f"{run}: velocity from {source}")
    print(f"{len(done)} runs given the launch velocity they trained with")


if __name__ == "__main__":
    main()
