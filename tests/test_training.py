"""The recipes' update loops: log, checkpoint and --stop-after cadence, rounds of rollouts and updates (the selection's
snapshots between them), an Online DT round's rollouts, DAgger's mixture, a buffer's batches, epochs of minibatches and
validation passes, and the choice of the snapshot kept and its options."""
from dataclasses import dataclass, field

import pytest
import torch
from tensordict import TensorDict

from quadratic_loss import Quadratic
from trakdis.optim import Updater
from trakdis.training import (OnlineRollouts, SelectionConfig, SnapshotSelection, buffer_batches, eval_batches,
                              mixture_shares, run_updates, shuffled_batches, train_epoch, train_rounds, train_updates)
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


def rounds_loop(tmp_path, *argv, rounds=4, stop_key=None):
    """Rounds of 2 updates; each round's "rollout" is recorded and logged, an evaluation every 2 rounds."""
    run = Run.start("toy", Cfg, ["--root", str(tmp_path), "--name", "a", "--no-progress", *argv])
    updater = Updater(Quadratic(), optimizer="adam", lr=1e-2)
    state = RunState(run, {"updates": 0, "rounds": 0}, step_key="updates", updater=updater)
    state.load()
    rolled, evaluated = [], []

    def roll_out(r):
        rolled.append((r, state["updates"]))
        return {"rollout/score": float(r), "round": r + 1}, f"rollout {r}"

    done = train_rounds(run, updater, TensorDict, state=state, rounds=rounds, updates_per_round=2, roll_out=roll_out,
                        evaluate=evaluated.append, eval_every=2, log_extra={"phase": 1}, loss_key="train/loss_q",
                        phases=PhaseTimer(), phase="round updates", stop_key=stop_key)
    return run, state, done, rolled, evaluated


def test_rounds_roll_out_then_update_log_evaluate_and_resume(tmp_path, capsys):
    run, state, done, rolled, evaluated = rounds_loop(tmp_path)
    assert done and state["rounds"] == 4 and state["updates"] == 8 and state.objects["updater"].updates == 8
    assert rolled == [(0, 0), (1, 2), (2, 4), (3, 6)]  # each round rolls out before its updates
    assert evaluated == [2]  # every 2 rounds, but not after the last (the recipe's final evaluation follows)
    frame = run.logger.frame()
    assert frame["step"].tolist() == [2, 4, 6, 8] and frame["round"].tolist() == [1, 2, 3, 4]
    assert frame["rollout/score"].tolist() == [0, 1, 2, 3] and (frame["phase"] == 1).all() and "train/loss_q" in frame
    assert "round 2/4: rollout 1, loss_q " in capsys.readouterr().out
    # --stop-after counts rounds (or the stop_key): checkpoint after the round, then continue with --resume
    run, state, done, rolled, _ = rounds_loop(tmp_path / "b", "--stop-after", "1")
    assert not done and state["rounds"] == 1 and rolled == [(0, 0)]
    run, state, done, rolled, _ = rounds_loop(tmp_path / "b", "--resume")
    assert done and rolled == [(1, 2), (2, 4), (3, 6)] and state.objects["updater"].updates == 8
    run, state, done, rolled, _ = rounds_loop(tmp_path / "c", "--stop-after", "4", stop_key="updates")
    assert not done and state["updates"] == 4 and "stopping after update 4" in capsys.readouterr().out


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


def test_online_rollouts_play_the_episodes_into_the_buffer_and_book_them():
    """One Online DT round's data: the handle's episodes (seeded), added to the buffer unless the
    control; their scores and the buffer's state for the log, one line for the printout."""
    import sys
    from pathlib import Path

    from tensordict.nn import TensorDictModule

    from trakdis.training import online_rollouts

    sys.path.insert(0, str(Path(__file__).parent / "evaluation"))
    from walk_env import Walk
    from torchrl.envs import StepCounter, TransformedEnv

    class Handle:  # a PolicyHandle's acting policy: always +0.5
        def make_policy(self, seed=None):
            return TensorDictModule(lambda s: torch.full_like(s, 0.5), in_keys=["state"], out_keys=["action"])

    class Buffer:
        online_fraction, added, keys = 0.25, [], ("state", "action")

        def add_episodes(self, episodes, keys):
            self.added.append((len(list(episodes)), keys))
            return self.added[-1][0]  # all kept

    env, buffer, phases = TransformedEnv(Walk(), StepCounter()), Buffer(), PhaseTimer()
    metrics, line = online_rollouts(env, Handle(), buffer, 3, horizon=4, seed=1, phases=phases, workers=1)
    assert buffer.added == [(3, ("state", "action"))] and metrics["online/kept"] == 3
    assert metrics["online/normalized_performance"] == pytest.approx(2.0)  # 4 steps of +0.5 from 0
    assert metrics["online/return"] == pytest.approx(-(0.5 + 1.0 + 1.5 + 2.0))
    assert metrics["online/buffer_online_fraction"] == 0.25 and phases.records["online rollouts"]["episodes"] == 3
    assert line.startswith("rollout normalized performance 2.000, return -5.000 (3 kept; buffer 25% online; 3 episodes")
    metrics, _ = online_rollouts(env, Handle(), buffer, 2, horizon=4, seed=1, add=False)  # the offline-only control
    assert buffer.added[-1] == (0, ("state", "action")) and metrics["online/kept"] == 0


