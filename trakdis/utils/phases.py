"""Where a recipe's time goes: wall and CPU seconds, and simulated episodes, per phase.

    phases = PhaseTimer()
    with phases.phase("offline training"):
        ...
    with phases.phase("evaluation", episodes=40):
        ...
    print(phases.table())

CPU seconds count this process and its worker processes (a ``ParallelEnv``'s or a collector's
workers), so that on a shared machine, where wall time moves with the other jobs, the work
itself can still be compared: ``wall ~= CPU / workers`` on an idle machine with one core per worker.
"""
from __future__ import annotations

import json
import os
import resource
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Collection, Iterator, Mapping

from .checkpoint import atomic_write_bytes

__all__ = ["PhaseTimer", "available_workers", "process_tree_cpu_seconds"]


def available_workers(cap: int = 2) -> int:
    """CPU cores this process may run on (its affinity mask), at most ``cap``: the default number
    of environments stepped in parallel."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        cores = os.cpu_count() or 1
    return max(1, min(int(cap), cores))


def _descendants_cpu_seconds(exclude: Collection[int] = ()) -> float:
    """CPU seconds (user + system, with their own reaped children) of the live descendants of this
    process, read from ``/proc`` (Linux; 0 elsewhere), leaving out the subtrees of the pids in
    ``exclude``. Finished children are counted by ``RUSAGE_CHILDREN`` instead, once they were waited for."""
    me = os.getpid()
    try:
        pids = [int(p) for p in os.listdir("/proc") if p.isdigit()]
    except OSError:
        return 0.0
    parent, ticks = {}, {}
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat", "rb") as f:
                stat = f.read().decode(errors="replace")
        except OSError:  # exited meanwhile, or not readable
            continue
        fields = stat[stat.rfind(")") + 2:].split()  # after "pid (comm) "
        try:
            parent[pid] = int(fields[1])
            ticks[pid] = sum(int(v) for v in fields[11:15])  # utime stime cutime cstime
        except (IndexError, ValueError):
            continue
    total, frontier = 0, [me]
    while frontier:
        kids = [pid for pid, ppid in parent.items() if ppid in frontier and pid not in exclude]
        total += sum(ticks[pid] for pid in kids)
        frontier = kids
    return total / os.sysconf("SC_CLK_TCK")


def process_tree_cpu_seconds(exclude: Collection[int] = ()) -> float:
    """CPU seconds used so far by this process, its finished children and its live descendants
    (but the live subtrees of the pids in ``exclude``)."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime + _descendants_cpu_seconds(exclude)


