"""Pixel SAC with a pluggable auxiliary task and an optional intrinsic reward.

One agent step's update, :meth:`SACAgent.update`, read top to bottom (order as in the CURL / DMC-GB code bases):
  1. sample the replay buffer, the RL batch first; ``beta_t`` of the step;
  2. augment: the RL crops of o and o' (:meth:`SACAgent.to_batch`);
  3. critic, every ``critic_update_every`` steps: ``encode`` the batch once, ``bellman_target``
     on ``r + beta_t * r_int``, ``critic_loss`` over the observation views the auxiliary task
     asks for (SVEA: clean + augmented);
  4. actor and temperature, every ``actor_update_every`` steps;
  5. soft update of the target Q heads (``critic_tau``) and target encoder
     (``encoder_tau``), every ``target_update_every`` steps;
  6. the auxiliary task, every ``aux.update_every`` steps;
  7. the intrinsic signal's own networks, if it has any (RND's predictor).
``agent.update_schedule``: ``sequential`` (the reference) encodes o afresh for the actor after the critic's step;
``fused`` lets the actor reuse the critic's encoding of o, and a task that can read the critic's pass adds its loss
to the critic's backward in step 3. The time limit is not terminal: ``discount`` is 0 only for true terminal states.
"""
from __future__ import annotations

import copy
import math
from dataclasses import replace
from typing import Optional

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from imssr.agents.generators import AgentGenerators
from imssr.agents.graphs import StepGraphs, set_capturable
from imssr.augmentations import center_crop, random_crop
from imssr.auxiliary import AuxiliaryTask
from imssr.batch import Batch, Encoding, NextObsContext
from imssr.config import AgentConfig
from imssr.errors import ImssrError
from imssr.intrinsic import BetaSchedule, IntrinsicReward, IntrinsicSignal
from imssr.networks import Actor, ConvTrunk, Critic, Encoder, ema, weight_init
from imssr.precision import autocast, full_precision, optimizer_step, upcast
from imssr.replay import FrameReplayBuffer

Metrics = dict[str, "torch.Tensor | float"]

Inputs = dict[str, "torch.Tensor | float | dict[str, torch.Tensor]"]
"""What one update reads besides the agent's own state: ``sample`` (the RL batch from the replay
buffer), ``aux_sample`` (the auxiliary task's own batch, when it trains on one at this step) and
``beta`` (``beta_t``, with an intrinsic reward: a float, or under ``agent.cuda_graphs`` a
float64 0-dim tensor, which a recording reads as its input)."""

Beta = Optional["float | torch.Tensor"]
"""``beta_t`` as an update hands it down (see :data:`Inputs`); None without an intrinsic reward."""


class SACNetworks(nn.Module):
    """Critic (owning the conv trunk), its target copy, the actor and log alpha."""

    def __init__(self, obs_channels: int, action_dim: int, cfg: AgentConfig):
        super().__init__()
        trunk = ConvTrunk(obs_channels, cfg.crop_size, cfg.encoder_layers, cfg.encoder_filters,
                          cfg.encoder_head_layers, cfg.channels_last, cfg.final_relu)
        self.critic = Critic(Encoder(trunk, cfg.feature_dim, cfg.projection_tanh), action_dim, cfg.hidden_dim,
                             q_heads_fp32=cfg.q_heads_fp32)
        self.actor = Actor(trunk.out_dim, cfg.feature_dim, action_dim, cfg.hidden_dim,
                           cfg.log_std_min, cfg.log_std_max, cfg.projection_tanh)
        self.apply(weight_init)
        self.critic_target = copy.deepcopy(self.critic)
        for p in self.critic_target.parameters():
            p.requires_grad_(False)
        self.log_alpha = nn.Parameter(torch.tensor(math.log(cfg.init_temperature)))