def test_snapshot_selection_keeps_a_snapshot_only_if_measurably_better(tmp_path):
    """A later snapshot replaces the kept one only if its paired gain exceeds ``margin`` standard
    errors (a tie or a noisy gain keeps the earlier one); no step is scored twice; the record and the
    kept weights survive a checkpoint."""
    module = torch.nn.Linear(2, 1)
    scores = {0: [0.5, 0.5, 0.5, 0.5], 1: [0.9, 0.1, 0.9, 0.1],  # mean 0.5: a tie, kept out
              2: [0.7, 0.6, 0.8, 0.7], 3: [1.0, 0.2, 1.0, 0.6],  # +0.2 +- 0.04: kept; +0.0 against it: not
              4: [0.8, 0.7, 0.9, 0.7]}  # +0.075 +- 0.025 over step 2: kept with margin 1, not with margin 4
    calls = []

    def score(step):
        calls.append(step)
        return scores[step]

    run = Run.start("toy", Cfg, ["--root", str(tmp_path), "--name", "sel", "--no-progress"])
    state = RunState(run, {"updates": 0}, step_key="updates")
    strict = SnapshotSelection(module, lambda step: scores[step], {}, margin=4.0)
    selection = SnapshotSelection(module, score, state)
    weights = {}
    for step in range(4):
        with torch.no_grad():
            module.weight.fill_(float(step))
        weights[step] = module.weight.clone()
        assert selection.consider(step) == pytest.approx(sum(scores[step]) / 4)
        strict.consider(step)
    assert selection.consider(2) == pytest.approx(0.7) and calls == [0, 1, 2, 3]  # scored once
    assert selection.record["best"] == strict.record["best"] == 2
    state["updates"] = 3
    state.save()
    # a resumed run: the record comes back from the checkpoint, the kept weights with it
    resumed = RunState(Run.start("toy", Cfg, ["--root", str(tmp_path), "--name", "sel", "--resume", "--no-progress"]),
                       {"updates": 0}, step_key="updates")
    fresh = torch.nn.Linear(2, 1)
    again = SnapshotSelection(fresh, lambda step: pytest.fail("rescored"), resumed)
    assert again.consider(3) == pytest.approx(0.7) and again.restore() == 2
    assert torch.equal(fresh.weight, weights[2])
    with torch.no_grad():
        module.weight.fill_(4.0)
    selection.consider(4), strict.consider(4)
    assert strict.record["best"] == 2 and selection.restore() == 4 and torch.equal(module.weight, torch.full((1, 2), 4.0))
    assert list(selection.means()) == [0, 1, 2, 3, 4]


def test_snapshot_selection_of_nothing_keeps_the_module():
    module = torch.nn.Linear(2, 1)
    before = module.weight.clone()
    assert SnapshotSelection(module, lambda step: [0.0], {}).restore() is None
    assert torch.equal(module.weight, before)


def test_snapshot_selection_rounds_and_episodes():
    """on_episodes scores the handle with the protocol reseeded past its own seed, at the run's update counter;
    after_round scores every `every` rounds; finish scores the last, restores the kept one and logs it."""
    import numpy as np

    @dataclass
    class Protocol:  # the part of EvalProtocol that the selection uses
        seed: int = 7
        episodes: int = 100
        calls: list = field(default_factory=list)

        def run(self, run, handle, env, **kw):
            self.calls.append((self.seed, self.episodes, env, kw))
            value = {0: 0.0, 2: 1.0, 4: 0.5, 5: 0.2}[int(handle.actor.weight[0, 0])]
            scores = np.full(self.episodes, value) + np.arange(self.episodes) * 0.01
            return type("Res", (), {"final_performance": scores})

    module = torch.nn.Linear(2, 1)
    handle = type("Handle", (), {"actor": module})()
    protocol, state, lines = Protocol(), {"updates": 0}, []
    with pytest.raises(ValueError, match="every"):
        SnapshotSelection(module, lambda step: [0.0], {}, every=0)
    selection = SnapshotSelection.on_episodes(None, handle, protocol, "env", state, episodes=3, every=2, name="teacher")
    for r in range(6):
        with torch.no_grad():
            module.weight.fill_(float(r))
        state["updates"] = 10 * r
        if r == 0:
            selection.consider(0)
        elif r < 5:
            selection.after_round(r)
    assert selection.finish(5, lines.append) == 2  # rounds 0, 2, 4 and the last (5) scored; round 2 the best
    calls = protocol.calls  # the copy's (dataclasses.replace shares the list)
    assert protocol.seed == 7 and {c[:3] for c in calls} == {(10_007, 3, "env")}
    assert [c[3]["step"] for c in calls] == [0, 20, 40, 50] and calls[1][3]["tag"] == "selection: teacher after round 2"
    assert all(c[3]["split"] == "train" and c[3]["prefix"] == "selection" and c[3]["keep_mode"] is module
               for c in calls)
    assert torch.equal(module.weight, torch.full((1, 2), 2.0))
    assert lines == ["selection: the teacher after round 2 is kept (train-split scores by round: 0 0.010, 2 1.010, "
                     "4 0.510, 5 0.210)"]
    assert selection.summary() == {"selected_round": 2, "selection_scores": selection.means()}


