"""trakdis.utils.stages: recipes run as the stages of a pipeline, skipped, resumed, in the background."""
import json
import sys
import textwrap

import pandas as pd
import pytest

from trakdis.utils.run import Run, RunConfig
from trakdis.utils.stages import Stages, import_recipe

# A recipe script: records its argv, writes out.txt unless --fail, exits non-zero with --fail.
RECIPE = textwrap.dedent('''
    import json, sys
    from pathlib import Path

    def main(argv):
        name, root = argv[argv.index("--name") + 1], argv[argv.index("--root") + 1]
        directory = Path(root) / "toy" / name
        directory.mkdir(parents=True, exist_ok=True)
        calls = directory / "calls.json"
        seen = json.loads(calls.read_text()) if calls.exists() else []
        calls.write_text(json.dumps([*seen, argv]))
        if "--fail" in argv:
            raise SystemExit(3)
        if "--interrupt" not in argv:
            (directory / "out.txt").write_text("done")

    if __name__ == "__main__":
        main(sys.argv[1:])
''')


@pytest.fixture
def stages(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "recipes").mkdir()
    (tmp_path / "recipes" / "toy.py").write_text(RECIPE)
    run = Run.start("pipe", RunConfig, ["--name", "p", "--seed", "5", "--no-progress"])
    return Stages(run, tmp_path / "recipes", timings_path=run.dir / "timings.csv")


def calls(tmp_path, name):
    import json

    return json.loads((tmp_path / "runs" / "toy" / name / "calls.json").read_text())


def test_a_recipe_is_imported_once_and_its_main_runs_the_stage(stages, tmp_path):
    module = stages.recipe("toy")
    assert stages.recipe("toy") is module and callable(module.main)
    stages.run("toy", "m", "out.txt", [])
    assert stages.recipe("toy") is module and (tmp_path / "runs" / "toy" / "m" / "out.txt").exists()
    with pytest.raises(FileNotFoundError, match="missing.py"):
        stages.recipe("missing")


def test_a_stage_runs_once_then_is_skipped_and_an_interrupted_one_resumes(stages, tmp_path, capsys):
    directory = stages.run("toy", "a", "out.txt", ["--x", "1"])
    assert directory.resolve() == tmp_path / "runs" / "toy" / "a" and (directory / "out.txt").exists()
    assert calls(tmp_path, "a") == [["--name", "a", "--root", "runs", "--seed", "5", "--threads", "1", "--no-progress",
                                     "--x", "1"]]
    assert stages.run("toy", "a", "out.txt", []) == directory and len(calls(tmp_path, "a")) == 1
    assert "exists, skipped" in capsys.readouterr().out
    stages.run("toy", "b", "out.txt", ["--interrupt"], seed=7)  # killed before its output: a log of it stays
    (tmp_path / "runs" / "toy" / "b" / "log.csv").write_text("step\n")
    stages.run("toy", "b", "out.txt", [])
    first, second = calls(tmp_path, "b")
    assert first[first.index("--seed") + 1] == "7" and "--resume" not in first and "--resume" in second
    timings = pd.read_csv(stages.timings_path)
    assert timings["stage"].tolist() == ["toy/a", "toy/b"]  # the second run of b replaced its row
    again = Stages(stages.pipeline, stages.recipes, timings_path=stages.timings_path)
    assert set(again.timings) == {"toy/a", "toy/b"}  # a resumed pipeline keeps the earlier stages' times


def test_background_stage_waits_and_failures_name_the_log(stages, tmp_path):
    job = stages.run("toy", "bg", "out.txt", [], background=True)
    assert stages.wait(job).resolve() == tmp_path / "runs" / "toy" / "bg" and (job.directory / "out.txt").exists()
    assert "toy/bg (background)" in stages.timings
    bad = stages.run("toy", "bad", "out.txt", ["--fail"], background=True)
    with pytest.raises(RuntimeError, match=r"background stage bad failed \(exit code 3\); see .*bad\.log"):
        stages.wait(bad)


def test_a_background_stage_runs_as_its_script_would(stages, tmp_path):
    (tmp_path / "recipes" / "helper.py").write_text("VALUE = 'sibling'\n")
    (tmp_path / "recipes" / "uses_sibling.py").write_text(
        "import sys\nfrom pathlib import Path\nimport helper\n"
        "if __name__ == '__main__':\n"
        "    out = Path(sys.argv[sys.argv.index('--root') + 1]) / 'uses_sibling' / 'u'\n"
        "    out.mkdir(parents=True)\n"
        "    (out / 'out.txt').write_text(helper.VALUE + ' ' + Path(sys.argv[0]).name)\n")
    job = stages.run("uses_sibling", "u", "out.txt", [], background=True)
    assert (stages.wait(job) / "out.txt").read_text() == "sibling uses_sibling.py"


