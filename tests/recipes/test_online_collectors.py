"""The online phase of online_dt.py on a MultiSyncCollector of 2 processes (--collector multi_sync):
its rollouts are episodes that enter the buffer as with one process."""
import json

import pandas as pd

from trakdis.utils.checkpoint import read_checkpoint

from .conftest import online_dt_args, run_recipe


def test_online_dt_rollouts_on_a_2_process_collector(workdir, dataset, teacher):
    # no evaluation (--eval-episodes 0; run_episodes on multi_sync: tests/evaluation/test_collectors.py):
    # each multi_sync call starts its processes (docs/scaling.md)
    out = run_recipe(workdir, "online_dt", *online_dt_args("multi", "--collector", "multi_sync", "--num-envs", 2,
                                                           "--eval-episodes", 0, "--online-rounds", 1))
    run_dir = workdir / "runs" / "online_dt" / "multi"
    assert json.loads((run_dir / "config.json").read_text())["collector"] == "multi_sync"
    assert "round 1/1: rollout normalized performance" in out.stdout and "2 envs" in out.stdout
    ck = read_checkpoint(run_dir / "checkpoint.pt")
    assert ck["counters"]["rounds"] == 1 and ck["buffer"]["num_online_added"] == 2  # 1 round x 2 episodes
    frame = pd.read_csv(run_dir / "log.csv")
    assert frame["online/normalized_performance"].notna().sum() == 1
    # as with one process (the teacher fixture, up to its first round): the same update steps logged;
    # the scores are not compared: the DT's forward on one env per process rounds differently from
    # its batched forward, and the cloth dynamics amplify that (docs/scaling.md)
    ref = pd.read_csv(teacher / "log.csv")
    assert frame["step"].tolist() == ref.loc[(ref["step"] > 0) & (ref["step"] <= 6 + 3), "step"].tolist()
    assert frame["online/kept"].dropna().tolist() == [2] and ck["buffer"]["online"].sum() == 2  # DAgger: every rollout
    assert frame["online/normalized_performance"].dropna().abs().lt(10).all()
    assert not [c for c in frame.columns if c.startswith("eval")]
