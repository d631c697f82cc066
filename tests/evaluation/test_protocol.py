"""A run's evaluation protocol: scores logged and printed, paired comparisons, the expert's baseline."""
import numpy as np
import pytest

from trakdis.evaluation import BackgroundEvaluation, EvalProtocol, RunEnvs, compare_scores, log_scores, protocol
from trakdis.policies import load_policy
from trakdis.utils.phases import PhaseTimer


class FakeRun:
    def __init__(self):
        self.rows, self.lines = [], []

    def log(self, step, metrics):
        self.rows.append((step, dict(metrics)))

    def print(self, *args):
        self.lines.append(" ".join(map(str, args)))


def test_log_scores_with_and_without_returns():
    run = FakeRun()
    m = log_scores(run, 3, "eval", "after", [0.5, 0.7], [-1.0, -2.0], detail="2 episodes in 1 s")
    assert m == run.rows[0][1] and run.rows[0][0] == 3
    assert list(m) == ["eval/normalized_performance", "eval/std", "eval/return"] and m["eval/return"] == -1.5
    assert run.lines[0] == ("after: normalized performance 0.600 +- 0.100 (std; standard error 0.100; return -1.500, "
                            "2 eval episodes); 2 episodes in 1 s")
    m = log_scores(run, 4, "eval_teacher", "teacher", [0.5, 0.7], note="; x", extra={"eval_teacher/e": 1.0})
    assert list(m) == ["eval_teacher/normalized_performance", "eval_teacher/std", "eval_teacher/e"]
    assert run.lines[1] == "teacher: normalized performance 0.600 +- 0.100 (2 eval episodes; x)"


def test_compare_scores_pairs_the_same_episodes():
    line, numbers = compare_scores({"expert": 0.8, "offline": 0.5, "online": 0.6, "none": None},
                                   {"offline": [0.4, 0.6], "online": np.array([0.6, 0.6])}, before="offline",
                                   after="online")
    assert numbers["gain"] == pytest.approx(0.1) and numbers["gain_se"] == pytest.approx(0.1)
    assert line == ("expert 0.800, offline 0.500 +- 0.100, online 0.600 +- 0.000; online - offline +0.100 +- 0.100 "
                    "(paired: the same 2 eval episodes)")
    line, numbers = compare_scores({"online": 0.6}, {"offline": None, "online": [0.6, 0.6]}, before="offline",
                                   after="online")
    assert numbers["gain"] is None and numbers["offline_se"] is None and line == "online 0.600 +- 0.000"


def test_run_and_the_experts_cached_baseline(tmp_path):
    evals = EvalProtocol("ClothFoldDiagonalPinned", horizon=3, episodes=2, num_envs=1, seed=10_000)
    expert = load_policy("expert", task=evals.task, horizon=evals.horizon)
    env = expert.make_env(num_envs=1, split="eval")
    try:
        run = FakeRun()
        res = evals.run(run, expert, env, step=7, tag="expert", prefix="x")
        assert len(res.final_performance) == 2 and run.rows[0][0] == 7 and "x/return" in run.rows[0][1]
        assert res.final_performance[0] != res.final_performance[1]  # two configurations
        phases = PhaseTimer()
        scores = evals.expert_baseline(run, env, phases, cache_root=tmp_path, episodes=1)
        assert np.array_equal(scores, res.final_performance[:1])  # the first configuration of the run's
        assert phases.records["expert evaluation"]["episodes"] == 1 and "cached in" in run.lines[-1]
        again = evals.expert_baseline(run, env, PhaseTimer(), cache_root=tmp_path, episodes=1)
        assert np.array_equal(again, scores) and "measured once, cached in" in run.lines[-1]
        assert run.rows[-1] == (0, run.rows[-2][1])  # logged under eval_expert/ at step 0 both times
        assert len(evals.expert_baseline(run, env, PhaseTimer(), cache_root=tmp_path)) == 2  # all: another file
        assert len(list((tmp_path / "expert_scores").glob("*.json"))) == 2
    finally:
        env.close()


