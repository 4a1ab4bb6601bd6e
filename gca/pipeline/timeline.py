"""A grid's timeline from its log: when each job ran, in grid time, and how many ran at once, plotted.

The grid (:func:`gca.pipeline.dispatch.run`) logs ``[grid HH:MM:SS] start <job> on ...``, ``done  <job> in <s> s``,
``stop  <job> at the deadline ...`` and ``FAIL  <job> ...``; each call of a ``--deadline`` grid opens with ``<n> jobs
(<m> to run) through ...`` and ends with ``after <s> s: ...``. Grid time is the calls' seconds summed: the gaps
between calls (another command, a machine's start) are left out, so a table resumed over three calls reads as one
span (session 49: the three-seed Table 1's 388 + 575 + 466 s). A job stopped at a deadline and resumed has one bar
per call.

    python -m gca.pipeline.timeline WORK/.grid/grid.log timeline.png [--json timeline.json]

``gca.pipeline.grid --collect`` writes ``timeline.png`` beside ``grid_results.tar.gz``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
from pathlib import Path

LINE_RE = re.compile(r"^\[grid (\d\d):(\d\d):(\d\d)\] (.*)$")
CALL_RE = re.compile(r"^\d+ jobs \(\d+ to run\)")
START_RE = re.compile(r"^(?:start|attach) (\S+)(?= on | \(log |$)")  # one machine: "... on gpu 0 (log L)"; SLURM: "(log L)"
BEFORE_RE = re.compile(r"^before: ")  # grid --before: logged ahead of its call's "N jobs" line
END_RE = re.compile(r"^(done|stop|FAIL|skip)\s+(\S+?):?(?=\s|$)")  # skip: "skip  X: Y failed" (cancelled)
AFTER_RE = re.compile(r"^after \d+ s:")
INPUT_STAGES = ("inputs", "object", "assets", "particles", "prior", "ground_truth", "preprocess")
COLORS = {"inputs": "#7f7f7f", "fit": "#bcbd22", "train:gca": "#d62728", "train:neuma": "#1f77b4",
          "train": "#9467bd", "evaluate": "#2ca02c", "nuisance": "#8c564b", "report": "#e377c2", "other": "#17becf"}


@dataclasses.dataclass
class Span:
    """One job's run in one call: ``start``, ``end`` [s of grid time]; ``how`` it ended: done, stop (a deadline),
    FAIL, skip (cancelled: a job it waits on failed), or open (the log ends with it running)."""

    job: str
    start: float
    end: float
    how: str
    call: int


@dataclasses.dataclass
class Timeline:
    """``spans`` in the order they started; ``calls``: each call's (start, end) [s of grid time]."""

    spans: list[Span]
    calls: list[tuple[float, float]]


def kind(job: str) -> str:
    """What a job is, for its colour: ``inputs`` (a data stage or a chain of them), ``fit`` (NCLaw's job: the scene's
    launch-velocity fit), ``train:<method>``, ``evaluate``, ``nuisance``, ``report``, else ``other``."""
    stage = job.split("@", 1)[0]
    if stage in INPUT_STAGES:
        return "inputs"
    if stage == "train":
        method = job.split(":", 1)[1].split("@", 1)[0].split("+", 1)[0] if ":" in job else ""
        return "fit" if method == "nclaw" else f"train:{method}" if f"train:{method}" in COLORS else "train"
    return stage if stage in COLORS else "other"


def parse(lines, where: str = "grid.log") -> Timeline:
    """The :class:`Timeline` of a grid log's ``lines`` (other lines, such as a failed job's log tail, are passed
    over). Clock times that go back (midnight) count as the next day. Raises ValueError naming ``where`` when no line
    is a grid line."""
    spans: list[Span] = []
    calls: list[tuple[float, float]] = []
    open_: dict[str, Span] = {}
    day, last_clock, call_wall, offset, now, before = 0, None, None, 0.0, 0.0, False

    def close_call() -> None:
        nonlocal offset
        for span in open_.values():
            span.end, span.how = now, "open"
        open_.clear()
        calls[-1] = (calls[-1][0], now)
        offset = now

    for line in lines:
        m = LINE_RE.match(line.rstrip("\n"))
        if m is None:
            continue
        clock = int(m.group(1)) * 3600 + int(m.group(2)) * 60 + int(m.group(3))
        if last_clock is not None and clock < last_clock:
            day += 1
        last_clock = clock
        wall, msg = clock + 86400 * day, m.group(4)
        if BEFORE_RE.match(msg):  # a call's --before command: the call starts at its "N jobs" line
            if call_wall is not None:  # the call before it ended without its "after" line (killed)
                close_call()
                call_wall = None
            before = True
            continue
        if CALL_RE.match(msg) or (call_wall is None and not calls and not before):  # a call's first line (or the log's)
            if call_wall is not None:
                close_call()
            call_wall, before = wall, False
            calls.append((offset, offset))
        elif call_wall is None:  # between a call's "after" and the next call: its results, the MPS daemon, --before
            continue
        now = offset + wall - call_wall
        if (s := START_RE.match(msg)) is not None:
            span = Span(s.group(1), now, now, "open", len(calls) - 1)
            spans.append(span)
            open_[span.job] = span
        elif (e := END_RE.match(msg)) is not None and e.group(2) in open_:
            span = open_.pop(e.group(2))
            span.end, span.how = now, e.group(1)
        elif e is not None and e.group(1) == "done" and msg.endswith("as it was stopped"):  # it ended on the stop's
            last = next((x for x in reversed(spans) if x.job == e.group(2)), None)  # signal, its work finished
            if last is not None and last.how == "stop" and last.call == len(calls) - 1:
                last.how = "done"
        elif AFTER_RE.match(msg):
            close_call()
            call_wall = None
    if not calls:
        raise ValueError(f"{where}: no grid log lines ('[grid HH:MM:SS] ...', gca.pipeline.dispatch.run's)")
    if call_wall is not None:
        close_call()
    return Timeline(spans, calls)


