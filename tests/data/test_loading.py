"""Finding and checking the recipes' datasets: default dataset names and the scripted-expert version check."""
import json

import pytest

from trakdis.data import DataConfig, DatasetError, default_dataset_path, ensure_dataset
from trakdis.envs import expert_version, render_version

CLOTHFOLD_EXPERT = expert_version("ClothFold")


def _fake_dataset(path, expert_version, task="ClothFold", horizon=100, render=None):
    path.mkdir(parents=True)
    config = {"task": task, "render_version": render_version(task) if render is None else render}
    if expert_version is not None:
        config["expert_version"] = expert_version
    (path / "meta.json").write_text(json.dumps({"format": "trakdis-dataset", "version": 1, "task": task,
                                                "num_episodes": 3, "horizon": horizon, "keys": {}, "config": config}))


def test_default_name():
    cfg = DataConfig(root="d", episodes=7, expert_noise=0.1)
    assert default_dataset_path(cfg, task="ClothFold", horizon=50, pixels=True).as_posix() == "d/ClothFold_7ep_h50_noise0.1_px32"
    assert default_dataset_path(DataConfig(path="x/y"), task="ClothFold", horizon=50, pixels=False).as_posix() == "x/y"
    aimed = DataConfig(root="d", episodes=7, expert_noise=0.1, aim_error=0.03)  # a misled expert's: its own name
    assert default_dataset_path(aimed, task="ClothFold", horizon=50, pixels=True).as_posix() == "d/ClothFold_7ep_h50_noise0.1_aim0.03_px32"
    closing = DataConfig(root="d", episodes=7, close_radius=0.01)  # another grasp radius: its own name too
    closing_path = default_dataset_path(closing, task="ClothFold", horizon=50, pixels=False)
    assert closing_path.as_posix() == "d/ClothFold_7ep_h50_noise0.15_close0.01"


def test_a_dataset_of_another_close_radius_is_refused(tmp_path):
    """--data.close-radius names the data it wants: a dataset collected with another radius (or the task's default)
    is a DatasetError naming it and both radii, and nothing on disk changes."""
    path = tmp_path / "data"
    _fake_dataset(path, CLOTHFOLD_EXPERT)
    before = (path / "meta.json").read_bytes()
    ask = dict(task="ClothFold", horizon=100, seed=0, pixels=True)
    with pytest.raises(DatasetError, match=rf"dataset {path} \(--data.path\) was collected by an expert closing its "
                                           rf"grasps within the task's default .* asks for 0.01 m \(--data.close-radius"):
        ensure_dataset(DataConfig(path=str(path), close_radius=0.01), **ask)
    assert (path / "meta.json").read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["data"]
    meta = json.loads(before)
    meta["config"]["close_radius"] = 0.01
    (path / "meta.json").write_text(json.dumps(meta))
    assert ensure_dataset(DataConfig(path=str(path), close_radius=0.01), **ask) == path
    for other, asked in ((0.02, "0.02 m"), (None, "the task's default")):  # a run's labels must be the data's expert's
        with pytest.raises(DatasetError, match=rf"within 0.01 m of the corners, but this run asks for {asked}"):
            ensure_dataset(DataConfig(path=str(path), close_radius=other), **ask)


def test_data_seed_names_the_dataset_and_seeds_its_collection(tmp_path, monkeypatch):
    from trakdis.data import loading

    calls = []
    monkeypatch.setattr(loading, "collect_expert_dataset", lambda path, **kw: calls.append((path, kw["seed"])))
    path = ensure_dataset(DataConfig(root=str(tmp_path), episodes=2, seed=5), task="ClothFold", horizon=4, seed=0,
                          pixels=False, log=lambda *a: None)
    assert path.name == "ClothFold_2ep_h4_noise0.15_seed5" and calls == [(path, 5)]  # --data.seed wins over the run's
    ensure_dataset(DataConfig(root=str(tmp_path), episodes=2), task="ClothFold", horizon=4, seed=3, pixels=False,
                   log=lambda *a: None)
    # unset: a default path names no seed, so it is seed 0's whichever run collects it first (the encoder's extra
    # datasets: their offsets); a path of one's own: the run's seed
    assert calls[-1] == (tmp_path / "ClothFold_2ep_h4_noise0.15", 0)
    ensure_dataset(DataConfig(root=str(tmp_path), episodes=2, expert_noise=0.5), task="ClothFold", horizon=4, seed=3,
                   pixels=False, log=lambda *a: None, seed_offset=1)
    assert calls[-1] == (tmp_path / "ClothFold_2ep_h4_noise0.5", 1)
    ensure_dataset(DataConfig(path=str(tmp_path / "mine")), task="ClothFold", horizon=4, seed=3, pixels=False,
                   log=lambda *a: None)
    assert calls[-1] == (tmp_path / "mine", 3)


