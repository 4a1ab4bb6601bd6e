"""Session 49: does the order of the (scene, seed) units change the three-seed Table 1's span? A processor-sharing
model (not a measurement): 36 GCA/NeuMA trainings (solo seconds of sessions 44-47, NeuMA 0.9x GCA, +25 s each for
its start and evaluation), 12 slots, the GPU's throughput T(k) rising from 1 to a cap (solo-seconds per second) as k
runs share it. Run: python3 benchmarks/results/table1_three_s49/unit_order_model.py"""
# processor-sharing model of the three-seed grid's trainings: 12 slots, GPU throughput T(k) [solo-seconds per second]
import itertools
solo = {"ball": 110, "duck": 114, "fish": 103, "pawn": 83, "cat": 84, "bottle": 87}  # GCA solo s (s44-47); NeuMA ~0.9x
def T(k, cap):  # throughput with k jobs running: linear to 2, then saturating at cap
    return min(k, 1 + (cap - 1) * (1 - 0.5 ** (k - 1)) / (1 - 0.5 ** 11)) if k else 0
def sim(order, cap, slots=12, start=60):
    jobs = [(s, m, seed, solo[s] * (1 if m == "gca" else 0.9) + 25) for s, m, seed in order]  # +25 s start/eval
    queue = list(jobs); run = []; t = start
    while queue or run:
        while queue and len(run) < slots:
            s, m, seed, w = queue.pop(0); run.append([w])
        k = len(run); rate = T(k, cap) / k
        dt = min(r[0] for r in run) / rate
        t += dt
        for r in run: r[0] -= dt * rate
        run = [r for r in run if r[0] > 1e-9]
    return t
scenes_name = sorted(solo); seeds = [1, 2, 0]
def units(scenes): return [(s, m, seed) for seed in seeds for s in scenes for m in ("gca", "neuma")]
def by_unit(scenes): return [(s, m, seed) for s in scenes for seed in seeds for m in ("gca", "neuma")]
heavy = sorted(solo, key=lambda s: -solo[s]); light = heavy[::-1]
for cap in (2.7, 3.2, 4.0):
    print(f"cap {cap}: name {sim(by_unit(scenes_name), cap):.0f} s, heavy-first {sim(by_unit(heavy), cap):.0f}, light-first {sim(by_unit(light), cap):.0f}")
