import json
import numpy as np
import pandas as pd
import pytest
import torch

from trakdis.utils.logger import WideCSVLogger, latest_run_dir, make_run_dir
from trakdis.utils.config import save_config
from dataclasses import dataclass


@dataclass
class C:
    a: int = 1


def test_rows_merge_and_columns(tmp_path):
    log = WideCSVLogger(tmp_path / "log.csv")
    log.log(0, {"train/loss_nll": torch.tensor(1.5)})
    log.log(0, {"eval/normalized_performance": np.float32(0.25)})
    log.log(10, {"train/loss_nll": 0.5})
    log.close()
    frame = pd.read_csv(tmp_path / "log.csv")
    assert list(frame.columns) == ["step", "train/loss_nll", "eval/normalized_performance"]
    assert frame["step"].tolist() == [0, 10]
    assert frame["eval/normalized_performance"].iloc[0] == pytest.approx(0.25)
    assert np.isnan(frame["eval/normalized_performance"].iloc[1])
    assert log.last("train/loss_nll") == 0.5


def test_resume_truncates_and_appends(tmp_path):
    p = tmp_path / "log.csv"
    log = WideCSVLogger(p)
    for s in range(5):
        log.log(s, {"train/x": s})
    log.close()
    with pytest.raises(FileExistsError):
        WideCSVLogger(p)
    log = WideCSVLogger(p, resume=True, truncate_after=2)  # checkpoint was at step 2
    log.log(3, {"train/x": 30, "eval/y": 1})
    log.close()
    frame = pd.read_csv(p)
    assert frame["step"].tolist() == [0, 1, 2, 3]
    assert frame["train/x"].tolist() == [0, 1, 2, 30]


def test_non_scalar_metric_named(tmp_path):
    log = WideCSVLogger(tmp_path / "log.csv")
    with pytest.raises(ValueError, match="train/vec"):
        log.log(0, {"train/vec": torch.ones(3)})


def test_run_dirs(tmp_path):
    run = make_run_dir("online_dt", name="a", root=tmp_path)
    assert run == tmp_path / "online_dt" / "a" and run.is_dir()
    save_config(C(), run / "config.json")
    (run / "log.csv").write_text("step\n")
    with pytest.raises(FileExistsError, match="--resume"):
        make_run_dir("online_dt", name="a", root=tmp_path)
    assert make_run_dir("online_dt", name="a", root=tmp_path, resume=True) == run
    assert make_run_dir("online_dt", root=tmp_path, resume=True) == run
    assert latest_run_dir(tmp_path, "online_dt") == run
    with pytest.raises(FileNotFoundError, match="distill"):
        make_run_dir("distill", root=tmp_path, resume=True)
    auto = make_run_dir("online_dt", root=tmp_path)
    auto2 = make_run_dir("online_dt", root=tmp_path)
    assert auto != auto2 and auto.parent == run.parent


def test_latest_run_file(tmp_path):
    import os
    from pathlib import Path

    from trakdis.utils.logger import latest_run_file

    assert latest_run_file("some/policy.pt", tmp_path, "online_dt", "policy.pt", flag="--teacher") == \
        Path("some/policy.pt")
    with pytest.raises(FileNotFoundError, match=r"run recipes/online_dt.py first or pass --teacher PATH"):
        latest_run_file("latest", tmp_path, "online_dt", "policy.pt", flag="--teacher")
    for i, name in enumerate(["a", "b"]):
        run = tmp_path / "online_dt" / name
        run.mkdir(parents=True)
        (run / "config.json").write_text("{}")
        (run / "policy.pt").write_text("")
        os.utime(run, (1000 + i, 1000 + i))
    assert latest_run_file("latest", tmp_path, "online_dt", "policy.pt", flag="--teacher") == \
        tmp_path / "online_dt" / "b" / "policy.pt"


def test_wide_csv_logger_is_a_torchrl_logger(tmp_path):
    from tensordict import TensorDict
    from torchrl.record.loggers import Logger

    def torchrl_style(logger: Logger) -> None:  # code written against TorchRL's interface only
        logger.log_scalar("train/reward", 1.5, step=3)
        logger.log_metrics({"train/loss": torch.tensor(0.25), "eval/score": np.float32(0.5)}, step=3)
        logger.log_metrics(TensorDict({"a": {"b": torch.tensor(7)}}, []), step=5)
        logger.log_scalar("count", 10.0)  # no step: the n-th value of a name goes to step n
        logger.log_scalar("count", 11.0)

    log = WideCSVLogger(tmp_path / "run" / "log.csv")
    assert isinstance(log, Logger) and log.exp_name == "run" and "log.csv" in repr(log)
    torchrl_style(log)
    log.log(3, {"train/extra": 2})
    log.close()
    frame = pd.read_csv(tmp_path / "run" / "log.csv")
    assert list(frame.columns) == ["step", "train/reward", "train/loss", "eval/score", "a/b", "count", "train/extra"]
    assert frame["step"].tolist() == [0, 1, 3, 5]
    row = frame.set_index("step").loc[3]
    assert (row["train/reward"], row["train/loss"], row["eval/score"], row["train/extra"]) == (1.5, 0.25, 0.5, 2)
    assert frame.set_index("step")["count"].loc[[0, 1]].tolist() == [10.0, 11.0]
    assert frame.set_index("step").loc[5, "a/b"] == 7

    log.log_hparams({"lr": 0.1, "nested": {"a": None}})
    assert json.loads((tmp_path / "run" / "hparams.json").read_text()) == {"lr": 0.1, "nested": {"a": None}}
    with pytest.raises(NotImplementedError, match="scalars only"):
        log.log_video("rollout", torch.zeros(1, 2, 3, 4, 4))
    with pytest.raises(NotImplementedError, match="scalars only"):
        log.log_histogram("w", torch.zeros(3))
    assert log.state_dict()["exp_name"] == "run"


@pytest.mark.parametrize("kind", ["tensorboard", "wandb"])
def test_missing_logger_backend_names_the_package_and_extra(monkeypatch, kind):
    from trakdis.utils import logger as logger_module

    monkeypatch.setattr(logger_module, "_has_package", lambda name: False)
    logger_module.check_logger_backend("csv")  # needs nothing
    with pytest.raises(ModuleNotFoundError, match=rf"--logger {kind} needs the '{kind}' package.*trakdis\[{kind}\]"):
        logger_module.check_logger_backend(kind)
    with pytest.raises(ValueError, match="unknown logger"):
        logger_module.check_logger_backend("mlflow")
