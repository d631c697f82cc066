"""The online phase of online_dt.py on a MultiSyncCollector of 2 processes (--collector multi_sync):
its rollouts are episodes that enter the buffer as with one process."""
import json

import pandas as pd

from trakdis.utils.checkpoint import load_checkpoint

from .conftest import online_dt_args, run_recipe


def test_online_dt_rollouts_on_a_2_process_collector(workdir, dataset, teacher):
    out = run_recipe(workdir, "online_dt", *online_dt_args("multi", "--collector", "multi_sync", "--num-envs", 2))
    run_dir = workdir / "runs" / "online_dt" / "multi"
    assert json.loads((run_dir / "config.json").read_text())["collector"] == "multi_sync"
    assert "round 2/2: rollout normalized performance" in out.stdout and "2 envs" in out.stdout
    ck = load_checkpoint(run_dir / "checkpoint.pt")
    assert ck["counters"]["rounds"] == 2 and ck["buffer"]["num_online_added"] == 4  # 2 rounds x 2 episodes
    frame = pd.read_csv(run_dir / "log.csv")
    assert frame["online/normalized_performance"].notna().sum() == 2
    reference = json.loads((teacher / "config.json").read_text())
    if reference["num_envs"] == 2:  # the teacher fixture: one process, ParallelEnv of 2 workers
        ref = pd.read_csv(teacher / "log.csv")
        ref_ck = load_checkpoint(teacher / "checkpoint.pt")
        assert json.loads((run_dir / "phases.json").read_text())["episodes_simulated"] == 10  # the expert's scores cached
        assert ck["buffer"]["online"].sum() == ref_ck["buffer"]["online"].sum()
        assert frame["online/kept"].dropna().tolist() == ref["online/kept"].dropna().tolist()
        for col in ("online/normalized_performance", "online/return", "eval/normalized_performance"):
            pd.testing.assert_series_equal(frame[col].dropna().reset_index(drop=True),
                                           ref[col].dropna().reset_index(drop=True), check_exact=False, atol=1e-4)