class PhaseTimer:
    """Per phase: ``wall`` and ``cpu`` seconds and ``episodes`` simulated, accumulated over every
    ``with timer.phase(name)`` block of that name (in first-use order). ``state_dict`` /
    ``load_state_dict`` (plain floats) let a resumed run report the phases of its earlier part.

    A child process that works beside the phases (a background evaluation) is left out of them
    with :meth:`exclude`, and its work is booked once, under its own name, with :meth:`add_background`
    when it has finished."""

    def __init__(self, state: Mapping[str, Mapping[str, Any]] | None = None):
        self.records: dict[str, dict[str, float]] = {}
        self.background: set[str] = set()
        self._exclude: set[int] = set()
        self._discount = 0.0
        if state:
            self.load_state_dict(state)

    def _cpu(self) -> float:
        return process_tree_cpu_seconds(self._exclude) - self._discount

    def exclude(self, pid: int) -> None:
        """Leave the live child ``pid`` (and its descendants) out of every phase's CPU seconds."""
        self._exclude.add(int(pid))

    def add_background(self, name: str, pid: int, *, episodes: int, wall: float, cpu: float, workers: int = 1) -> None:
        """Book the finished (waited-for) excluded child ``pid``: ``cpu`` seconds (its own count, which
        ``RUSAGE_CHILDREN`` now includes) leave the later phases' readings and go to ``name``, a row
        that overlapped the others (its wall time is not part of the total)."""
        self._exclude.discard(int(pid))
        self._discount += float(cpu)
        self.add(name, episodes=episodes, wall=wall, cpu=cpu)
        self.records[name]["workers"] = max(int(self.records[name]["workers"]), int(workers))
        self.background.add(name)

    def _record(self, name: str) -> dict[str, float]:
        return self.records.setdefault(name, {"wall": 0.0, "cpu": 0.0, "episodes": 0, "workers": 1})

    @contextmanager
    def phase(self, name: str, *, episodes: int = 0, workers: int = 1) -> Iterator[dict[str, float]]:
        """Time the block; the yielded record's ``"episodes"`` may be raised inside it."""
        rec = self._record(name)
        rec["episodes"] += int(episodes)
        rec["workers"] = max(int(rec["workers"]), int(workers))
        wall, cpu = time.perf_counter(), self._cpu()
        try:
            yield rec
        finally:
            rec["wall"] += time.perf_counter() - wall
            rec["cpu"] += max(0.0, self._cpu() - cpu)

    def add(self, name: str, *, episodes: int = 0, wall: float = 0.0, cpu: float = 0.0) -> None:
        rec = self._record(name)
        rec["episodes"] += int(episodes)
        rec["wall"] += float(wall)
        rec["cpu"] += float(cpu)

    @property
    def episodes(self) -> int:
        return int(sum(r["episodes"] for r in self.records.values()))

    @property
    def wall(self) -> float:
        """Wall seconds of the phases that ran one after another (background rows overlapped them)."""
        return float(sum(r["wall"] for k, r in self.records.items() if k not in self.background))

    def state_dict(self) -> dict[str, dict[str, float]]:
        return {k: {**v, "background": k in self.background} for k, v in self.records.items()}

    def load_state_dict(self, state: Mapping[str, Mapping[str, Any]]) -> None:
        self.records = {str(k): {"wall": float(v["wall"]), "cpu": float(v["cpu"]), "episodes": int(v["episodes"]),
                                 "workers": int(v.get("workers", 1))} for k, v in state.items()}
        self.background = {str(k) for k, v in state.items() if v.get("background")}

    def table(self, total_wall: float | None = None) -> str:
        """A plain-text table: phase, wall s, CPU s, episodes, s per episode (CPU), workers; then the totals."""
        width = max([len("phase"), len("total"), *map(len, self.records)])
        lines = [f"{'phase':<{width}}  {'wall s':>8}  {'CPU s':>8}  {'episodes':>8}  {'CPU s/ep':>8}  workers"]
        for name, r in self.records.items():
            per = f"{r['cpu'] / r['episodes']:8.2f}" if r["episodes"] else f"{'':8}"
            wall = f"({r['wall']:6.1f})" if name in self.background else f"{r['wall']:8.1f}"
            lines.append(f"{name:<{width}}  {wall}  {r['cpu']:8.1f}  {r['episodes']:8d}  {per}  {r['workers']:>7d}")
        cpu = sum(r["cpu"] for r in self.records.values())
        wall = self.wall if total_wall is None else total_wall
        if wall - self.wall > 0.05:
            lines.append(f"{'other':<{width}}  {wall - self.wall:8.1f}")
        lines.append(f"{'total':<{width}}  {wall:8.1f}  {cpu:8.1f}  {self.episodes:8d}")
        if self.background:
            lines.append("(wall in parentheses: in a background process at low priority, beside the other phases; "
                         "not part of the total wall)")
        return "\n".join(lines)

    def report(self, print_fn: Callable[[str], Any], path: str | Path | None = None, *, total_wall: float,
               resumed: bool = False, extra: Mapping[str, Any] | None = None) -> None:
        """Print the :meth:`table` and the episodes per phase with ``print_fn``, and write ``path``
        (JSON: the phases, ``episodes_simulated``, ``wall_seconds_this_process`` = ``total_wall``,
        ``extra`` and the load average)."""
        print_fn(f"phases ({'resumed run: earlier parts included; ' if resumed else ''}wall and CPU seconds, "
                 f"CPU of this process and its env workers):\n" + self.table(total_wall=total_wall))
        if path is not None:
            data = {"phases": self.state_dict(), "episodes_simulated": self.episodes,
                    "wall_seconds_this_process": total_wall, **dict(extra or {}),
                    "loadavg": list(os.getloadavg()) if hasattr(os, "getloadavg") else None}
            atomic_write_bytes(Path(path), (json.dumps(data, indent=1) + "\n").encode())
        print_fn(f"episodes simulated: {self.episodes} ("
                 + ", ".join(f"{k} {r['episodes']}" for k, r in self.records.items() if r["episodes"]) + ")")