def test_a_default_dataset_of_another_seed_is_used_and_said_so(tmp_path, monkeypatch):
    from trakdis.data import loading

    cfg = DataConfig(root=str(tmp_path), episodes=2)
    path = default_dataset_path(cfg, task="ClothFold", horizon=4, pixels=False)
    path.mkdir()
    (path / "meta.json").write_text("{}")
    monkeypatch.setattr(loading, "collect_expert_dataset", lambda path, **kw: pytest.fail("collected again"))
    for found, notes in ((0, 0), (2, 1)):  # collected by an earlier trakdis with its run's seed 2
        monkeypatch.setattr(loading, "read_meta", lambda p, found=found: {
            "task": "ClothFold", "horizon": 4,
            "config": {"seed": found, "expert_version": expert_version("ClothFold")}})
        lines = []
        assert ensure_dataset(cfg, task="ClothFold", horizon=4, seed=5, pixels=False, log=lines.append) == path
        assert len(lines) == notes and all("collected with seed 2, not the default path's 0" in x for x in lines)


@pytest.mark.parametrize("found", [None, CLOTHFOLD_EXPERT - 1])
def test_default_dataset_of_an_older_expert_is_refused(tmp_path, found):
    cfg = DataConfig(root=str(tmp_path), episodes=3)
    path = default_dataset_path(cfg, task="ClothFold", horizon=100, pixels=True)
    _fake_dataset(path, found)
    with pytest.raises(DatasetError, match=rf"{path.name}.*version {found or 1} of the ClothFold scripted expert.*--data.path"):
        ensure_dataset(cfg, task="ClothFold", horizon=100, seed=0, pixels=True)
    # an explicit --data.path is used as it is
    explicit = DataConfig(path=str(path))
    assert ensure_dataset(explicit, task="ClothFold", horizon=100, seed=0, pixels=True) == path


def test_default_dataset_of_the_current_expert_is_used(tmp_path):
    cfg = DataConfig(root=str(tmp_path), episodes=3)
    path = default_dataset_path(cfg, task="ClothFold", horizon=100, pixels=True)
    _fake_dataset(path, CLOTHFOLD_EXPERT)
    assert ensure_dataset(cfg, task="ClothFold", horizon=100, seed=0, pixels=True) == path


