"""A 1-d walk env for the evaluation tests: state += action, normalized_performance = state."""
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import EnvBase


class Walk(EnvBase):
    """1-d walk: state += action; normalized_performance = state. It starts at 0, or with
    ``random_start`` at U(-1, 1) drawn from its seeded generator at each reset; ``unstable_at``:
    the episode ends early (``sim_unstable``) at that step."""

    def __init__(self, unstable_at=None, random_start=False):
        super().__init__(batch_size=())
        self.unstable_at = unstable_at
        self.random_start = random_start
        self.rng = torch.Generator().manual_seed(12345)
        self.observation_spec = Composite(
            state=Unbounded(shape=(1,)), normalized_performance=Unbounded(shape=(1,)),
            sim_unstable=Unbounded(shape=(1,), dtype=torch.bool),
        )
        self.action_spec = Bounded(-1, 1, shape=(1,))
        self.reward_spec = Unbounded(shape=(1,))

    def _reset(self, td):
        self._t = 0
        s = torch.rand(1, generator=self.rng) * 2 - 1 if self.random_start else torch.zeros(1)
        return TensorDict(state=s, normalized_performance=s.clone(), sim_unstable=torch.zeros(1, dtype=torch.bool),
                          done=torch.zeros(1, dtype=torch.bool), terminated=torch.zeros(1, dtype=torch.bool))

    def _step(self, td):
        self._t += 1
        s = td["state"] + td["action"]
        bad = self.unstable_at is not None and self._t >= self.unstable_at
        return TensorDict(state=s, normalized_performance=s.clone(), reward=-s.abs(),
                          sim_unstable=torch.tensor([bad]), done=torch.tensor([bad]), terminated=torch.zeros(1, dtype=torch.bool))

    def _set_seed(self, seed):
        self.rng.manual_seed(int(seed))
