"""The recipes' update loop: log, checkpoint and --stop-after cadence."""
from dataclasses import dataclass

import torch
from tensordict import TensorDict

from quadratic_loss import Quadratic
from trakdis.optim import Updater
from trakdis.training import eval_batches, shuffled_batches, train_updates
from trakdis.utils.run import Run, RunConfig, RunState


@dataclass
class Cfg(RunConfig):
    pass




def loop(tmp_path, *argv, total=7):
    run = Run.start("toy", Cfg, ["--root", str(tmp_path), "--name", "a", "--no-progress", *argv])
    updater = Updater(Quadratic(), optimizer="adam", lr=1e-2)
    state = RunState(run, {"updates": 0}, step_key="updates", updater=updater)
    state.load()
    logged, evaluated = [], []
    done = train_updates(run, updater, TensorDict, state=state, total=total, log_every=3, checkpoint_every=2,
                         log_extra={"phase": 0}, on_log=logged.append, on_update=evaluated.append)
    return run, state, done, logged, evaluated


def test_cadence_stop_and_resume(tmp_path):
    run, state, done, logged, evaluated = loop(tmp_path)
    assert done and state["updates"] == 7 and logged == [3, 6, 7] and evaluated == list(range(1, 8))
    frame = run.logger.frame()
    assert frame["step"].tolist() == [3, 6, 7] and (frame["phase"] == 0).all() and "train/loss_q" in frame
    assert run.resume_state() is None
    run, state, done, logged, _ = loop(tmp_path / "b", "--stop-after", "4")
    assert not done and state["updates"] == 4 and logged == [3]
    run, state, done, logged, _ = loop(tmp_path / "b", "--resume")
    assert done and state.resuming and state["updates"] == 7 and logged == [6, 7]
    assert state.objects["updater"].updates == 7


def test_shuffled_batches_cover_the_data_once_in_a_seeded_order():
    data = TensorDict({"x": torch.arange(10)}, batch_size=[10])
    torch.manual_seed(0)
    batches = [b["x"] for b in shuffled_batches(data, 4, desc="test")]
    assert [len(b) for b in batches] == [4, 4, 2] and sorted(torch.cat(batches).tolist()) == list(range(10))
    torch.manual_seed(0)
    assert torch.equal(torch.cat(batches), data["x"][torch.randperm(10)])  # the order drawn first


def test_eval_batches_in_eval_mode_without_gradients():
    data = TensorDict({"x": torch.arange(5.0)}, batch_size=[5])
    module = torch.nn.Dropout(0.5).train()
    seen = []

    def fn(batch):
        seen.append((module.training, torch.is_grad_enabled()))
        return batch["x"].sum()

    assert [float(v) for v in eval_batches(module, data, 2, fn)] == [1.0, 5.0, 4.0]
    assert seen == [(False, False)] * 3 and module.training  # its mode restored
    module.eval()
    assert torch.equal(torch.cat(eval_batches(module, TensorDict({"x": torch.ones(3)}, [3]), 2, lambda b: module(b["x"]))),
                       torch.ones(3)) and not module.training