def test_rounds_score_the_selection_after_every_round_but_the_last_before_the_evaluation(tmp_path):
    """train_rounds' selection: its after_round(r) after each round but the last, before evaluate(r) (every
    eval_every rounds); the last round's snapshot is the selection's finish, the recipe's."""
    run = Run.start("toy", Cfg, ["--root", str(tmp_path), "--name", "a", "--no-progress"])
    updater = Updater(Quadratic(), optimizer="adam", lr=1e-2)
    state = RunState(run, {"updates": 0, "rounds": 0}, step_key="updates", updater=updater)
    calls = []

    class Selection:
        def after_round(self, r):
            calls.append(("select", r))

    assert train_rounds(run, updater, TensorDict, state=state, rounds=4, updates_per_round=1,
                        roll_out=lambda r: ({}, ""), selection=Selection(), evaluate=lambda r: calls.append(("eval", r)),
                        eval_every=2, loss_key="train/loss_q")
    assert calls == [("select", 1), ("select", 2), ("eval", 2), ("select", 3)]


def test_snapshot_selection_without_an_env_scores_nothing_and_keeps_the_last_round():
    """on_episodes without an env (no selection episodes, or no rounds): inactive; it scores no snapshot, finish
    keeps the last round's weights and logs nothing, and its record and summary are the empty ones."""
    module = torch.nn.Linear(2, 1)
    before = module.weight.clone()
    state, lines = {"updates": 0}, []
    handle = type("Handle", (), {"actor": module})()
    selection = SnapshotSelection.on_episodes(None, handle, "protocol, never run", None, state, episodes=30, every=2)
    assert not selection.active and selection.consider(0) is None
    selection.after_round(2)
    assert selection.finish(5, lines.append) == 5 and lines == [] and torch.equal(module.weight, before)
    assert state["selection"] == {"scores": {}, "best": None, "state_dict": None}
    assert selection.summary() == {"selected_round": None, "selection_scores": {}}
    assert SnapshotSelection(module, lambda step: [0.0], {}).active


def test_selection_config_checks_its_options_and_resolves_the_tasks_episodes():
    from trakdis.envs import task_defaults

    assert (SelectionConfig().select_episodes, SelectionConfig().select_every) == (0, 4)
    for bad in ({"select_every": 0}, {"select_episodes": -1}, {"select_margin": -1.0}):
        with pytest.raises(ValueError, match=f"--{next(iter(bad)).replace('_', '-')}"):
            SelectionConfig(**bad)
    assert SelectionConfig(select_episodes=None).resolved_select_episodes("ClothFoldDiagonalPinned") == \
        task_defaults("ClothFoldDiagonalPinned").select_episodes
    assert SelectionConfig(select_episodes=3).resolved_select_episodes("ClothFold") == 3


def test_online_rollouts_round_by_round(monkeypatch):
    """OnlineRollouts: round r plays online_rollouts with its arguments, reseeded with seed + 1000 (r + 1),
    ``online/round`` = r + 1 beside the round's metrics."""
    import trakdis.training as training

    calls = []

    def fake(env, handle, buffer, episodes, **kwargs):
        calls.append((env, handle, buffer, episodes, kwargs))
        return {"online/kept": episodes, **kwargs["extra"]}, "line"

    monkeypatch.setattr(training, "online_rollouts", fake)
    label = object()
    roll_out = OnlineRollouts("env", "handle", "buffer", 3, horizon=6, seed=5, policy_seed=5, deterministic=False,
                              add=False, collector="multi_sync", workers=2, label=label)
    assert roll_out(0) == ({"online/kept": 3, "online/round": 1}, "line")
    roll_out(2)
    assert [c[4]["seed"] for c in calls] == [1005, 3005] and calls[1][4]["extra"] == {"online/round": 3}
    assert calls[0][:4] == ("env", "handle", "buffer", 3)
    assert {k: calls[0][4][k] for k in ("horizon", "policy_seed", "deterministic", "add", "collector", "workers",
                                        "label", "phases")} == {
        "horizon": 6, "policy_seed": 5, "deterministic": False, "add": False, "collector": "multi_sync", "workers": 2,
        "label": label, "phases": None}


def test_buffer_batches_sample_the_batch_size_on_the_device():
    class Buffer:
        def sample(self, n):
            return TensorDict({"x": torch.arange(n)}, batch_size=[n])

    sample = buffer_batches(Buffer(), 5, "cpu")
    batch = sample()
    assert batch.batch_size == (5,) and batch.device == torch.device("cpu") and torch.equal(batch["x"], torch.arange(5))