def test_background_expert_baseline_is_booked_and_cached(tmp_path):
    evals = EvalProtocol("ClothFoldDiagonalPinned", horizon=3, episodes=1, num_envs=1, seed=10_000)
    run, phases = FakeRun(), PhaseTimer()
    job = evals.expert_baseline(run, None, phases, cache_root=tmp_path, background=True, episodes=5)
    assert isinstance(job, BackgroundEvaluation) and job.num_episodes == 1  # at most the protocol's episodes
    res = evals.finish_background(run, job, phases, "scripted expert", step=0, tag="scripted expert",
                                  prefix="eval_expert")
    assert "evaluation (scripted expert, background)" in phases.background and len(res.final_performance) == 1
    assert "in a background process" in run.lines[-2] and "cached in" in run.lines[-1]
    cached = evals.expert_baseline(run, None, PhaseTimer(), cache_root=tmp_path)
    assert np.array_equal(cached, res.final_performance)


def test_run_snapshot_plays_a_frozen_copy_on_its_own_env_and_closes_it():
    import dataclasses

    import torch
    from tensordict.nn import TensorDictModule
    from torchrl.envs import StepCounter, TransformedEnv

    from walk_env import Walk

    @dataclasses.dataclass
    class WalkHandle:  # what EvalProtocol reads of a PolicyHandle
        encoder: torch.nn.Module | None = None
        actor: torch.nn.Module | None = None
        envs: list = dataclasses.field(default_factory=list)

        @property
        def uses_pixels(self):
            return False

        def make_env(self, **kwargs):
            self.envs.append((kwargs, TransformedEnv(Walk(), StepCounter(max_steps=2)), self.encoder))
            return self.envs[-1][1]

        def make_policy(self, seed=None):
            return TensorDictModule(lambda s: torch.full_like(s, 0.5), in_keys=["state"], out_keys=["action"])

    evals, run = EvalProtocol("ClothFold", horizon=2, episodes=1, num_envs=1), FakeRun()
    for encoder in (None, torch.nn.Linear(1, 1).train()):
        handle = WalkHandle(encoder=encoder, actor=torch.nn.Linear(1, 1).train())
        res = evals.run_snapshot(run, handle, step=4, tag="snap", prefix="eval_t", parallel=True)
        assert res.final_performance.tolist() == [1.0] and run.rows[-1][0] == 4 and "eval_t/std" in run.rows[-1][1]
        kwargs, env, env_encoder = handle.envs[-1]
        assert kwargs == {"num_envs": 1, "split": "eval", "parallel": True} and env.is_closed
        if encoder is None:
            assert env_encoder is None
        else:  # a copy, in eval mode; the model in training keeps its mode
            assert env_encoder is not encoder and not env_encoder.training and encoder.training
        assert handle.actor.training  # the mode of keep_mode (default: the actor) is restored


class FakeJob(BackgroundEvaluation):  # no process: only what the protocol calls
    def __init__(self, name):
        self.name, self.cancelled = name, False

    def done(self):
        return False

    def cancel(self):
        self.cancelled = True


def fake_protocol(monkeypatch, finished):
    from trakdis.evaluation.episodes import EpisodeResults

    evals = EvalProtocol("ClothFold", horizon=3, episodes=2, num_envs=1)

    def results(score):
        return EpisodeResults(final_performance=np.array([score, score]), returns=np.zeros(2), lengths=np.full(2, 3),
                              unstable=np.zeros(2, dtype=bool), episodes=[], seconds=1.0, num_envs=1)

    monkeypatch.setattr(evals, "run", lambda run, handle, env, *, step, tag: results(0.5))
    monkeypatch.setattr(evals, "in_background", lambda spec, phases: FakeJob(str(spec)))

    def finish(run, job, phases, what, *, step, tag, prefix="eval"):
        finished.append((job.name, what, step, prefix))
        return results(0.25)

    monkeypatch.setattr(evals, "finish_background", finish)
    return evals


