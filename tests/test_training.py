"""The recipes' update loops: log, checkpoint and --stop-after cadence, a round's updates, DAgger's
mixture, epochs of minibatches and validation passes."""
from dataclasses import dataclass

import pytest
import torch
from tensordict import TensorDict

from quadratic_loss import Quadratic
from trakdis.optim import Updater
from trakdis.training import (eval_batches, mixture_shares, run_updates, shuffled_batches, train_candidates,
                              train_epoch, train_updates)
from trakdis.utils.checkpoint import load_checkpoint, save_checkpoint
from trakdis.utils.phases import PhaseTimer
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


def candidates_loop(tmp_path, *argv, candidates=3, total=4):
    """Candidate k starts from w = (k + 1) * [1, 1] (candidate 0: the updater as built) and scores
    -|w| after its updates, read back from the policy file it saved: the smallest w wins."""
    run = Run.start("toy", Cfg, ["--root", str(tmp_path), "--name", "a", "--no-progress", *argv])
    updater = Updater(Quadratic(), optimizer="adam", lr=0.05)
    state = RunState(run, {"updates": 0}, step_key="updates", updater=updater)
    state.load()
    scored = []

    def fresh_state(k):
        fresh = Updater(Quadratic(), optimizer="adam", lr=0.05)
        fresh.loss_module.w.data.fill_(k + 1.0)
        return fresh.state_dict()

    def score(path, k):
        scored.append(k)
        w = load_checkpoint(path)["w"]
        return lambda: [-float(w.norm()), -float(w.norm())]

    done = train_candidates(run, updater, TensorDict, state=state, phases=PhaseTimer(), candidates=candidates,
                            total=total, fresh_state=fresh_state, score=score, log_every=2, checkpoint_every=2,
                            save_policy=lambda path: save_checkpoint(path, {"w": updater.loss_module.w.detach().clone()}),
                            log_extra={"phase": 0})
    return run, state, done, scored


def test_candidates_keep_the_best_score_and_resume(tmp_path):
    run, state, done, scored = candidates_loop(tmp_path, candidates=3)
    assert done and scored == [0, 1, 2] and state["candidate"] == 3 and state["updates"] == 12
    assert state["candidate_kept"] == 0 and state["candidate_scores"][0] == max(state["candidate_scores"])
    kept = load_checkpoint(run.dir / "candidates" / "policy_0.pt")["w"]
    assert torch.equal(state.objects["updater"].loss_module.w.detach(), kept)  # the kept one, not the last
    frame = run.logger.frame()
    assert frame["step"].tolist() == [2, 4, 6, 8, 10, 12] and frame["candidate"].tolist() == [0, 0, 1, 1, 2, 2]
    # stopped inside candidate 1 (candidate 0's scoring lost with the process): scored again on resume
    run, state, done, scored = candidates_loop(tmp_path / "b", "--stop-after", "6")
    assert not done and scored == [0] and state["candidate"] == 1
    run, state, done, scored = candidates_loop(tmp_path / "b", "--resume")
    assert done and scored == [0, 1, 2] and state["candidate_kept"] == 0
    assert torch.equal(state.objects["updater"].loss_module.w.detach(), kept)
    # one candidate: train_updates, no files
    run, state, done, scored = candidates_loop(tmp_path / "c", candidates=1)
    assert done and scored == [] and state["updates"] == 4 and not (run.dir / "candidates").exists()


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


def test_run_updates_steps_n_times_and_returns_the_mean_metrics():
    updater = Updater(Quadratic(), optimizer="adam", lr=1e-2)
    sampled = []
    metrics = run_updates(updater, lambda: sampled.append(1) or TensorDict(), 3, desc="round 1")
    assert len(sampled) == 3 and updater.updates == 3
    assert set(metrics) >= {"train/loss_q"} and 0 < metrics["train/loss_q"] < 2.0  # the mean over 3 steps, from 2


def test_mixture_shares_decay_from_all_teacher_to_all_student():
    assert [mixture_shares(4, r, 5) for r in range(5)] == [[4, 0], [3, 1], [2, 2], [1, 3], [0, 4]]
    assert mixture_shares(3, 0, 1) == [3, 0]  # a single round: the teacher's
    assert sum(mixture_shares(7, 2, 6)) == 7


def test_train_epoch_weights_each_batch_by_its_size():
    class Mean(torch.nn.Module):  # loss: (w - x)^2 averaged over the batch; metric: the batch's mean x
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.zeros(()))

        def forward(self, batch):
            return TensorDict(loss=((self.w - batch["x"]) ** 2).mean(), x=batch["x"].mean())

    module = Mean()
    optim = torch.optim.SGD(module.parameters(), lr=0.1)
    data = TensorDict({"x": torch.arange(5.0)}, [5])
    torch.manual_seed(0)
    out = train_epoch(module, optim, data, 2, loss_key="loss", metrics=("x",), desc="epoch 1")
    assert set(out) == {"x"} and out["x"] == pytest.approx(2.0)  # batches of 2, 2, 1: the mean over the 5 steps
    assert float(module.w) != 0.0  # stepped
