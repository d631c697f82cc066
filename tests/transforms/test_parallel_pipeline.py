"""All transforms in one ParallelEnv pipeline (one worker spawn keeps the suite fast).

Inside the workers (so the transforms, the encoder included, are pickled to spawned processes):
ImageResize -> EncoderTransform -> ReturnToGo -> StateNoise. Outside, on the batched env:
a second ImageResize and StateNoise, as a user would add them on top of a ParallelEnv.
"""

import functools

import torch
from torchrl.collectors import Collector
from torchrl.envs import Compose, ParallelEnv, TransformedEnv, check_env_specs
from torchrl.envs.utils import RandomPolicy

from test_return_to_go import check_countdown
from toy_pixel_env import TinyEncoder, make_toy_env_with
from trakdis.transforms import EncoderTransform, ImageResize, ReturnToGo, StateNoise


def _worker_transforms():
    torch.manual_seed(0)
    return Compose(
        ImageResize(in_keys=["pixels"], size=12),
        EncoderTransform(TinyEncoder(out_dim=4)),
        ReturnToGo(-1.0, rtg_scale=2.0),
        StateNoise(0.01, in_keys=["state"], seed=0),
    )


def test_parallel_env_pipeline():
    par = ParallelEnv(2, functools.partial(make_toy_env_with, _worker_transforms, size=16), mp_start_method="spawn")
    env = TransformedEnv(
        par,
        Compose(ImageResize(in_keys=["pixels"], out_keys=["tiny"], size=6), StateNoise(1e-3, seed=1)),
    )
    try:
        check_env_specs(env, seed=0)
        spec = env.observation_spec
        assert spec["pixels"].shape == (2, 12, 12, 3) and spec["tiny"].shape == (2, 6, 6, 3)
        assert spec["state_estimate"].shape == (2, 4) and spec["return_to_go"].shape == (2, 1)
        col = Collector(env, RandomPolicy(env.action_spec), frames_per_batch=24, total_frames=24)
        batch = next(iter(col))
        col.shutdown(close_env=False)
        assert batch["pixels"].shape == (2, 12, 12, 12, 3) and batch["tiny"].shape == (2, 12, 6, 6, 3)
        # the workers' encoder is the pickled copy of the same weights; outside noise is small
        ref = _worker_transforms()[1].encoder
        expected = ref(batch["pixels"].flatten(0, 1)).unflatten(0, (2, 12))
        assert (batch["state_estimate"] - expected).abs().max() < 0.02
        assert (batch["state_estimate"] - expected).abs().max() > 0
        assert check_countdown(batch, -1.0, 2.0) >= 2  # partial resets inside the ParallelEnv
    finally:
        if not par.is_closed:
            par.close()
