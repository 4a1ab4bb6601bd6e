"""Session 53: when would the lost three-seed grid have ended? A processor-sharing model (not a measurement) of its
jobs at 1065 s of grid time (grid.log): each job's work in "12-packed seconds" (its own scene and method's seed-1/2
packed duration in this grid), less what it had run; rates rise as fewer jobs share the GPU, T(k) solo-seconds per
second saturating at a cap. Run: python3 benchmarks/results/table1_three_s53/tail_model.py"""
def T(k, cap):  # throughput with k jobs running: linear to 2, then saturating at cap (session 49's model)
    return min(k, 1 + (cap - 1) * (1 - 0.5 ** (k - 1)) / (1 - 0.5 ** 11)) if k else 0
T0 = 1065.0
EVAL = 18.0  # an evaluation's packed seconds here (16-24 s)
running = {"pawn:neuma@1": 318 - 357, "bottle:gca": 516 - (T0 - 759), "bottle:neuma": 507 - (T0 - 770),
           "cat:gca": 458 - (T0 - 1003), "cat:neuma": 435 - (T0 - 1034), "duck:gca": 296 - (T0 - 1056),
           "duck:neuma": 248 - (T0 - 1057), "eval1": 8, "eval2": 10, "eval3": 12, "eval4": 14, "eval5": 16}
queue = {"pawn:gca": 338, "pawn:neuma": 318, "fish:gca": 384, "fish:neuma": 366}
def sim(cap, slots=12, report=15.0):
    run = {k: max(v, 5.0) for k, v in running.items()}  # the pawn's NeuMA past its seed-2 time: 5 s left
    q = dict(queue); t = T0
    while run or q:
        while q and len(run) < slots:
            k = next(iter(q)); run[k] = q.pop(k)
        k = len(run); rate = (T(k, cap) / k) / (T(12, cap) / 12)  # relative to 12 packed
        name = min(run, key=run.get); dt = run[name] / rate; t += dt
        for n in run: run[n] -= dt * rate
        del run[name]
        if not name.startswith("eval"): run["eval:" + name] = EVAL  # each training's evaluation follows it
        run = {n: v for n, v in run.items() if v > 1e-9}
    return t + report
for cap in (2.7, 3.2, 4.0):
    print(f"cap {cap}: the table at {sim(cap):.0f} s of grid time ({sim(cap) / 60:.1f} min)")
