"""Many seeds of one experiment as one agent: member agents stacked along a leading axis.

:class:`AgentBatch` takes ``N`` :class:`~imssr.agents.sac.SACAgent` members of one configuration
(one seed each; they may differ in the intrinsic reward's scalars) and trains them in lockstep:
every parameter, Adam moment and target weight is stored once as an ``(N, ...)`` tensor, and
each piece of the single agent's update (:class:`~imssr.agents.sac.Eager`'s ``call``, ``step``
and ``read``) runs once for all members:

* ``call``: ``torch.func.functional_call`` of the single agent's own code on each member's
  weights, in one of two ways (``mode``): ``vmap`` maps it over the members with
  ``torch.func.vmap``, so a convolution runs grouped over the members and a linear layer as one
  batched matmul, and the number of kernels does not grow with ``N`` (what a GPU wants);
  ``loop`` runs it member after member, the very ops of a run alone (what a CPU wants: its
  grouped convolutions are slow, and a kernel launch costs nothing; ``bench/seeds.py``).
  ``auto``: ``vmap`` on CUDA, ``loop`` on the CPU.  Random draws come from each member's own
  generators (:mod:`imssr.draws`), in the order its run alone draws them.
* ``step``: the backward of the members' summed losses gives each member exactly its own
  gradient (a member's loss reads only its own weights), and one Adam over the stacked weights
  is ``N`` Adams: its update is element by element and all members share the step count.
* ``read``: soft target updates and the temperature, element by element on the stacked weights.

So a member is the run it would be alone: the same weights, draws and arithmetic, only grouped
(``tests/test_agent_batch.py`` checks it to float64 rounding under ``vmap``, bit for bit under
``loop``).  A member's state is a single
agent's (:meth:`AgentBatch.member_state_dict`), so every seed's checkpoint is a standard one.
"""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any, Optional, Sequence

import torch
from torch import nn
from torch.func import functional_call, vmap

from imssr import draws
from imssr.agents.graphs import set_capturable
from imssr.agents.sac import GENERATORS, Eager, Metrics, SACAgent, restore_generators
from imssr.batch import Batch
from imssr.config import IntrinsicConfig
from imssr.config.batching import agent_refusal
from imssr.errors import ImssrError
from imssr.intrinsic.reward import STAT_KEYS, BetaSchedule
from imssr.settings import BATCH_LAYOUTS

if TYPE_CHECKING:
    import numpy as np

MODES = BATCH_LAYOUTS
"""How a batch runs its members' computation (``agent.batch_layout``; see the module's doc;
``streams``: :class:`~imssr.agents.members.Members`)."""


def resolve_mode(mode: str, device: torch.device) -> str:
    """``mode`` with ``auto`` resolved for ``device``: ``vmap`` on CUDA, ``loop`` elsewhere."""
    if mode not in MODES:
        raise ImssrError(f"unknown seed-batch layout {mode!r}; valid: {', '.join(MODES)}")
    if mode == "auto":
        return "vmap" if device.type == "cuda" else "loop"
    return mode


def batch_refusal(members: Sequence[SACAgent], stacked: bool = True) -> Optional[str]:
    """Why ``members`` cannot train as one batch (one line), or None; ``stacked``: as one
    :class:`AgentBatch` of stacked weights, which also needs every member to hold the same
    tensors."""
    first = members[0]
    if agent_refusal(first.cfg):
        return agent_refusal(first.cfg)
    for m in members[1:]:
        if (m.cfg, m.obs_shape, m.action_dim, m.device) != (first.cfg, first.obs_shape, first.action_dim, first.device):
            return "the members of one batch must share the agent's settings, observation and action shapes"
        if (m.aux is None) != (first.aux is None) or (m.aux is not None and m.aux.cfg != first.aux.cfg):
            return "the members of one batch must share the auxiliary task's settings"
    enabled = [m for m in members if m.intrinsic is not None]
    for m in enabled[1:]:
        if _without_beta(m.intrinsic.cfg) != _without_beta(enabled[0].intrinsic.cfg):
            return "the members of one batch may differ in intrinsic.beta0 and intrinsic.enabled only"
    if stacked and enabled and len(enabled) < len(members) and any(True for _ in enabled[0].signal.parameters()):
        return (f"the {enabled[0].signal.name} signal has weights of its own: members with and without it "
                "train in separate batches")
    return None


def _without_beta(cfg: IntrinsicConfig) -> IntrinsicConfig:
    return dataclasses.replace(cfg, beta0=0.0)