def test_evaluate_now_or_in_the_background_and_finish_the_pending_latest_first(monkeypatch):
    finished, got = [], []
    evals = fake_protocol(monkeypatch, finished)
    monkeypatch.setattr(evals, "expert_baseline", lambda run, env, phases, **kw: FakeJob("expert"))
    phases = PhaseTimer()
    res = evals.evaluate(FakeRun(), None, None, phases, "offline teacher", step=3, tag="t",
                         on_scores=lambda s: got.append(("now", s.tolist())))
    assert res.final_performance.tolist() == [0.5, 0.5] and got == [("now", [0.5, 0.5])]
    assert phases.records["evaluation (offline teacher)"]["episodes"] == 2
    evals.expert_scores(FakeRun(), None, phases, cache_root="x", background=True,
                        on_scores=lambda s: got.append(("expert", s.tolist())))
    assert evals.evaluate(FakeRun(), None, None, phases, "offline teacher", step=9, tag="t", background="p.pt",
                          background_step=6, on_scores=lambda s: got.append(("offline", s.tolist()))) is None
    assert finished == [] and len(got) == 1
    evals.finish_pending(FakeRun(), phases)
    assert finished == [("p.pt", "offline teacher", 6, "eval"), ("expert", "scripted expert", 0, "eval_expert")]
    assert got[1:] == [("offline", [0.25, 0.25]), ("expert", [0.25, 0.25])]
    evals.finish_pending(FakeRun(), phases)  # nothing left
    assert len(finished) == 2


def test_expert_scores_known_now_and_run_envs_closing_and_cancelling(monkeypatch):
    finished, got, closed = [], [], []
    evals = fake_protocol(monkeypatch, finished)
    monkeypatch.setattr(evals, "expert_baseline", lambda run, env, phases, **kw: np.array([0.75, 0.25]))
    monkeypatch.setattr(protocol, "close_env", lambda env: closed.append(env))
    evals.expert_scores(FakeRun(), None, PhaseTimer(), cache_root="x", on_scores=lambda s: got.append(np.mean(s)))
    assert got == [0.5]
    phases, a, b = PhaseTimer(), object(), object()
    with pytest.raises(RuntimeError, match="boom"):
        with RunEnvs(phases, a, None, b, evals=evals) as envs:
            envs.start_workers()  # envs without workers: nothing to start
            envs.join_workers()
            envs.close(b)
            envs.close(b)  # closed once
            evals.evaluate(FakeRun(), None, None, phases, "offline teacher", step=1, tag="t", background="p.pt")
            job = evals._pending[-1][0]
            raise RuntimeError("boom")
    assert closed == [b, a] and job.cancelled and evals._pending == []
    assert {"env worker start (after training)", "env worker shutdown"} <= set(phases.records)


def test_run_envs_without_a_phase_timer_closes_its_envs_in_order(monkeypatch):
    closed = []
    monkeypatch.setattr(protocol, "close_env", lambda env: closed.append(env))
    a, b, c = object(), object(), object()
    with RunEnvs(None, a, None, b, c) as envs:  # a run that times no phases (distill.py)
        envs.start_workers()
        envs.join_workers()
    assert closed == [a, b, c]


def test_a_protocol_of_no_episodes_evaluates_nothing(tmp_path):
    # --eval-episodes 0 (pipeline.py's stages): no episode, no job, no log row, no callback, no cache file
    run, calls = FakeRun(), []
    evals = EvalProtocol("ClothFold", 6, 0, 1)
    assert evals.evaluate(run, None, None, PhaseTimer(), "final", step=1, tag="t", on_scores=calls.append) is None
    assert evals.evaluate(run, None, None, PhaseTimer(), "bg", step=1, tag="t", background="policy.pt") is None
    evals.expert_scores(run, None, PhaseTimer(), cache_root=tmp_path, on_scores=calls.append)
    evals.finish_pending(run, PhaseTimer())
    assert calls == [] and run.rows == [] and list(tmp_path.iterdir()) == []


def test_eval_config_makes_the_protocol_and_the_envs_it_describes():
    from trakdis.evaluation import EvalConfig

    made = []

    class Handle:
        def make_env(self, **kwargs):
            made.append(kwargs)
            return "env"

    cfg = EvalConfig(eval_episodes=5, num_envs=2, parallel=False, collector="multi_sync")
    evals = cfg.eval_protocol("ClothFold", 7, seed=3, log_returns=False)
    assert (evals.task, evals.horizon, evals.episodes, evals.num_envs, evals.seed) == ("ClothFold", 7, 5, 2, 10_003)
    assert evals.collector == "multi_sync" and not evals.log_returns
    assert cfg.make_env(Handle()) == "env" and cfg.make_env(Handle(), "train", target_return=-1.0) == "env"
    assert made == [{"num_envs": 2, "split": "eval", "parallel": False},
                    {"num_envs": 2, "split": "train", "parallel": False, "target_return": -1.0}]
    assert EvalConfig(eval_episodes=0).make_env(Handle()) is None and len(made) == 2  # nothing to evaluate