class SACAgent:
    """SAC from pixels; ``aux`` and ``intrinsic`` are plug-ins.  Built complete by
    :func:`imssr.agents.build.make_agent`, which makes every part handed in here."""

    def __init__(self, obs_shape: tuple[int, ...], action_dim: int, cfg: AgentConfig, nets: SACNetworks,
                 optimizers: tuple[torch.optim.Optimizer, ...], generators: AgentGenerators, graphs: StepGraphs,
                 aux: Optional[AuxiliaryTask] = None, fuse_aux: bool = False,
                 intrinsic: Optional[IntrinsicReward] = None, schedule: Optional[BetaSchedule] = None,
                 signal: Optional[IntrinsicSignal] = None):
        self.cfg, self.nets, self.obs_shape, self.action_dim = cfg, nets, tuple(obs_shape), action_dim
        self.device = graphs.device  # the device the agent was built for, as named
        self.target_entropy = -float(action_dim)
        self.critic_opt, self.actor_opt, self.alpha_opt = optimizers
        """SAC's optimisers: the critic's (the conv trunk's too), the actor's (its projection and
        MLP: the trunk is the critic's) and the temperature's."""
        self.generators = generators
        self.gen, self.noise_gen, self.intrinsic_gen = generators.all()
        self.graphs = graphs
        """Runs :meth:`learn` and :meth:`act_on`: directly, or recorded as CUDA graphs under
        ``agent.cuda_graphs`` (:mod:`imssr.agents.graphs`)."""
        self.aux = aux
        self.fuse_aux = fuse_aux
        """Whether the task's loss is read from the critic's pass and joins its backward: the fused
        schedule, a task that can (:attr:`AuxiliaryTask.reads_critic_pass`), on the RL batch (a
        batch of its own needs a pass of its own)."""
        self.intrinsic, self.schedule, self.signal = intrinsic, schedule, signal
        self.updates = 0

    def autocast(self):
        """The context of the agent's forward passes: bfloat16 autocast under
        ``agent.precision = bf16`` (:mod:`imssr.precision`), else none."""
        return autocast(self.device, self.cfg.precision)

    @property
    def alpha(self) -> torch.Tensor:
        return self.nets.log_alpha.exp()

    # -- acting ------------------------------------------------------------------
    @torch.no_grad()
    def act(self, obs: np.ndarray, deterministic: bool) -> np.ndarray:
        """Action in [-1, 1] for one stacked uint8 observation (centre crop)."""
        x = torch.as_tensor(obs, device=self.device).unsqueeze(0)
        action = self.graphs(("act", deterministic), lambda inputs: self.act_on(inputs, deterministic), {"obs": x})
        return action[0].cpu().numpy().astype(np.float32)

    def act_on(self, inputs: dict[str, torch.Tensor], deterministic: bool) -> torch.Tensor:
        """:meth:`policy_action` on ``inputs["obs"]`` (what :meth:`act` runs or records)."""
        with torch.no_grad(), self.autocast():
            return self.policy_action(inputs["obs"], deterministic)

    def policy_action(self, obs: torch.Tensor, deterministic: bool) -> torch.Tensor:
        """Actions ``(B, |A|)`` for a batch of uint8 observation stacks (centre crop); a sample
        from :attr:`noise_gen` unless ``deterministic``."""
        trunk = self.nets.critic.encoder.trunk(center_crop(obs, self.cfg.crop_size))
        return self.nets.actor(trunk, generator=self.noise_gen, sample=not deterministic).action

    # -- learning ----------------------------------------------------------------
    def update(self, replay: FrameReplayBuffer, step: int) -> Metrics:
        """All updates of one agent step; ``step`` counts agent steps.  Metrics stay on the
        device (the training loop reads them once per episode): no host sync in an update.
        The host's part (the replay samples, ``beta_t``) is done here; :meth:`learn` does the
        rest, run as it is or recorded under ``agent.cuda_graphs``: one recording per
        :meth:`update_key`."""
        inputs: Inputs = {"sample": replay.sample_batch(self.cfg.batch_size, self.device)}
        if self.aux_due(step) and self.aux.cfg.own_batch:
            inputs["aux_sample"] = replay.sample_batch(self.aux.cfg.batch_size, self.device)
        if self.schedule is not None:
            beta = self.schedule(step)
            # A recording reads beta from its input: a fill, not a copy from the host, which
            # would wait for the device.
            inputs["beta"] = torch.full((), beta, dtype=torch.float64, device=self.device) \
                if self.graphs.enabled else beta
        metrics = self.graphs(("update", *self.update_key(step)), lambda x: self.learn(x, step), inputs)
        self.updates += 1
        return metrics

    def learn(self, inputs: Inputs, step: int) -> Metrics:
        """The update of agent step ``step`` on its replay samples and ``beta_t`` (:data:`Inputs`),
        in the order of the module's doc."""
        c, metrics, trunk = self.cfg, {}, None
        batch = self.to_batch(inputs["sample"])
        fuse = self.fuse_aux and self.aux_due(step)
        with self.autocast():
            if step % c.critic_update_every == 0:
                critic_metrics, trunk = self.update_critic(batch, inputs.get("beta"), fuse, step)
                metrics.update(critic_metrics)
            if step % c.actor_update_every == 0:
                metrics.update(self.update_actor_and_alpha(batch, trunk))
            if step % c.target_update_every == 0:
                self.soft_update_targets()
            if self.aux_due(step) and not fuse:
                metrics.update(self.update_aux(inputs, batch, step))
            if self.signal is not None:
                metrics.update(self.update_signal(batch))
        return metrics

    def update_key(self, step: int) -> tuple[bool, ...]:
        """Which parts of the update run at agent step ``step``: the critic, the actor and temperature, the target
        EMA, the auxiliary task.  Everything else an update does is the same at every step."""
        c = self.cfg
        return (step % c.critic_update_every == 0, step % c.actor_update_every == 0,
                step % c.target_update_every == 0, self.aux_due(step))

    def beta(self, step: int) -> Optional[float]:
        """``beta_t`` at agent step ``step`` (:class:`~imssr.intrinsic.BetaSchedule`); None without
        an intrinsic reward."""
        return None if self.schedule is None else self.schedule(step)

    def to_batch(self, sample: dict[str, np.ndarray | torch.Tensor]) -> Batch:
        """The update's :class:`Batch` from a replay sample (arrays, or tensors already on the
        agent's device: :meth:`FrameReplayBuffer.sample_batch`, taken as they are): the RL crops
        of o and o' (drawn from :attr:`gen`, o first), the transition's fields as columns."""
        d, size = self.device, self.cfg.crop_size
        sample = {k: torch.as_tensor(sample[k], device=d) for k in ("obs", "next_obs", "action", "reward", "discount")}
        return Batch(obs=random_crop(sample["obs"], size, self.gen), action=sample["action"],
                     reward=sample["reward"].unsqueeze(-1), discount=sample["discount"].unsqueeze(-1),
                     next_obs=random_crop(sample["next_obs"], size, self.gen), raw_obs=sample["obs"],
                     raw_next_obs=sample["next_obs"], generator=self.gen)

    def update_critic(self, batch: Batch, beta: Beta, fuse: bool, step: int) -> tuple[Metrics, Optional[torch.Tensor]]:
        """The critic's step, with the task's loss read from its pass if ``fuse`` (each optimiser steps its own
        parameters, the shared encoder's once, the critic's, on the summed gradient; then the task's
        :meth:`AuxiliaryTask.after_step`).  Returns its metrics and, under the fused schedule, the pass's trunk of
        o, detached (the actor's input, as DrQ-v2); else None (the actor encodes o afresh after this step)."""
        loss, metrics, trunk = self.fused_objective(batch, beta, with_task_loss=fuse)
        optimizer_step(loss, self.critic_opt, *([self.aux.optimizer] if fuse else []))
        if fuse:
            self.aux.after_step(step)
        return metrics, (trunk if self.cfg.update_schedule == "fused" else None)

    def critic_objective(self, batch: Batch, beta: Beta) -> tuple[torch.Tensor, Metrics]:
        """The sequential schedule's critic loss (:meth:`critic_loss` on a fresh :meth:`encode`
        of ``batch`` and its :meth:`bellman_target` with ``beta_t = beta``) and its metrics."""
        loss, metrics, _ = self.fused_objective(batch, beta, with_task_loss=False)
        return loss, metrics

    def fused_objective(self, batch: Batch, beta: Beta,
                        with_task_loss: bool) -> tuple[torch.Tensor, Metrics, torch.Tensor]:
        """The critic's loss on one :meth:`encode` of ``batch`` and its :meth:`bellman_target`,
        plus the task's mean per-sample loss read from the same pass if ``with_task_loss``; the
        metrics; and that pass's trunk of o, detached (the fused schedule's actor input)."""
        enc = self.encode(batch, with_task_loss=with_task_loss)
        target_q, metrics = self.bellman_target(batch, enc, beta)
        loss, q_mean = self.critic_loss(batch, enc, target_q)
        if with_task_loss:  # its metric before the critic's, as the fused update always listed them
            aux_loss = enc.aux_loss.mean()
            metrics["aux_loss"] = aux_loss.detach()
        metrics.update(critic_loss=loss.detach(), q_mean=q_mean)
        return (loss + aux_loss if with_task_loss else loss), metrics, enc.obs_trunk.detach()

    def encode(self, batch: Batch, with_task_loss: bool = False) -> Encoding:
        """The update's encoder passes (:class:`~imssr.batch.Encoding`): the online trunk over the critic's views of
        o in one pass, with grad; o' through the online trunk and the target encoder, without.  ``with_task_loss``:
        the auxiliary task's per-sample loss read from this pass too (``Encoding.aux_loss``; PAD's also needs o'
        with grad, in the same pass).  Computed before the Bellman target, whose intrinsic signal may reuse it
        (IM-PAD); the two draw from different generators, so the order changes no random draw."""
        trunk_net = self.nets.critic.encoder.trunk
        views = self.aux.critic_views(batch) if self.aux is not None else [(batch.obs, 1.0)]
        obs = views[0][0] if len(views) == 1 else torch.cat([v for v, _ in views])
        next_features = None
        if with_task_loss and self.aux.reads_critic_pass == "obs+next_obs":
            both = trunk_net.shared_features(torch.cat([obs, batch.next_obs]))
            features, next_features = both[:len(obs)], both[len(obs):]
        else:
            features = trunk_net.shared_features(obs)
        with torch.no_grad():
            next_trunk = trunk_net(batch.next_obs) if next_features is None \
                else trunk_net.head_features(next_features.detach())
            next_latent = self.nets.critic_target.encoder(batch.next_obs)
        enc = Encoding(view_weights=tuple(w for _, w in views), features=features,
                       trunk=trunk_net.head_features(features),  # = trunk_net(obs)
                       next_trunk=next_trunk, next_latent=next_latent, next_features=next_features)
        if with_task_loss:
            enc = replace(enc, aux_loss=self.aux.per_sample_loss(batch, enc))
        return enc

    @torch.no_grad()
    def bellman_target(self, batch: Batch, enc: Encoding, beta: Beta = None) -> tuple[torch.Tensor, Metrics]:
        """``y = r + beta_t * r_int + gamma * d * (min_i Q*_i(z*', a') - alpha log pi(a'|o'))``,
        ``a' ~ pi(. | o')``, and the intrinsic reward's statistics.  The reward is the paper's
        Eq. (1) with Algorithm 1's ``r_int``: the signal of o', normalised in the batch.
        ``beta``: ``beta_t`` (a float, or a float64 tensor under CUDA graphs)."""
        n = self.nets
        next_policy = n.actor(enc.next_trunk, generator=self.noise_gen)
        tq1, tq2 = n.critic_target.q(enc.next_latent, next_policy.action)
        reward, stats = batch.reward, {}
        if self.intrinsic is not None:
            bonus, stats = self.intrinsic(self.intrinsic_signal(batch, enc), beta)
            reward = reward + bonus
        with full_precision(tq1):
            # y in float32: r + beta r_int + gamma V' adds terms of different scales, and every
            # regression of this update aims at it.
            target_v = torch.min(upcast(tq1), upcast(tq2)) - self.alpha * next_policy.log_prob
            return reward + batch.discount * self.cfg.discount * target_v, stats

    @torch.no_grad()
    def intrinsic_signal(self, batch: Batch, enc: Encoding) -> torch.Tensor:
        """The raw per-sample signal of o' (the task's loss, RND's error, RE3's distance),
        ``(B,)``, before normalisation and beta; draws fresh views from ``intrinsic_gen`` only."""
        if self.signal is None:
            raise ImssrError("this agent has no intrinsic signal (intrinsic.enabled is false)")
        ctx = NextObsContext(batch=batch, enc=enc, generator=self.intrinsic_gen, form=self.intrinsic.cfg.form)
        return self.signal(ctx)

    def critic_loss(self, batch: Batch, enc: Encoding, target_q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``sum_v w_v (||Q1(z_v, a) - y||^2 + ||Q2(z_v, a) - y||^2)`` over the views of o, each
        regressed to the same clean target (one view of weight 1 unless a task adds some: SVEA's
        Eq. L_SVEA), and the mean Q1 of ``batch.obs`` (detached)."""
        n, views = self.nets, len(enc.view_weights)
        q1_all, q2_all = n.critic.q(n.critic.encoder.projection(enc.trunk), batch.action.repeat(views, 1))
        with full_precision(q1_all):  # the TD errors against the float32 target, in float32
            q1_all, q2_all = upcast(q1_all), upcast(q2_all)
            loss = 0.0
            for q1, q2, weight in zip(q1_all.chunk(views), q2_all.chunk(views), enc.view_weights, strict=True):
                loss = loss + weight * (F.mse_loss(q1, target_q) + F.mse_loss(q2, target_q))
            return loss, q1_all[:len(batch)].detach().mean()

    def actor_losses(self, trunk: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """SAC's policy and temperature losses on ``trunk``, the online trunk's output on ``batch.obs`` without a
        graph, and the policy's mean entropy.  The temperature's loss reads log pi detached and the actor's reads
        alpha detached: either step leaves the other's loss as it was."""
        n = self.nets
        policy = n.actor(trunk, generator=self.noise_gen)
        q1, q2 = n.critic.q(n.critic.encoder.projection(trunk), policy.action)
        with full_precision(q1):  # float32 like alpha and log pi; min Q cast up to meet them
            actor_loss = (self.alpha.detach() * policy.log_prob - torch.min(upcast(q1), upcast(q2))).mean()
        # The temperature's loss is float32 throughout: log_alpha is a float32 parameter and log pi
        # comes from the actor's float32 Gaussian.
        alpha_loss = (self.alpha * (-policy.log_prob - self.target_entropy).detach()).mean()
        log_std = policy.log_std
        entropy = 0.5 * log_std.shape[1] * (1.0 + math.log(2 * math.pi)) + log_std.sum(dim=-1)
        return actor_loss, alpha_loss, entropy.detach().mean()

    def update_actor_and_alpha(self, batch: Batch, trunk: Optional[torch.Tensor]) -> Metrics:
        """The actor's step, then the temperature's, on ``trunk`` (the fused schedule's encoding of o from the
        critic's pass) or on a fresh encoding of o after the critic's step; their metrics (alpha after its step)."""
        if trunk is None:
            with torch.no_grad():  # the actor never trains the convolutions: no graph
                trunk = self.nets.critic.encoder.trunk(batch.obs)
        actor_loss, alpha_loss, entropy = self.actor_losses(trunk)
        optimizer_step(actor_loss, self.actor_opt)
        optimizer_step(alpha_loss, self.alpha_opt)
        return {"actor_loss": actor_loss.detach(), "alpha": self.alpha.detach(),
                "alpha_loss": alpha_loss.detach(), "entropy": entropy}

    def aux_due(self, step: int) -> bool:
        """Whether the auxiliary task trains at agent step ``step``."""
        return self.aux is not None and self.aux.trains and step % self.aux.cfg.update_every == 0

    def update_aux(self, inputs: Inputs, batch: Batch, step: int) -> Metrics:
        """The task's own step, on the RL batch or on a batch of its own (``aux.own_batch``:
        ``inputs["aux_sample"]``, drawn after the RL batch)."""
        if self.aux.cfg.own_batch:
            batch = self.to_batch(inputs["aux_sample"])
        return self.step_aux(batch, step)

    def step_aux(self, batch: Batch, step: int) -> Metrics:
        """One step of the task's optimiser on its objective over ``batch``, then its own
        targets' momentum update (:meth:`AuxiliaryTask.after_step`)."""
        loss = self.aux.objective(batch)
        optimizer_step(loss, self.aux.optimizer)
        self.aux.after_step(step)
        return {"aux_loss": loss.detach()}

    def update_signal(self, batch: Batch) -> Metrics:
        """One step of the intrinsic signal's own networks, if it trains any (RND's predictor)."""
        if self.signal.optimizer is None:
            return {}
        loss, metrics = self.signal.objective(batch)
        optimizer_step(loss, self.signal.optimizer)
        return metrics

    @torch.no_grad()
    def soft_update_targets(self) -> None:
        n, c = self.nets, self.cfg
        ema(n.critic.q.parameters(), n.critic_target.q.parameters(), c.critic_tau)
        ema(n.critic.encoder.parameters(), n.critic_target.encoder.parameters(), c.encoder_tau)

    # -- persistence ------------------------------------------------------------
    def state_dict(self) -> dict:
        state = {
            "nets": self.nets.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "actor_opt": self.actor_opt.state_dict(),
            "alpha_opt": self.alpha_opt.state_dict(),
            **self.generators.state_dict(), "updates": self.updates,
        }
        if self.aux is not None:
            state["aux"] = self.aux.full_state_dict()
        if self.signal is not None:
            state["signal"] = self.signal.full_state_dict()
        return state

    def load_state_dict(self, state: dict, restore_rng: bool = True) -> None:
        """Load weights, optimisers and (unless ``restore_rng`` is False) random states.

        Evaluation passes ``restore_rng=False``; a checkpoint written on another device type (CPU vs CUDA generator
        states differ) reseeds the generators instead, since bit-exact resume across devices is impossible anyway.
        """
        # Optimisers adopt loaded state tensors without copying them; copy so that
        # an in-memory state (e.g. another live agent's) is never shared.
        state = copy.deepcopy(state)
        self.nets.load_state_dict(state["nets"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.alpha_opt.load_state_dict(state["alpha_opt"])
        self.updates = state["updates"]
        if restore_rng:
            self.generators.load_state_dict(state, self.updates)
        if self.aux is not None:
            self.aux.load_full_state_dict(state["aux"])
        if self.signal is not None:
            self.signal.load_full_state_dict(state["signal"])
        # A state saved under CUDA graphs holds capturable optimisers; one saved without, not.
        set_capturable(self.graphs.optimizers, self.graphs.record)
        self.graphs.reset()