def running(timeline: Timeline, t: float, kinds=None) -> int:
    """How many jobs (of ``kinds``, all by default) ran at grid time ``t`` [s]."""
    return sum(1 for s in timeline.spans if s.start <= t < s.end and (kinds is None or kind(s.job) in kinds))


def summary(timeline: Timeline) -> dict:
    """Grid seconds in all and per call, each kind's job-seconds [s], and the mean jobs running per call."""
    per_kind: dict[str, float] = {}
    for s in timeline.spans:
        per_kind[kind(s.job)] = per_kind.get(kind(s.job), 0.0) + s.end - s.start
    mean = []
    for i, (a, b) in enumerate(timeline.calls):
        busy = sum(s.end - s.start for s in timeline.spans if s.call == i)
        mean.append(round(busy / (b - a), 2) if b > a else 0.0)
    return {"grid_seconds": timeline.calls[-1][1], "calls_seconds": [round(b - a, 1) for a, b in timeline.calls],
            "job_seconds": {k: round(v, 1) for k, v in sorted(per_kind.items())}, "mean_running": mean,
            "jobs": len({s.job for s in timeline.spans}), "stopped": sum(s.how == "stop" for s in timeline.spans),
            "failed": sorted(s.job for s in timeline.spans if s.how == "FAIL")}


def plot(timeline: Timeline, path: Path, title: str = "grid timeline") -> None:
    """Bars per job (a row each, in the order they first started; colour: :func:`kind`; a hatched end: stopped at a
    deadline, a cross: failed), the calls' boundaries, and below the jobs running [count] and the GCA/NeuMA trainings
    among them, against grid time [min]. Written atomically to ``path`` (PNG)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gca.io import atomic_path

    rows: dict[str, int] = {}
    for s in timeline.spans:
        rows.setdefault(s.job, len(rows))
    fig, (top, low) = plt.subplots(2, 1, figsize=(11, 3 + 0.09 * len(rows)), dpi=100, sharex=True,
                                   gridspec_kw={"height_ratios": [max(2, len(rows) // 12), 1]})
    for s in timeline.spans:
        top.barh(rows[s.job], (s.end - s.start) / 60, left=s.start / 60, height=0.8, color=COLORS[kind(s.job)],
                 hatch="//" if s.how == "stop" else None, edgecolor="k" if s.how != "done" else None, linewidth=0.3)
        if s.how == "FAIL":
            top.plot(s.end / 60, rows[s.job], "kx", ms=5)
    for a, b in timeline.calls[1:]:
        for ax in (top, low):
            ax.axvline(a / 60, color="k", lw=0.8, ls="--")
    top.set(ylim=(len(rows), -1), ylabel="job (by first start)", title=title)
    top.set_yticks([])
    used = sorted({kind(s.job) for s in timeline.spans}, key=list(COLORS).index)
    if used:
        top.legend(handles=[matplotlib.patches.Patch(color=COLORS[k], label=k) for k in used], fontsize=7,
                   ncol=len(used), loc="lower right")
    end = timeline.calls[-1][1]
    ts = [i * end / 400 for i in range(401)]
    low.step([t / 60 for t in ts], [running(timeline, t) for t in ts], where="post", label="jobs running")
    low.step([t / 60 for t in ts], [running(timeline, t, ("train:gca", "train:neuma")) for t in ts], where="post",
             label="GCA + NeuMA trainings")
    low.set(xlabel="grid time [min] (calls summed; dashed: a new call)", ylabel="count")
    low.legend(fontsize=7, loc="lower left")
    try:
        fig.tight_layout()
        with atomic_path(Path(path)) as tmp:
            fig.savefig(tmp, format="png", metadata={"Software": None})
    finally:
        plt.close(fig)


def from_log(log: Path, png: Path, title: str | None = None) -> dict:
    """Parse grid log ``log``, plot it to ``png``; returns :func:`summary`. Raises ValueError naming ``log``."""
    timeline = parse(Path(log).read_text(errors="replace").splitlines(), str(log))
    plot(timeline, png, title or "grid timeline: " + str(log).replace("$", r"\$"))  # a path's "$" is no mathtext
    return summary(timeline)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("log", type=Path, help="a grid's log (WORK/.grid/grid.log)")
    ap.add_argument("png", type=Path, help="the plot to write")
    ap.add_argument("--json", type=Path, help="also write the summary here")
    args = ap.parse_args(argv)
    if not args.log.is_file():
        raise SystemExit(f"{args.log}: no such grid log")
    try:
        info = from_log(args.log, args.png)
    except ValueError as err:
        raise SystemExit(str(err)) from None
    if args.json:
        args.json.write_text(json.dumps(info, indent=1) + "\n")
    print(f"timeline: {args.png} ({info['jobs']} jobs, {info['grid_seconds']:.0f} s of grid time in "
          f"{len(info['calls_seconds'])} call(s), {info['stopped']} stopped at a deadline)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
