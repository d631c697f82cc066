"""Acting wrapper: runs a Decision Transformer actor step by step for a batch of environments.

TorchRL's ``DecisionTransformerInferenceWrapper`` expects the whole trajectory window in the
input tensordict (the caller must keep it, e.g. with ``CatFrames``) and re-encodes all ``3K``
tokens at every step. :class:`DTActingPolicy` instead keeps the context itself (preallocated
ring buffers, one row per env), resets rows per env from ``"step_count" == 0``, stores its own
chosen action, and can decode incrementally with a key/value cache.
"""
from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import InteractionType, ProbabilisticTensorDictModule, TensorDictModule, TensorDictModuleBase
from tensordict.nn.probabilistic import interaction_type
from torch import nn

from trakdis.modules.decision_transformer import TOKENS_PER_STEP, StochasticDTActor, find_dt_actor
from trakdis.modules.grasp_distribution import GraspConditionedTanhNormal
from trakdis.modules.transformer import KVCache

__all__ = ["DTActingPolicy"]

_MODES = ("window", "kv_cache")


class DTActingPolicy(TensorDictModuleBase):
    """Step-by-step acting for a batch of ``N`` envs with a rolling context of the last K steps.

    Per call it reads ``observation_key`` ``[*B, state_dim]``, ``"return_to_go"`` ``[*B, 1]`` and
    ``"step_count"`` ``[*B, 1]`` (int; 0 means this env was just reset: its context is cleared)
    and writes ``"action"`` ``[*B, action_dim]`` for the newest step, drawn from the actor's
    ``TanhNormal`` according to the current ``ExplorationType`` (``DETERMINISTIC``: ``tanh(loc)``;
    ``RANDOM``: a sample; default: the actor's default, deterministic). With a grasp head
    (``GraspConditionedTanhNormal``), ``DETERMINISTIC`` switches each grasp at the median of its
    switch time: once the probability that a sampled grasp would have switched since its last
    switch (close an open picker, open a closed one) reaches one half; the movement is ``tanh(loc)``
    of the grasp's branch. ``*B`` may be empty (an
    unbatched env), ``[1]`` or any shape; a change of batch shape re-allocates (and clears) the
    context. Call under ``actor.eval()`` to disable dropout. Inputs are cast to the actor's dtype
    (float64 observations work); an empty batch, or a NaN/inf observation or return-to-go (which
    would make the env's actions NaN until its next reset), is a ``ValueError`` naming the key,
    raised before the context changes.

    Args:
        actor: an actor from :func:`~trakdis.modules.make_dt_actor` (or any module containing one
            ``StochasticDTActor`` wrapped in a ``TensorDictModule`` and a probabilistic module).
        context_len: K; defaults to the actor's ``DTModelConfig.context_len``.
        mode: how each step is computed; per-step cost never grows with the number of steps taken.

            * ``"window"`` (default): re-encode the last K steps (``3K`` tokens) with the same
              forward as training. Exactly equal, at every step, to the actor's output at the
              last position of the corresponding left-padded training window. Cost ``O(K^2)`` per step.
            * ``"kv_cache"``: encode only the 3 new tokens ``(a_{t-1}, R_t, s_t)`` and attend to a
              rolling key/value cache holding the last K steps' tokens. Exact (same as
              ``"window"``) while fewer than K steps were taken since the env's reset. Afterwards it
              is a sliding-window approximation (as in Mistral's rolling buffer cache): the queries
              see exactly the training window's tokens, but cached keys/values of older tokens were
              computed when *their* context still held steps that have since left the window,
              whereas training re-encodes the window from scratch. Cost ``O(K)`` per step.
        observation_key: defaults to the actor's observation in_key.
        return_to_go_key, step_count_key, action_key: tensordict keys.
    """

    def __init__(
        self,
        actor: nn.Module,
        context_len: int | None = None,
        *,
        mode: str = "window",
        observation_key=None,
        return_to_go_key="return_to_go",
        step_count_key="step_count",
        action_key="action",
    ):
        super().__init__()
        if mode not in _MODES:
            raise ValueError(f"mode={mode!r}; expected one of {_MODES}")
        self.actor = actor
        self.dt: StochasticDTActor = find_dt_actor(actor)
        tdms = [m for m in actor.modules() if isinstance(m, TensorDictModule) and m.module is self.dt]
        probs = [m for m in actor.modules() if isinstance(m, ProbabilisticTensorDictModule)]
        if len(probs) != 1:
            raise ValueError(f"expected one probabilistic module (the action distribution) in the actor, found {len(probs)}")
        self._prob_module = probs[0]
        # the distribution's parameters in the order the DT's head returns them, under the names the
        # probabilistic module reads (the head's out_keys)
        self._dist_keys = tdms[0].out_keys if tdms else list(self.dt.dist_keys)
        if observation_key is None:
            if not tdms:
                raise ValueError("cannot infer observation_key from the actor; pass observation_key=")
            observation_key = tdms[0].in_keys[0]
        self.context_len = int(context_len or self.dt.config.context_len)
        if self.context_len < 1:
            raise ValueError(f"context_len={context_len} must be >= 1")
        self.mode = mode
        self.observation_key = observation_key
        self.return_to_go_key = return_to_go_key
        self.step_count_key = step_count_key
        self.action_key = action_key
        self.in_keys = [observation_key, return_to_go_key, step_count_key]
        self.out_keys = [action_key]
        self._n = None  # number of envs the buffers were built for

    # -- context buffers -------------------------------------------------------------------
    def _allocate(self, n: int, device, dtype) -> None:
        c, k = self.dt.config, self.context_len
        self._obs = torch.zeros(n, k, c.state_dim, device=device, dtype=dtype)
        self._act = torch.zeros(n, k, c.action_dim, device=device, dtype=dtype)
        self._rtg = torch.zeros(n, k, 1, device=device, dtype=dtype)
        self._ts = torch.zeros(n, k, dtype=torch.long, device=device)
        self._valid = torch.zeros(n, k, dtype=torch.bool, device=device)  # per step, in ring order
        if self.mode == "kv_cache":
            self._cache = KVCache(self.dt.transformer.transformer.config, n, TOKENS_PER_STEP * k, device=device, dtype=dtype)
            # slot p holds tokens (a_{t-1}, R_t, s_t) of the step t written at ring position p
            self._tok_valid = torch.zeros(n, k, TOKENS_PER_STEP, dtype=torch.bool, device=device)
            self._causal3 = torch.ones(3, 3, dtype=torch.bool, device=device).tril_()
        if self.dt.config.grasp_head:  # per env and picker: the probability of no switch since the last one
            self._stay = torch.ones(n, len(self.dt.config.grasp_dims), device=device, dtype=dtype)
            self._grasp_index = torch.tensor(self.dt.config.grasp_dims, device=device)
        self._ptr = 0
        self._n = n

    def reset(self) -> None:
        """Forget all context (all envs)."""
        self._n = None

    # -- one step ----------------------------------------------------------------------------
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(self.observation_key)
        rtg = tensordict.get(self.return_to_go_key)
        step_count = tensordict.get(self.step_count_key)
        c = self.dt.config
        batch = tuple(tensordict.batch_size)
        for name, x, width in ((self.observation_key, obs, c.state_dim), (self.return_to_go_key, rtg, 1), (self.step_count_key, step_count, 1)):
            if tuple(x.shape) != (*batch, width):
                raise ValueError(f"DTActingPolicy: {name!r} has shape {tuple(x.shape)}, expected {(*batch, width)}")
        n = 1
        for s in batch:
            n *= s
        if n == 0:
            raise ValueError(f"DTActingPolicy: empty batch: {self.observation_key!r} has shape {tuple(obs.shape)}")
        for name, x in ((self.observation_key, obs), (self.return_to_go_key, rtg)):
            if x.is_floating_point() and not bool(torch.isfinite(x).all()):
                bad = (~torch.isfinite(x)).reshape(n, -1).any(-1).nonzero().flatten().tolist()
                raise ValueError(f"DTActingPolicy: {name!r} holds NaN or inf values (envs {bad} of batch {batch}); "
                                 f"refused, since it would stay in the acting context until the next reset")
        # run on the actor's device/dtype (e.g. CPU envs with a GPU policy); the action goes back
        # to the device of the input observation
        param = self.dt.head_loc.weight
        out_device = obs.device
        obs = obs.reshape(n, c.state_dim).to(param.device, param.dtype)
        rtg = rtg.reshape(n, 1).to(param.device, param.dtype)
        step_count = step_count.reshape(n).to(param.device, torch.long)
        with torch.no_grad():
            if self._n != n or self._obs.device != obs.device:
                self._allocate(n, obs.device, obs.dtype)
            grasp = self.dt.config.grasp_head and self._deterministic()
            if grasp:
                prev_closed = self._previous_grasps(step_count)
            params = self._step(obs, rtg, step_count)
            if grasp:
                action = self._median_switch(params, prev_closed)
            else:
                small = TensorDict(dict(zip(self._dist_keys, params)), batch_size=[n])
                action = self._prob_module(small).get(self._prob_module.out_keys[0])
            self._act[:, self._ptr] = action
            self._ptr = (self._ptr + 1) % self.context_len
        tensordict.set(self.action_key, action.reshape(*batch, c.action_dim).to(out_device))
        return tensordict

    # -- the grasp head's deterministic grasp ---------------------------------------------------
    def _deterministic(self) -> bool:
        mode = interaction_type() or self._prob_module.default_interaction_type
        return mode in (InteractionType.DETERMINISTIC, InteractionType.MODE)

    def _previous_grasps(self, step_count: torch.Tensor) -> torch.Tensor:
        """Each env's grasp commands at its previous step ``[N, P]`` (open after a reset)."""
        prev = (self._ptr - 1) % self.context_len
        had = self._valid[:, prev] & (step_count != 0)
        self._stay[step_count == 0] = 1.0
        return (self._act[:, prev].index_select(-1, self._grasp_index) > 0) & had[:, None]

    def _median_switch(self, params, prev_closed: torch.Tensor) -> torch.Tensor:
        # A grasp is a switch in time: at each step the head gives the probability of switching (closing
        # an open picker, opening a closed one) given that it has not switched so far. Sampled, the switch
        # comes at some step; deterministically it comes at that time's median, the step where the
        # probability of having switched since the last switch reaches one half. Where the probability is
        # spread over several steps (a close timed from the timestep), the argmax of each step alone may never
        # close. Small doubts add up too: a hold at 0.99 per step would release after 69 steps, so the rule
        # needs a head that reads its own past grasps (DTModelConfig refuses a grasp head with hidden grasp
        # commands) and is confident while it holds.
        dist = GraspConditionedTanhNormal(*params, grasp_dims=self.dt.config.grasp_dims)
        p_closed = torch.sigmoid(dist.grasp_logits)
        self._stay *= torch.where(prev_closed, p_closed, 1.0 - p_closed)
        switch = self._stay <= 0.5
        self._stay[switch] = 1.0
        return dist.action_for(prev_closed ^ switch)

    def _step(self, obs, rtg, step_count):
        k, p = self.context_len, self._ptr
        prev = (p - 1) % k
        reset = step_count == 0
        self._valid[reset] = False
        # the previous step's action token (kv mode), read before slot p is overwritten (K == 1)
        a_prev, ts_prev = self._act[:, prev].clone(), self._ts[:, prev].clone()
        has_prev = self._valid[:, prev].clone()
        self._obs[:, p] = obs
        self._rtg[:, p] = rtg
        self._ts[:, p] = step_count
        self._act[:, p] = 0.0  # unknown yet; it follows s_t, so causality makes its value irrelevant
        self._valid[:, p] = True
        if self.mode == "window":
            order = (torch.arange(k, device=obs.device) + p + 1) % k  # oldest -> newest
            h = self.dt.transformer(
                self._obs[:, order], self._act[:, order], self._rtg[:, order], self._ts[:, order], self._valid[:, order]
            )[:, -1]
            return self.dt.head(h)
        # kv_cache mode
        self._tok_valid[reset] = False
        self._tok_valid[:, p, 0] = has_prev
        self._tok_valid[:, p, 1:] = True
        # the oldest step in the window lost its preceding action (a_{t-K} is not in the window)
        self._tok_valid[:, (p + 1) % k, 0] = False
        dtm = self.dt.transformer
        dtm._check_timestep(step_count)
        t_now = dtm.embed_timestep(step_count)
        tokens = torch.stack(
            (
                dtm.embed_past_action(a_prev) + dtm.embed_timestep(ts_prev),
                dtm.embed_return(rtg) + t_now,
                dtm.embed_state(obs) + t_now,
            ),
            dim=1,
        )  # [N, 3, D]
        n = obs.shape[0]
        attn = self._tok_valid.view(n, 1, 1, k * TOKENS_PER_STEP).expand(n, 1, TOKENS_PER_STEP, k * TOKENS_PER_STEP).clone()
        cols = slice(TOKENS_PER_STEP * p, TOKENS_PER_STEP * (p + 1))
        attn[:, :, :, cols] &= self._causal3
        attn[:, :, :, cols] |= torch.eye(TOKENS_PER_STEP, dtype=torch.bool, device=obs.device)  # never an empty row
        slots = torch.arange(cols.start, cols.stop, device=obs.device)
        h = dtm.forward_cached(tokens, self._cache, slots, attn)[:, 2]  # output at s_t
        return self.dt.head(h)