class MemberSchedules:
    """The members' beta schedules in place of one: ``beta_t`` of the current member (0 for a
    member without the intrinsic reward), as a 0-dim tensor inside the members' vmap."""

    def __init__(self, schedules: Sequence[Optional[BetaSchedule]], device: torch.device):
        self.schedules, self.device = list(schedules), device

    def __call__(self, step: int) -> torch.Tensor:
        return draws.member_values(self._values(step), torch.float64, self.device)

    def tensor(self, step: int, device: torch.device) -> torch.Tensor:
        """The members' ``beta_t`` as one ``(N,)`` float64 tensor (a CUDA graph's input, which the
        members' vmap maps over).  From pinned memory on CUDA: a copy from pageable memory would
        wait for the device."""
        values = torch.tensor(self._values(step), dtype=torch.float64)
        if torch.device(device).type == "cuda":
            values = values.pin_memory()
        return values.to(device, non_blocking=True)

    def _values(self, step: int) -> list[float]:
        return [0.0 if s is None else s(step) for s in self.schedules]


class _Call(nn.Module):
    """The template agent's modules under one root, so that ``functional_call`` swaps in the
    members' weights everywhere the single agent's code reads them."""

    def __init__(self, modules: dict[str, nn.Module]):
        super().__init__()
        self.agent = nn.ModuleDict(modules)

    def forward(self, fn, *args):
        return fn(*args)


class MemberExecution(Eager):
    """Runs the single agent's update pieces once for all members (see the module's doc)."""

    def __init__(self, root: _Call, stacked: dict[str, torch.Tensor], optimizers: dict[int, torch.optim.Optimizer],
                 n: int, mode: str):
        self.root, self.stacked, self.optimizers, self.n, self.mode = root, stacked, optimizers, n, mode

    def call(self, fn, *args):
        specs = [_split(a) for a in args]
        tensors = [t for t, _ in specs]
        if self.mode == "loop":
            outs = []
            for i in range(self.n):
                weights = {name: value[i] for name, value in self.stacked.items()}
                member_args = [_join(_row(t, i), static) for t, (_, static) in zip(tensors, specs)]
                with draws.member(i):
                    outs.append(_tensors(functional_call(self.root, weights, (fn, *member_args), strict=True)))
            return _stack(outs)
        in_dims = (0, *[None if t is None else 0 for t in tensors])

        def member(weights, *member_tensors):
            rebuilt = [_join(t, static) for t, (_, static) in zip(member_tensors, specs)]
            return _tensors(functional_call(self.root, weights, (fn, *rebuilt), strict=True))

        return vmap(member, in_dims=in_dims, randomness="same")(self.stacked, *tensors)

    def step(self, loss: torch.Tensor, *optimizers: torch.optim.Optimizer) -> None:
        # d(sum_i L_i)/d theta_i = dL_i/d theta_i: each member's own gradient, exactly.
        super().step(loss.sum(), *(self.optimizers[id(o)] for o in optimizers))

    def read(self, fn):
        return functional_call(self.root, self.stacked, (fn,), strict=True)


def _split(arg) -> tuple[Any, Any]:
    """An argument as (what vmap maps over, what stays as it is)."""
    if isinstance(arg, (torch.Tensor, dict)):
        return arg, None
    if isinstance(arg, Batch):
        fields = {f.name: getattr(arg, f.name) for f in dataclasses.fields(arg)}
        return ({k: v for k, v in fields.items() if isinstance(v, torch.Tensor)},
                ("batch", {k: v for k, v in fields.items() if not isinstance(v, torch.Tensor)}))
    return None, ("value", arg)


def _join(tensors, static):
    if static is None:
        return tensors
    kind, value = static
    return Batch(**tensors, **value) if kind == "batch" else value


def _row(tensors, i: int):
    if tensors is None:
        return None
    if isinstance(tensors, dict):
        return {k: v[i] for k, v in tensors.items()}
    return tensors[i]


def _stack(outs: list):
    """The members' outputs (same structure) as one, each tensor stacked on a leading axis."""
    first = outs[0]
    if isinstance(first, dict):
        return {k: _stack([o[k] for o in outs]) for k in first}
    if isinstance(first, (tuple, list)):
        return type(first)(_stack(list(parts)) for parts in zip(*outs))
    return torch.stack(outs)


def _stacked_like(values: list[torch.Tensor], like: torch.Tensor) -> torch.Tensor:
    """``values`` stacked on a new leading axis, each row laid out as ``like`` (a channels-last
    convolution weight stays channels-last: a member's row is then its run's very tensor)."""
    if like.dim() == 4 and like.is_contiguous(memory_format=torch.channels_last) and not like.is_contiguous():
        o, i, h, w = like.shape
        out = torch.empty((len(values), o, h, w, i), dtype=like.dtype, device=like.device).permute(0, 1, 4, 2, 3)
        return out.copy_(torch.stack(values))
    return torch.stack(values)


def _tensors(out):
    """``out`` with its Python numbers as tensors (vmap returns tensors only)."""
    if isinstance(out, dict):
        return {k: _tensors(v) for k, v in out.items()}
    if isinstance(out, (tuple, list)):
        return type(out)(_tensors(v) for v in out)
    if isinstance(out, (int, float)):
        return torch.tensor(out)
    return out