def test_submitted_stages_run_in_the_background_one_at_a_time_and_are_waited_for(stages, tmp_path):
    (tmp_path / "recipes" / "slow.py").write_text(RECIPE.replace("import json, sys", "import json, sys, time").replace('"toy"', '"slow"')
                                                   .replace("    if \"--fail\"", "    time.sleep(0.5)\n    if \"--fail\""))
    with stages.queued():
        first = stages.submit("slow", "q1", "out.txt", [])
        second = stages.submit("slow", "q2", "out.txt", [], seed=9)
        assert len(stages._running) == 1 and len(stages._queue) == 1  # max_background=1: the second waits
        stages.run("toy", "fg", "out.txt", [])  # a foreground stage meanwhile
    assert (first / "out.txt").exists() and (second / "out.txt").exists()
    assert calls(tmp_path, "fg")
    args = json.loads((tmp_path / "runs" / "slow" / "q2" / "calls.json").read_text())[0]
    assert args[args.index("--seed") + 1] == "9" and "--no-progress" in args
    assert {"slow/q1 (background)", "slow/q2 (background)", "toy/fg"} <= set(stages.timings)
    with stages.queued():
        assert stages.submit("slow", "q1", "out.txt", []) == first  # finished: skipped, nothing started
        assert not stages._running


def test_a_stage_still_queued_is_withdrawn_and_one_started_is_not(stages, tmp_path):
    (tmp_path / "recipes" / "slow.py").write_text(RECIPE.replace("import json, sys", "import json, sys, time")
                                                   .replace('"toy"', '"slow"')
                                                   .replace('    if "--fail"', '    time.sleep(0.5)\n    if "--fail"'))
    with stages.queued():
        first = stages.submit("slow", "w1", "out.txt", [])
        second = stages.submit("slow", "w2", "out.txt", [])
        assert not stages.withdraw("w1") and not stages.withdraw("never-submitted")  # w1 runs already
        assert stages.withdraw("w2") and not stages.withdraw("w2")
    assert (first / "out.txt").exists() and not second.exists()


def test_the_queue_starts_the_next_stage_while_a_foreground_stage_runs(stages, tmp_path):
    (tmp_path / "recipes" / "slow.py").write_text(RECIPE.replace("import json, sys", "import json, sys, time")
                                                   .replace('"toy"', '"slow"')
                                                   .replace("    if \"--fail\"", "    time.sleep(0.3)\n    if \"--fail\""))
    (tmp_path / "recipes" / "nap.py").write_text("import time\n\ndef main(argv):\n    time.sleep(8)\n")
    with stages.queued(poll_seconds=0.1):
        first = stages.submit("slow", "a", "out.txt", [])
        second = stages.submit("slow", "b", "out.txt", [])
        stages.run("nap", "n", "never.txt", [])  # 8 s in the foreground, no stage boundary meanwhile
        assert (first / "out.txt").exists() and (second / "out.txt").exists()  # both ran during the nap


def test_a_failed_submitted_stage_raises_and_stops_the_queue(stages, tmp_path):
    (tmp_path / "recipes" / "sleepy.py").write_text("import time\ntime.sleep(60)\n")
    with pytest.raises(RuntimeError, match=r"background stage bad failed \(exit code 3\)"):
        with stages.queued():
            stages.submit("toy", "bad", "out.txt", ["--fail"])
            stages.submit("toy", "never", "out.txt", [])
    assert not (tmp_path / "runs" / "toy" / "never").exists()  # dropped after the failure
    with pytest.raises(KeyError):
        with stages.queued():
            stages.submit("sleepy", "s", "out.txt", [])
            job = stages._running[0]
            raise KeyError("a foreground stage failed")
    assert job.proc.poll() is not None and not stages._running  # terminated, not left running


def test_import_recipe_names_a_missing_script(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.py"):
        import_recipe(tmp_path / "nope.py")
    module = import_recipe(_write(tmp_path / "r.py", "X = 1\n"))
    assert module.X == 1 and sys.modules[module.__name__] is module


def _write(path, text):
    path.write_text(text)
    return path


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_killed_pipeline_leaves_no_background_stage_running(tmp_path):
    import os
    import signal
    import subprocess
    import time
    from pathlib import Path

    (tmp_path / "recipes").mkdir()
    (tmp_path / "recipes" / "sleepy.py").write_text("import os, time\nprint(os.getpid(), flush=True)\ntime.sleep(60)\n")
    script = tmp_path / "pipe.py"
    script.write_text(textwrap.dedent('''
        import time
        from trakdis.utils.run import Run, RunConfig
        from trakdis.utils.stages import Stages
        run = Run.start("pipe", RunConfig, ["--name", "p", "--no-progress"])
        stages = Stages(run, "recipes")
        stages.run("sleepy", "s", "out.txt", [], background=True)
        time.sleep(60)
    '''))
    parent = subprocess.Popen([sys.executable, str(script)], cwd=tmp_path)
    log = tmp_path / "runs" / "pipe" / "p" / "s.log"
    deadline = time.time() + 60
    while time.time() < deadline and not (log.exists() and log.read_text().strip()):
        time.sleep(0.2)
    child = int(log.read_text().split()[0])
    parent.send_signal(signal.SIGKILL)
    parent.wait()

    def alive(pid):  # a zombie (state Z: dead, not yet reaped by whoever adopted it) counts as dead
        try:
            return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
        except FileNotFoundError:
            return False

    deadline = time.time() + 10
    while time.time() < deadline and alive(child):
        time.sleep(0.1)
    if not alive(child):
        return
    os.kill(child, signal.SIGKILL)
    pytest.fail("the background stage outlived its killed pipeline")
