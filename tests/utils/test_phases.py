"""PhaseTimer: wall and CPU seconds (worker processes included) and episodes per phase."""
import subprocess
import sys
import time

import pytest

from trakdis.utils.phases import PhaseTimer, available_workers, process_tree_cpu_seconds

BURN = "import time\nt = time.process_time()\nwhile time.process_time() - t < {s}: pass\n"


def test_phases_accumulate_and_table():
    timer = PhaseTimer()
    with timer.phase("collect", episodes=4, workers=2):
        time.sleep(0.05)
    with timer.phase("train"):
        t = time.process_time()
        while time.process_time() - t < 0.1:
            pass
    with timer.phase("collect", episodes=2, workers=2) as rec:
        rec["episodes"] += 1  # counted inside the block
    assert list(timer.records) == ["collect", "train"]
    assert timer.records["collect"]["episodes"] == 7 and timer.episodes == 7
    assert timer.records["collect"]["wall"] >= 0.05 and timer.records["train"]["cpu"] >= 0.09
    table = timer.table(total_wall=timer.wall + 1.0).splitlines()
    assert table[0].split()[:4] == ["phase", "wall", "s", "CPU"]
    assert table[1].startswith("collect") and table[1].split()[3] == "7" and table[1].split()[-1] == "2"
    assert table[-2].startswith("other") and table[-1].startswith("total") and table[-1].split()[3] == "7"
    again = PhaseTimer(timer.state_dict())  # a resumed run goes on from the saved records
    with again.phase("train", episodes=0):
        pass
    assert again.records["collect"] == timer.records["collect"] and again.episodes == 7


def test_phase_is_recorded_when_the_block_raises():
    timer = PhaseTimer()
    with pytest.raises(RuntimeError):
        with timer.phase("eval", episodes=3):
            raise RuntimeError("boom")
    assert timer.records["eval"]["episodes"] == 3 and timer.records["eval"]["wall"] >= 0


def test_cpu_of_worker_processes_is_counted():
    before = process_tree_cpu_seconds()
    child = subprocess.Popen([sys.executable, "-c", BURN.format(s=0.5)])
    time.sleep(0.3)
    alive = process_tree_cpu_seconds() - before  # a live child, read from /proc
    child.wait()
    after = process_tree_cpu_seconds() - before  # a finished child, from RUSAGE_CHILDREN
    assert after >= 0.45 and alive >= 0.0


def test_available_workers():
    assert 1 <= available_workers() <= 2 and available_workers(cap=1) == 1


def test_excluded_background_child_is_booked_once_under_its_own_row():
    timer = PhaseTimer()
    child = subprocess.Popen([sys.executable, "-c", BURN.format(s=0.6)])
    timer.exclude(child.pid)
    with timer.phase("train"):  # the child burns CPU meanwhile: not this phase's
        time.sleep(0.3)
    assert timer.records["train"]["cpu"] < 0.2
    with timer.phase("wait"):
        child.wait()  # its CPU seconds now count in RUSAGE_CHILDREN
        timer.add_background("eval (background)", child.pid, episodes=3, wall=0.6, cpu=0.6)
    assert timer.records["wait"]["cpu"] < 0.2, "the finished child's CPU was booked to the phase that waited"
    assert timer.records["eval (background)"]["cpu"] == pytest.approx(0.6)
    assert timer.wall == pytest.approx(timer.records["train"]["wall"] + timer.records["wait"]["wall"])
    table = timer.table()
    assert "(" in table.splitlines()[3] and "background" in table.splitlines()[-1]
    again = PhaseTimer(timer.state_dict())  # a resumed run keeps the row marked as background
    assert again.background == {"eval (background)"} and again.wall == pytest.approx(timer.wall)


def test_report_prints_the_table_and_episodes_and_writes_json(tmp_path):
    import json

    timer = PhaseTimer()
    timer.add("collection", episodes=4, wall=1.0, cpu=0.5)
    timer.add("training", wall=2.0, cpu=2.0)
    lines = []
    timer.report(lines.append, tmp_path / "phases.json", total_wall=3.5, resumed=True, extra={"num_envs": 2})
    assert lines[0].startswith("phases (resumed run: earlier parts included; wall and CPU seconds")
    assert "collection" in lines[0] and "other" in lines[0]
    assert lines[1] == "episodes simulated: 4 (collection 4)"
    data = json.loads((tmp_path / "phases.json").read_text())
    assert list(data)[:4] == ["phases", "episodes_simulated", "wall_seconds_this_process", "num_envs"]
    assert data["episodes_simulated"] == 4 and data["wall_seconds_this_process"] == 3.5 and "loadavg" in data