class _StackedReplay:
    """The members' replay buffers as one: a sample is each member's own draw, stacked."""

    def __init__(self, replays: Sequence):
        self.replays = replays

    def sample_batch(self, batch_size: int, device) -> dict[str, torch.Tensor]:
        samples = [r.sample_batch(batch_size, device) for r in self.replays]
        return {k: torch.stack([s[k] for s in samples]) for k in samples[0]}


class AgentBatch:
    """``N`` member agents of one configuration trained as one (see the module's doc)."""

    def __init__(self, members: Sequence[SACAgent], mode: str = "auto"):
        if not members:
            raise ImssrError("a batch of agents needs at least one member")
        reason = batch_refusal(members)
        if reason is not None:
            raise ImssrError(reason)
        self.n = len(members)
        self.mode = resolve_mode(mode, members[0].device)
        if self.mode == "streams":
            raise ImssrError("the streams layout keeps each member's own agent: build it with make_batch")
        self.intrinsic_on = [m.intrinsic is not None for m in members]
        self.template = t = next((m for m in members if m.intrinsic is not None), members[0])
        self.root = _Call(self._modules_of(t))
        member_roots = [dict(_Call(self._modules_of(m)).named_parameters()) for m in members]
        member_buffers = [dict(_Call(self._modules_of(m)).named_buffers()) for m in members]
        template_params = dict(self.root.named_parameters())
        self.stacked: dict[str, torch.Tensor] = {}
        for name, like in template_params.items():
            values = _stacked_like([_member_value(r, name, template_params).detach() for r in member_roots], like)
            self.stacked[name] = nn.Parameter(values, requires_grad=like.requires_grad)
        template_buffers = dict(self.root.named_buffers())
        for name, like in template_buffers.items():
            self.stacked[name] = _stacked_like([_member_value(b, name, template_buffers) for b in member_buffers], like)
        self.name_of = {id(p): name for name, p in template_params.items()}
        self.optimizers = {id(opt): self._stacked_optimizer(opt) for opt in t.optimizers()}
        for i, m in enumerate(members):
            for opt, member_opt in zip(t.optimizers(), m.optimizers()):
                self._set_member_optimizer_state(self.optimizers[id(opt)], i, member_opt.state_dict())
        for attr, _ in GENERATORS:
            setattr(t, attr, draws.MemberGenerators([getattr(m, attr) for m in members]))
        if t.intrinsic is not None:
            t.intrinsic.schedule = MemberSchedules([m.intrinsic.schedule if m.intrinsic is not None else None
                                                    for m in members], t.device)
        t.updates = members[0].updates
        t.run = MemberExecution(self.root, self.stacked, self.optimizers, self.n, self.mode)
        t.graphs.prepare = lambda: set_capturable(self.optimizers.values(), True)

    # -- building -------------------------------------------------------------------
    @staticmethod
    def _modules_of(agent: SACAgent) -> dict[str, nn.Module]:
        return {"nets": agent.nets, **({"aux": agent.aux} if agent.aux is not None else {}),
                **({"signal": agent.signal} if agent.signal is not None else {})}

    def _stacked_optimizer(self, opt: torch.optim.Optimizer) -> torch.optim.Optimizer:
        """The template's optimiser rebuilt over the stacked weights: same class, groups and
        settings, so that its state dict has the single agent's layout."""
        groups = [{**{k: v for k, v in g.items() if k != "params"},
                   "params": [self.stacked[self.name_of[id(p)]] for p in g["params"]]} for g in opt.param_groups]
        return type(opt)(groups, **opt.defaults)

    def _set_member_optimizer_state(self, stacked_opt: torch.optim.Optimizer, i: int, member_state: dict) -> None:
        params = [p for g in stacked_opt.param_groups for p in g["params"]]
        for index, values in member_state["state"].items():
            param = params[index]
            state = stacked_opt.state[param]
            for key, value in values.items():
                if key != "step" and isinstance(value, torch.Tensor) and value.shape == param.shape[1:]:
                    if key not in state:
                        state[key] = torch.zeros_like(param, dtype=value.dtype)
                    state[key][i].copy_(value)
                else:  # the step count: one for all members (they step in lockstep)
                    state[key] = value.clone() if isinstance(value, torch.Tensor) else value

    # -- the members' runs ------------------------------------------------------------
    def update(self, replays: Sequence, step: int) -> Metrics:
        """All updates of agent step ``step`` for every member, each sampling its own replay
        buffer (``replays[i]``); metrics are ``(N,)`` tensors (:meth:`member_metrics`)."""
        if len(replays) != self.n:
            raise ImssrError(f"{len(replays)} replay buffers for {self.n} members")
        return self.template.update(_StackedReplay(replays), step)

    def act(self, obs, deterministic: bool) -> torch.Tensor:
        """Each member's action ``(N, |A|)`` for its own observation stack ``obs[i]``."""
        t = self.template
        x = torch.as_tensor(obs, device=t.device).unsqueeze(1)
        return t.graphs(("act", deterministic), lambda inputs: t.act_on(inputs, deterministic), {"obs": x})[:, 0]

    @torch.no_grad()
    def member_act(self, i: int, obs) -> "np.ndarray":
        """Member ``i``'s deterministic action for one observation stack (evaluation): the single
        agent's pass on the member's weights."""
        t = self.template
        x = torch.as_tensor(obs, device=t.device).unsqueeze(0)
        weights = {name: value[i] for name, value in self.stacked.items()}
        with t.autocast():
            action = functional_call(self.root, weights, (t.policy_action, x, True), strict=True)
        return action[0].cpu().numpy().astype("float32")

    def member_metrics(self, metrics: Metrics, i: int) -> Metrics:
        """Member ``i``'s metrics, with only the keys its run alone logs."""
        return {k: v[i] for k, v in metrics.items() if self.intrinsic_on[i] or k not in STAT_KEYS}

    def member_state_dict(self, i: int) -> dict:
        """Member ``i``'s state in :meth:`SACAgent.state_dict`'s layout (what its run alone
        would save)."""
        t = self.template

        def module_state(prefix: str, module: nn.Module) -> dict:
            return {k: self.stacked[f"agent.{prefix}.{k}"][i].detach().clone() for k in module.state_dict()}

        state = {"nets": module_state("nets", t.nets)}
        for key, opt in zip(("critic_opt", "actor_opt", "alpha_opt"), (t.critic_opt, t.actor_opt, t.alpha_opt)):
            state[key] = self._member_optimizer_state(self.optimizers[id(opt)], i)
        for attr, _ in GENERATORS:
            state[attr] = getattr(t, attr).generators[i].get_state()
        state["updates"] = t.updates
        for key, module in (("aux", t.aux), ("signal", t.signal)):
            if module is None or (key == "signal" and not self.intrinsic_on[i]):
                continue
            full = {"module": module_state(key, module)}
            if module.optimizer is not None:
                full["optimizer"] = self._member_optimizer_state(self.optimizers[id(module.optimizer)], i)
            state[key] = full
        return state

    def _member_optimizer_state(self, stacked_opt: torch.optim.Optimizer, i: int) -> dict:
        full = stacked_opt.state_dict()
        params = [p for g in stacked_opt.param_groups for p in g["params"]]
        state = {}
        for index, values in full["state"].items():
            shape = params[index].shape
            state[index] = {k: ((v[i] if k != "step" and v.shape == shape else v).clone()
                                if isinstance(v, torch.Tensor) else v) for k, v in values.items()}
        return {"state": state, "param_groups": full["param_groups"]}

    def load_member_state_dict(self, i: int, state: dict, restore_rng: bool = True) -> None:
        """Set member ``i`` from a single agent's :meth:`SACAgent.state_dict` (its own checkpoint);
        its generators too, unless ``restore_rng`` is false, as :meth:`SACAgent.load_state_dict`
        does (a state saved on another device type reseeds them)."""
        t = self.template
        with torch.no_grad():
            for prefix, module_state in (("nets", state["nets"]), ("aux", state.get("aux", {}).get("module")),
                                         ("signal", state.get("signal", {}).get("module"))):
                for k, v in (module_state or {}).items():
                    self.stacked[f"agent.{prefix}.{k}"][i].copy_(v)
        for key, opt in zip(("critic_opt", "actor_opt", "alpha_opt"), (t.critic_opt, t.actor_opt, t.alpha_opt)):
            self._set_member_optimizer_state(self.optimizers[id(opt)], i, state[key])
        for key, module in (("aux", t.aux), ("signal", t.signal)):
            if module is not None and module.optimizer is not None and key in state:
                self._set_member_optimizer_state(self.optimizers[id(module.optimizer)], i, state[key]["optimizer"])
        t.updates = state["updates"]
        set_capturable(self.optimizers.values(), t.graphs.record)
        t.graphs.reset()
        if restore_rng:
            restore_generators({key: getattr(t, key).generators[i] for key, _ in GENERATORS}, state, t.updates)


def _member_value(named: dict[str, torch.Tensor], name: str, template: dict[str, torch.Tensor]) -> torch.Tensor:
    """A member's tensor ``name``; a member without the intrinsic signal (only allowed for a
    signal without weights, :func:`batch_refusal`) has nothing to miss."""
    if name not in named:
        raise ImssrError(f"member without {name!r}: its batch cannot stack it")
    value = named[name]
    if value.shape != template[name].shape:
        raise ImssrError(f"{name!r} differs in shape between members")
    return value
