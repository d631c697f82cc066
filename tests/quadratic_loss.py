"""A loss module with one parameter vector: loss_q = sum(w ** 2), w starting at ones (optimiser tests)."""
import torch
from tensordict import TensorDict


class Quadratic(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.ones(2))

    def forward(self, td):
        return TensorDict(loss_q=(self.w**2).sum())