@pytest.mark.parametrize("task,horizon", [("ClothFoldDiagonalPinned", 100), ("ClothFold", 20)])
def test_dataset_of_another_task_or_horizon_is_refused(tmp_path, task, horizon):
    """A pinned dataset must not train a policy labelled unpinned, nor horizon-20 data a horizon-30 run."""
    path = tmp_path / "data"
    _fake_dataset(path, CLOTHFOLD_EXPERT, task=task, horizon=horizon)
    before = (path / "meta.json").read_bytes()
    with pytest.raises(DatasetError, match=rf"dataset {path} \(--data.path\) holds task {task} with horizon {horizon}, "
                                           rf"but this run asks for --task ClothFoldDiagonalUnpinned --horizon 30"):
        ensure_dataset(DataConfig(path=str(path)), task="ClothFoldDiagonalUnpinned", horizon=30, seed=0, pixels=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"] and (path / "meta.json").read_bytes() == before


@pytest.mark.parametrize("content", ["[]", "null", '{"format": "trakdis-dataset", "version": 1, "task": "ClothFold"}'])
def test_malformed_meta_is_a_dataset_error(tmp_path, content):
    path = tmp_path / "data"
    path.mkdir()
    (path / "meta.json").write_text(content)
    with pytest.raises(DatasetError, match="meta.json"):
        ensure_dataset(DataConfig(path=str(path)), task="ClothFold", horizon=100, seed=0, pixels=True)


def test_horizon_below_one_is_refused(tmp_path):
    with pytest.raises(ValueError, match="--horizon 0"):
        ensure_dataset(DataConfig(root=str(tmp_path)), task="ClothFold", horizon=0, seed=0, pixels=True)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("found", ["absent", render_version("ClothFold") - 1])
def test_default_pixel_dataset_of_an_older_rendering_is_refused(tmp_path, found):
    cfg = DataConfig(root=str(tmp_path), episodes=3)
    path = default_dataset_path(cfg, task="ClothFold", horizon=100, pixels=True)
    _fake_dataset(path, CLOTHFOLD_EXPERT, render=found)
    if found == "absent":  # datasets before render_version existed (version 1)
        meta = json.loads((path / "meta.json").read_text())
        del meta["config"]["render_version"]
        (path / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="rendering version"):
        ensure_dataset(cfg, task="ClothFold", horizon=100, seed=0, pixels=True)


def test_rendering_versions_are_per_task(tmp_path):
    # the unpinned fold's camera changed (version 3) and ClothFold's did not: images of ClothFold's
    # rendering version are refused for the unpinned fold and kept for ClothFold
    task = "ClothFoldDiagonalUnpinned"
    assert render_version(task) == render_version("ClothFold") + 1
    cfg = DataConfig(root=str(tmp_path), episodes=3)
    for name, version in ((task, expert_version(task)), ("ClothFold", CLOTHFOLD_EXPERT)):
        _fake_dataset(default_dataset_path(cfg, task=name, horizon=100, pixels=True), version, task=name,
                      render=render_version("ClothFold"))
    assert ensure_dataset(cfg, task="ClothFold", horizon=100, seed=0, pixels=True).exists()
    with pytest.raises(DatasetError, match=f"{task} at version 3"):
        ensure_dataset(cfg, task=task, horizon=100, seed=0, pixels=True)


def test_ensure_dataset_timed_books_the_collected_episodes(tmp_path, monkeypatch):
    from trakdis.data import DataConfig, ensure_dataset_timed, loading
    from trakdis.utils.phases import PhaseTimer

    def fake_ensure(cfg, *, task, horizon, pixels, **kwargs):  # "collects" by writing meta.json
        path = loading.default_dataset_path(cfg, task=task, horizon=horizon, pixels=pixels)
        path.mkdir(parents=True, exist_ok=True)
        (path / "meta.json").write_text("{}")
        return path

    monkeypatch.setattr(loading, "ensure_dataset", fake_ensure)
    cfg = DataConfig(root=str(tmp_path), episodes=3, num_envs=1)
    phases, lines = PhaseTimer(), []
    path = ensure_dataset_timed(cfg, phases=phases, task="ClothFold", horizon=5, seed=0, pixels=False, log=lines.append)
    assert (path / "meta.json").exists() and phases.records["dataset collection"]["episodes"] == 3
    assert len(lines) == 1 and lines[0].startswith("collected 3 episodes in")
    ensure_dataset_timed(cfg, phases=phases, task="ClothFold", horizon=5, seed=0, pixels=False, log=lines.append)
    assert phases.records["dataset collection"]["episodes"] == 3 and len(lines) == 1  # found: nothing collected


@pytest.mark.parametrize("with_pixels", [False, True])
def test_load_offline_data_prefers_an_existing_pixel_dataset_and_prints_its_returns(tmp_path, monkeypatch, with_pixels):
    import torch
    from tensordict import TensorDict

    from trakdis.data import load_offline_data, loading
    from trakdis.utils.phases import PhaseTimer

    cfg = DataConfig(root=str(tmp_path), episodes=2, num_envs=1)
    if with_pixels:  # found: used as it is, although this run asks for no images
        _fake_dataset(default_dataset_path(cfg, task="ClothFold", horizon=3, pixels=True), CLOTHFOLD_EXPERT, horizon=3)
    asked = []
    monkeypatch.setattr(loading, "ensure_dataset_timed", lambda cfg, *, pixels, **kw: asked.append(pixels) or tmp_path / "d")
    steps = TensorDict({"state": torch.zeros(2, 3, 4), "action": torch.zeros(2, 3, 2), "pixels": torch.zeros(2, 3, 1),
                        "reward": torch.tensor([[[-1.0], [-1.0], [0.0]], [[-0.5], [0.0], [0.0]]]),
                        "normalized_performance": torch.tensor([[[0.1], [0.2], [0.3]], [[0.5], [0.7], [0.0]]])},
                       batch_size=[2, 3])
    monkeypatch.setattr(loading, "load_expert_dataset", lambda path: (steps, {"lengths": torch.tensor([3, 2])}))
    lines = []
    trajectories, lengths = load_offline_data(cfg, phases=PhaseTimer(), task="ClothFold", horizon=3, seed=0,
                                              log=lines.append)
    assert asked == [with_pixels] and lengths.tolist() == [3, 2]
    assert set(trajectories.keys()) == {"state", "action", "reward", "normalized_performance"}
    assert lines == [f"offline data: 2 episodes from {tmp_path / 'd'}; return -1.250 (best -0.500); "
                     "final normalized performance 0.500"]


def _episodes(n, horizon, state_dim=2):
    """``n`` fake padded episodes with pixels: state (episode, step), reward -1 per step."""
    import torch
    from tensordict import TensorDict

    state = torch.stack(torch.meshgrid(torch.arange(n).float(), torch.arange(horizon).float(), indexing="ij"), -1)
    return TensorDict({"pixels": torch.zeros(n, horizon, 2, 2, 3, dtype=torch.uint8), "state": state[..., :state_dim],
                       "action": torch.zeros(n, horizon, 1), "reward": -torch.ones(n, horizon, 1),
                       "normalized_performance": torch.zeros(n, horizon, 1)}, [n, horizon])


def test_load_train_val_steps_splits_by_episode_and_adds_the_extra_datasets(tmp_path, monkeypatch):
    import torch

    from trakdis.data import load_train_val_steps, loading, split_episodes_train_val

    cfg = DataConfig(root=str(tmp_path), episodes=5)
    main = default_dataset_path(cfg, task="ClothFold", horizon=3, pixels=True)
    extra = default_dataset_path(DataConfig(root=str(tmp_path), episodes=5, expert_noise=0.3), task="ClothFold",
                                 horizon=3, pixels=True)
    aimed = default_dataset_path(DataConfig(root=str(tmp_path), episodes=5, aim_error=0.03), task="ClothFold",
                                 horizon=3, pixels=True)
    datasets = {main: (_episodes(5, 3), torch.tensor([3, 2, 3, 1, 3])), extra: (_episodes(2, 3), torch.tensor([3, 2])),
                aimed: (_episodes(1, 3), torch.tensor([2]))}
    seeds = {}

    def ensure_dataset(cfg, *, task, horizon, seed, pixels, seed_offset=0, **kw):
        path = default_dataset_path(cfg, task=task, horizon=horizon, pixels=pixels)
        seeds[path] = loading.collection_seed(cfg, seed=seed, seed_offset=seed_offset)
        return path

    monkeypatch.setattr(loading, "ensure_dataset", ensure_dataset)
    monkeypatch.setattr(loading, "load_expert_dataset",
                        lambda path: (datasets[path][0], {"lengths": datasets[path][1]}))
    collected = {main: (7, 0.15), extra: (8, 0.3), aimed: (9, 0.15)}  # the seed and noise each was collected with
    monkeypatch.setattr(loading, "read_meta", lambda p: {"config": {"seed": collected[p][0], "noise": collected[p][1],
                                                                    "custom_policy": False}})
    lines = []
    path, train, val, train_eps, val_eps = load_train_val_steps(cfg, task="ClothFold", horizon=3, seed=7,
                                                                keys=("pixels", "state"), val_fraction=0.4,
                                                                extra_noise=(0.3,), extra_aim_error=(0.03,),
                                                                log=lines.append)
    assert path == main and seeds == {main: 0, extra: 1, aimed: 2}  # default paths: seeds that no run's --seed moves
    expected_train, expected_val = split_episodes_train_val(5, 0.4, seed=7)
    assert train_eps.tolist() == expected_train.tolist() and val_eps.tolist() == expected_val.tolist()
    lengths = [3, 2, 3, 1, 3]
    assert val.shape[0] == sum(lengths[i] for i in val_eps) and set(train.keys()) == {"pixels", "state"}
    assert train.shape[0] == sum(lengths[i] for i in train_eps) + 5 + 2  # + all the extra datasets' 3 + 2 and 2 steps
    assert lines == [f"training images +5 from {extra}", f"training images +2 from {aimed}"]
    assert load_train_val_steps(cfg, task="ClothFold", horizon=3, seed=7, keys=("state",), val_fraction=0.0).val is None
    # --extra-seeds: the same expert's datasets of other seeds (own default paths); --extra-data: existing ones by path,
    # never collected. The main dataset, or one collected exactly as it was, is refused (the same episodes twice).
    given = tmp_path / "more"
    given.mkdir()
    (given / "meta.json").write_text("{}")
    reseeded = default_dataset_path(DataConfig(root=str(tmp_path), episodes=5, seed=3), task="ClothFold", horizon=3,
                                    pixels=True)
    assert reseeded.name.endswith("_noise0.15_seed3_px32")
    datasets[given], datasets[reseeded] = (_episodes(2, 3), torch.tensor([1, 3])), (_episodes(1, 3), torch.tensor([2]))
    collected.update({reseeded: (3, 0.15), given: (5, 0.15)})
    lines.clear()
    seeds.clear()
    more = load_train_val_steps(cfg, task="ClothFold", horizon=3, seed=7, keys=("state",), val_fraction=0.4,
                                extra_seeds=(3,), extra_data=(str(given),), log=lines.append)
    assert seeds[reseeded] == 3 and more.train.shape[0] == train.shape[0] - 5 - 2 + 2 + 4
    assert lines == [f"training images +2 from {reseeded}", f"training images +4 from {given}"]
    main.mkdir(parents=True)
    (main / "meta.json").write_text("{}")
    for bad, message in (({"extra_data": (str(tmp_path / "none"),)}, "no dataset there"),
                         ({"extra_data": (str(main),)}, "is the main dataset"),
                         ({"extra_seeds": (0,)}, "collected as the main dataset")):
        if "extra_seeds" in bad:  # seed 0's dataset, found collected exactly as the main one was
            collected[main.parent / main.name.replace("_px32", "_seed0_px32")] = (7, 0.15)
        with pytest.raises(DatasetError, match=message):
            load_train_val_steps(cfg, task="ClothFold", horizon=3, seed=7, keys=("state",), val_fraction=0.4, **bad)


def test_load_encoded_dataset_puts_the_encoders_output_beside_the_kept_entries(tmp_path, monkeypatch):
    import torch

    from trakdis.data import load_encoded_dataset, loading

    monkeypatch.setattr(loading, "ensure_dataset", lambda cfg, **kw: tmp_path / "d")
    monkeypatch.setattr(loading, "load_expert_dataset",
                        lambda path: (_episodes(3, 4), {"lengths": torch.tensor([4, 2, 3])}))
    data, lengths, path = load_encoded_dataset(DataConfig(), lambda px: px.float().sum((-3, -2, -1)).unsqueeze(-1) + 1,
                                               task="ClothFold", horizon=4, seed=0, keys=("action", "reward"))
    assert path == tmp_path / "d" and lengths.tolist() == [4, 2, 3] and data.batch_size == (3, 4)
    assert set(data.keys()) == {"action", "reward", "state_estimate"} and (data["state_estimate"] == 1).all()


def test_offline_state_buffer_fits_on_a_fresh_run_and_reloads_from_the_checkpoint(tmp_path, monkeypatch):
    from dataclasses import dataclass

    import torch

    from trakdis.data import loading, offline_state_buffer
    from trakdis.utils.phases import PhaseTimer
    from trakdis.utils.run import Run, RunConfig, RunState

    @dataclass
    class Cfg(RunConfig):
        pass

    data, lengths = _episodes(3, 4), torch.tensor([4, 2, 3])
    data["reward"][1] = -0.5  # episode 1: the best return (-1: 2 real steps, no reward in the padding)
    data["reward"] *= (torch.arange(4)[None] < lengths[:, None]).unsqueeze(-1)
    loaded = []
    monkeypatch.setattr(loading, "load_offline_data", lambda cfg, **kw: loaded.append(kw) or (data, lengths))

    def start(*argv, name="a", **noise):
        run = Run.start("toy", Cfg, ["--root", str(tmp_path), "--name", name, "--no-progress", *argv])
        state = RunState(run, {"normalizer": None, "best_return": None, "buffer_capacity": None}, step_key="x",
                         counters_key="counters")
        state["x"] = 0
        buffer, normalizer = offline_state_buffer(state, DataConfig(), phases=PhaseTimer(), task="ClothFold", horizon=4,
                                                  seed=0, context_len=2, min_scale=0.5,
                                                  **(noise or {"state_noise": 0.1}))
        state.load()
        return state, buffer, normalizer

    state, buffer, normalizer = start()
    real = data["state"][torch.arange(4)[None] < lengths[:, None]]
    assert torch.allclose(normalizer.loc, real.mean(0)) and torch.allclose(normalizer.scale, real.std(0).clamp_min(0.5))
    assert state["best_return"] == pytest.approx(-1.0) and state["buffer_capacity"] == 3 and len(buffer) == 3
    assert len(loaded) == 1 and state.objects["buffer"] is buffer
    batch = buffer.sample(4)  # standardised (and noisy) states
    assert batch["state"].abs().max() < 10 and batch.batch_size == (4, 2)
    state.save()
    resumed, buffer2, normalizer2 = start("--resume")
    assert len(loaded) == 1  # the dataset is not read again
    assert resumed["best_return"] == state["best_return"] and torch.equal(normalizer2.loc, normalizer.loc)
    assert len(buffer2) == 3 and torch.equal(buffer2.returns, buffer.returns)
    # state_offset: the same windows (same seed) shifted by one offset per window, the same at both its steps
    _, exact, _ = start(name="exact", state_noise=0.0)
    _, offset, _ = start(name="offset", state_noise=0.0, state_offset=0.1)
    windows, shifted = exact.sample(64), offset.sample(64)
    full = windows["mask"].all(1)  # (padded positions stay zero)
    shift = (shifted["state"] - windows["state"])[full]
    assert full.sum() > 8 and torch.equal(shifted["mask"], windows["mask"])
    assert torch.allclose(shift[:, 0], shift[:, 1], atol=1e-6) and shift.abs().min() > 0


@pytest.mark.parametrize("distill, proprio", [(True, ()), (False, ()), (False, (1,))])
def test_student_buffer_keys_proprioception_and_noise(distill, proprio):
    """distill.py's buffer: the estimate standardised by the teacher's normaliser; the true state beside it
    for the teacher's labels (distillation) or the picker dims it replaces (--proprio-pickers); noise on the
    estimate, never on the true state, with distillation too (its data may have no rollouts)."""
    import torch

    from trakdis.data import student_buffer
    from trakdis.transforms import state_normalizer

    data = _episodes(3, 4)
    data["state_estimate"] = data["state"] + 100.0  # an encoder 100 units off in both dims
    normalizer = state_normalizer(torch.zeros(2), torch.full((2,), 2.0), keys=("state", "state_estimate"))
    buffer = student_buffer(5, 2, 4, 1.0, normalizer=normalizer, distill=distill, proprio_dims=proprio,
                            state_noise=0.5, seed=0)
    buffer.load_offline(data.exclude("pixels", "normalized_performance") if distill or proprio
                        else data.exclude("pixels", "normalized_performance", "state"), torch.tensor([4, 4, 4]))
    batch = buffer.sample(64)
    assert ("state" in batch.keys()) == bool(distill or proprio)
    real = batch["mask"] if "mask" in batch.keys() else torch.ones(batch.shape, dtype=torch.bool)
    off = (batch["state_estimate"] - (batch["state"] if "state" in batch.keys() else 0.0) / 1.0)[real]
    if distill:  # the true state exact, the estimate 50 standard units off plus noise of 0.25 units
        assert torch.equal(batch["state"][real] * 2.0, batch["state"][real] * 2.0 // 1)  # integers: no noise
        assert 0.15 < (off - 50.0).std() < 0.35 and (off - 50.0).abs().mean() < 0.5
    elif proprio:  # dim 1 from the true state (noise added to the estimate before the override)
        assert torch.allclose(off[:, 1], torch.zeros_like(off[:, 1]))
        assert not torch.allclose(batch["state_estimate"][real][:, 0] % 0.5, torch.zeros_like(off[:, 0]))
    else:
        est = batch["state_estimate"][real] * 2.0 - 100.0  # back in state units: state + noise
        assert 0.0 < (est - est.round()).abs().mean() < 0.5  # states are integers here, the noise is not


def test_expert_versions_are_per_task(tmp_path):
    """A task whose expert changed refuses its older default datasets; another task keeps them."""
    cfg = DataConfig(root=str(tmp_path), episodes=3)
    pinned = "ClothFoldDiagonalPinned"  # its expert is still version 2
    kept = default_dataset_path(cfg, task=pinned, horizon=100, pixels=True)
    _fake_dataset(kept, 2, task=pinned, render=render_version(pinned))
    assert ensure_dataset(cfg, task=pinned, horizon=100, seed=0, pixels=True) == kept
    for task in ("ClothFoldDiagonalUnpinned", "ClothFold"):  # their experts are version 3
        old = default_dataset_path(cfg, task=task, horizon=100, pixels=True)
        _fake_dataset(old, 2, task=task, render=render_version(task))
        with pytest.raises(DatasetError, match=rf"{old.name}.*version 2 of the {task} scripted expert.*version "
                                               rf"{expert_version(task)}"):
            ensure_dataset(cfg, task=task, horizon=100, seed=0, pixels=True)


def test_state_buffer_config_makes_the_teachers_buffer_with_its_options(monkeypatch):
    """StateBufferConfig (online_dt.py's --state-scale-floor, --train-state-noise, ...): offline_state_buffer with
    these options, the task's out-of-view fill with --mask-unseen-pickers; its checks while parsing."""
    import trakdis.data.loading as loading
    from trakdis.data import StateBufferConfig
    from trakdis.transforms import OutOfViewFill

    calls = []
    monkeypatch.setattr(loading, "offline_state_buffer", lambda state, data, **kwargs: calls.append((state, data, kwargs)))
    cfg = StateBufferConfig(state_scale_floor=0.02, train_state_noise=0.01, train_state_offset=0.015,
                            mask_unseen_pickers=True, rtg_scale=2.0, buffer_replacement="oldest", early_windows=False)
    cfg.state_buffer("state", "data", phases="phases", task="ClothFold", horizon=6, seed=3, context_len=4,
                     target_key="expert_action", extra_capacity=5, collect_pixels=True, progress=False)
    (state, data, kwargs), = calls
    fill = kwargs.pop("fill")
    assert (state, data) == ("state", "data") and isinstance(fill, OutOfViewFill)
    assert fill.starts == OutOfViewFill.for_task("ClothFold").starts
    assert {k: v for k, v in kwargs.items() if k != "log"} == {
        "phases": "phases", "task": "ClothFold", "horizon": 6, "seed": 3, "context_len": 4, "rtg_scale": 2.0,
        "min_scale": 0.02, "state_noise": 0.01, "state_offset": 0.015, "early_windows": False, "replacement": "oldest",
        "collect_pixels": True, "progress": False, "target_key": "expert_action", "extra_capacity": 5}
    StateBufferConfig().state_buffer("state", "data", phases=None, task="ClothFold", horizon=6, seed=3, context_len=4)
    assert calls[1][2]["fill"] is None and calls[1][2]["target_key"] is None
    assert StateBufferConfig.SAVED_AS == {"state_noise": "train_state_noise"}  # the option's earlier name
    for bad in ({"buffer_capacity": 0}, {"rtg_scale": 0.0}, {"state_scale_floor": 0.0}, {"train_state_noise": -1.0},
                {"train_state_offset": -1.0}):
        with pytest.raises(ValueError, match=f"--{next(iter(bad)).replace('_', '-')}"):
            StateBufferConfig(**bad)


def test_encoder_data_config_loads_the_train_val_steps_with_its_options(monkeypatch):
    import trakdis.data.loading as loading
    from trakdis.data import EncoderDataConfig

    calls = []

    def load(data, **kwargs):
        calls.append((data, kwargs))
        return "steps"

    monkeypatch.setattr(loading, "load_train_val_steps", load)
    cfg = EncoderDataConfig(extra_noise=(0.4,), extra_aim_error=(0.03,), extra_seeds=(1,), extra_data=("d",),
                            val_fraction=0.3)
    assert cfg.train_val_steps("data", task="ClothFold", horizon=6, seed=2, keys=("pixels", "state"), image_size=16,
                               progress=False) == "steps"
    (data, kwargs), = calls
    assert data == "data" and {k: v for k, v in kwargs.items() if k != "log"} == {
        "task": "ClothFold", "horizon": 6, "seed": 2, "keys": ("pixels", "state"), "val_fraction": 0.3,
        "image_size": 16, "extra_noise": (0.4,), "extra_aim_error": (0.03,), "extra_seeds": (1,), "extra_data": ("d",),
        "progress": False}
