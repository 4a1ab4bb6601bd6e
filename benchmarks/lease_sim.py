"""One fresh machine on a grid state's remaining training runs, simulated on the CPU: the plain lease rule against
dispatch.lease_admits, with grid.packed_seconds taken as the truth (8 slots, ~200 s of inputs, one 1800-s lease less
its margins: DETACH=1, one grid over the machine, no stop between calls). A prediction aid for benchmarks/NOTES.md, no GPU.
  python -m gca.pipeline.grid --work /tmp/mlw <the grid's options> --restore-state STATE --stages report  (any stage)
  python benchmarks/lease_sim.py /tmp/mlw [methods first, as grid --first-methods]
  MACHINE_S=1400 SLOTS=12 python benchmarks/lease_sim.py ...   (table_bundle.sh's MACHINE_S and SLOTS; defaults 1800, 8)
"""
import os
import sys
from collections import Counter
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from gca.pipeline import grid, dispatch

work = Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/mlw")  # a grid work folder with the state restored
params = yaml.safe_load((work / "params.yaml").read_text())
jobs = grid.expand(yaml.safe_load((ROOT / "dvc.yaml").read_text()), params, ["train"])
jobs = grid.link(grid.batch_runs(grid.split_runs(jobs, params), 1))
todo = [n for n in jobs if n.startswith("train@") and not dispatch.is_done(work, n)]
exp = grid._expected_in(work, 900.0, 8)
T = {n: exp(n) for n in todo}
prio = dispatch.critical_path(jobs)
first = grid.first_methods(sys.argv[2:])  # python benchmarks/lease_sim.py WORK [FIRST METHODS ...]
order = dispatch.launch_order(todo, prio, todo, lambda n: T[n], first)
print(len(todo), "runs left; expected 8-way [s]:", sorted(round(v) for v in T.values()))
packed = lambda s, k: grid.packed_seconds(s, 8, k)
SLOTS = int(os.environ.get("SLOTS", 8))
MACHINE, INPUTS, DT = int(os.environ.get("MACHINE_S", 1800)) - 60 - 150, 200.0, 1.0  # DETACH=1: the grid's deadline (LEFT - 150)

def simulate(aware):
    t, queue, running, done = INPUTS, list(order), {}, []
    while t < MACHINE:
        k = len(running)
        for n in list(running):  # progress at the current load
            running[n] -= DT / packed(T[n], k)
            if running[n] <= 0:
                done.append(n); del running[n]
        for n in list(queue):
            if len(running) >= SLOTS:
                break
            left = MACHINE - t
            ok = (dispatch.lease_admits(left, T[n], [(T[m], f) for m, f in running.items()], packed) if aware
                  else T[n] <= left)
            if ok:
                running[n] = 1.0; queue.remove(n)
        t += DT
    return done, list(running)

for aware in (False, True):
    done, cut = simulate(aware)  # cut: the runs still going at the lease's end
    per = Counter((scene, run.split("@", 1)[0]) for scene, runs in map(dispatch.job_runs, done) for run in runs)
    print(("lease_admits" if aware else "old rule    "), f"{len(done)} trainings done, {len(cut)} cut off by the lease:",
          ", ".join(f"{scene} {method} x{k}" for (scene, method), k in sorted(per.items())))
