"""trakdis.utils.ray_stages: a pipeline's stages as Ray tasks on a local 2-CPU Ray, ordered by the run directories
their arguments name, skipped by their output files, failures reported with their logs, parts merged."""
import json
import sys
import textwrap
from pathlib import Path

import pytest

from trakdis.utils.run import Run, RunConfig
from trakdis.utils.stages import Parts

ray = pytest.importorskip("ray")

from trakdis.utils.ray_stages import RayConfig, RayStages, make_stages  # noqa: E402

# A recipe script: --input DIR must hold out.txt (a stage it needs); --sleep S first; --fail exits 3; writes out.txt
# (its argv, the time it started and ended) unless --interrupt.
RECIPE = textwrap.dedent('''
    import json, sys, time
    from pathlib import Path

    def main(argv):
        start = time.time()
        name, root = argv[argv.index("--name") + 1], argv[argv.index("--root") + 1]
        directory = Path(root) / "toy" / name
        directory.mkdir(parents=True, exist_ok=True)
        if "--input" in argv:
            assert (Path(argv[argv.index("--input") + 1]) / "out.txt").exists(), "ran before its input"
        if "--sleep" in argv:
            time.sleep(float(argv[argv.index("--sleep") + 1]))
        print(f"toy {name} ran")
        if "--fail" in argv:
            raise SystemExit(3)
        if "--interrupt" in argv:
            (directory / "log.csv").write_text("step")
            return
        (directory / "out.txt").write_text(json.dumps({"argv": argv, "start": start, "end": time.time()}))

    if __name__ == "__main__":
        main(sys.argv[1:])
''')


def merge_by_concatenating(parts, directory):  # a Parts.merge: the parts' out.txt in one; False if asked
    outs = [json.loads((p / "out.txt").read_text()) for p in parts]
    if any("--refuse" in o["argv"] for o in outs):
        return False
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "out.txt").write_text(json.dumps({"parts": [o["argv"] for o in outs], "merged": True}))
    return True


@pytest.fixture(scope="module", autouse=True)
def local_ray():
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers cannot import a test module
    ray.init(num_cpus=2, include_dashboard=False, object_store_memory=100 * 2**20)
    yield
    ray.shutdown()


@pytest.fixture
def stages(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "recipes").mkdir()
    (tmp_path / "recipes" / "toy.py").write_text(RECIPE)
    run = Run.start("pipe", RunConfig, ["--name", "p", "--seed", "5", "--no-progress"])
    return RayStages(run, tmp_path / "recipes", timings_path=run.dir / "timings.csv")


def out(tmp_path, name):
    return json.loads((tmp_path / "runs" / "toy" / name / "out.txt").read_text())


def test_stages_run_side_by_side_after_the_stages_their_arguments_name(stages, tmp_path):
    with stages.queued():
        a = stages.run("toy", "a", "out.txt", ["--sleep", "2"])
        assert not (a / "out.txt").exists()  # submitted, not run: run() returns at once
        b = stages.run("toy", "b", "out.txt", ["--sleep", "2"])  # beside a (2 CPUs)
        c = stages.run("toy", "c", "out.txt", ["--input", str(a)])  # after a
        d = stages.submit("toy", "d", "out.txt", [], after=[c])  # after c, named by `after`
        assert stages.wait(c) == c and (c / "out.txt").exists()
    assert out(tmp_path, "c")["start"] >= out(tmp_path, "a")["end"]
    assert out(tmp_path, "d")["start"] >= out(tmp_path, "c")["end"]
    assert out(tmp_path, "b")["start"] < out(tmp_path, "a")["end"]  # side by side on the 2 CPUs
    # the common options, as Stages passes them (progress bars off: the output goes to a log)
    argv = out(tmp_path, "c")["argv"]
    assert argv[:8] == ["--name", "c", "--root", "runs", "--seed", "5", "--threads", "1"] and "--no-progress" in argv
    assert "toy c ran" in (stages.pipeline.dir / "c.log").read_text()
    assert set(stages.timings) == {"toy/a", "toy/b", "toy/c", "toy/d"}


def test_finished_stages_are_skipped_and_an_interrupted_one_resumes(stages, tmp_path, capsys):
    with stages.queued():
        stages.run("toy", "a", "out.txt", [])
        stages.run("toy", "i", "out.txt", ["--interrupt"])
    with stages.queued():
        stages.run("toy", "a", "out.txt", ["--x"])
        stages.run("toy", "i", "out.txt", [])
    assert "toy: runs/toy/a/out.txt exists, skipped" in capsys.readouterr().out
    assert "--x" not in out(tmp_path, "a")["argv"] and "--resume" in out(tmp_path, "i")["argv"]


def test_a_failed_stage_is_reported_with_its_log_and_the_others_go_on(stages, tmp_path):
    with pytest.raises(RuntimeError, match="2 stage") as err:
        with stages.queued():
            bad = stages.run("toy", "bad", "out.txt", ["--fail"])
            stages.run("toy", "after-bad", "out.txt", ["--input", str(bad)])
            stages.run("toy", "fine", "out.txt", ["--sleep", "1"])
    text = str(err.value)
    assert f"toy/bad: failed (exit code 3); see {(stages.pipeline.dir / 'bad.log').resolve()}" in text
    assert "toy/after-bad: not run: it needs toy/bad, which failed" in text
    assert (tmp_path / "runs" / "toy" / "fine" / "out.txt").exists()
    assert "toy bad ran" in (stages.pipeline.dir / "bad.log").read_text()
    with pytest.raises(RuntimeError, match="toy/bad failed"):
        stages.wait(bad)


def test_parts_run_side_by_side_and_are_merged_or_the_stage_runs_whole(stages, tmp_path):
    parts = Parts(args=(("--part", "0"), ("--part", "1")), merge=merge_by_concatenating)
    with stages.queued():
        merged = stages.run("toy", "m", "out.txt", [], parts=parts)
        whole = stages.run("toy", "w", "out.txt", ["--refuse"], parts=parts)
    assert json.loads((merged / "out.txt").read_text())["merged"]
    assert [p[-2:] for p in json.loads((merged / "out.txt").read_text())["parts"]] == [["--part", "0"], ["--part", "1"]]
    assert "--part" not in json.loads((whole / "out.txt").read_text())["argv"]  # refused: run whole
    assert "2 parts cannot stand for it: run whole" in (stages.pipeline.dir / "w.log").read_text()


def test_make_stages_picks_ray_by_the_flags(tmp_path, monkeypatch):
    from dataclasses import dataclass

    @dataclass
    class Cfg(RayConfig, RunConfig):
        pass

    monkeypatch.chdir(tmp_path)
    run = Run.start("pipe", Cfg, ["--name", "q", "--ray", "--no-progress"])
    assert isinstance(make_stages(run, tmp_path), RayStages)
    run = Run.start("pipe", Cfg, ["--name", "r", "--no-progress"])
    assert type(make_stages(run, tmp_path)).__name__ == "Stages"
    with pytest.raises(SystemExit):
        Run.start("pipe", Cfg, ["--name", "s", "--eval-chunk", "-1"])
