"""What a run is made of: the torch device and the agent its config describes (shared by
training and by the evaluation of a saved run), a training's parts at agent step 0
(:func:`build_training`), and a saved run's agent at one of its checkpoints (:func:`load_agent`)."""
from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np
import torch

from imssr._gl import gl_renderer, pin_egl_device, software_rendering_warning
from imssr.agents import SACAgent
from imssr.agents.build import make_agent
from imssr.algos import get_algo
from imssr.config import RunConfig
from imssr.envs import env_from_config
from imssr.envs.worker import EnvWorker
from imssr.errors import ImssrError
from imssr.precision import configure_process
from imssr.replay import make_replay_buffer
from imssr.rng import seed_everything
from imssr.rundir import RunDir
from imssr.rundir.checkpoint import Checkpoint
from imssr.seeds import TRAINING_EVAL_SEED_OFFSET, evaluation_seed
from imssr.training.state import RunState


def resolve_device(name: str) -> torch.device:
    """The torch device of ``train.device``; on CUDA, MuJoCo's EGL renders on the same GPU
    (:func:`imssr._gl.pin_egl_device`, before any env is made)."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ImssrError(f"unknown device {name!r}; use cpu, cuda, cuda:N or auto") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ImssrError(f"device {name!r} requested but CUDA is not available; use --device cpu")
    if device.type not in ("cpu", "cuda"):
        raise ImssrError(f"unsupported device {name!r}; use cpu, cuda, cuda:N or auto")
    if device.type == "cuda":
        pin_egl_device(device.index if device.index is not None else torch.cuda.current_device())
    return device


def build_agent(cfg: RunConfig, obs_shape, action_dim: int, device) -> SACAgent:
    """The agent of the run ``cfg`` on ``device`` (:func:`~imssr.agents.build.make_agent`), after
    the process-wide switches its settings ask for (:func:`~imssr.precision.configure_process`)."""
    configure_process(cfg.agent, torch.device(device))
    return make_agent(obs_shape, action_dim, cfg.agent, aux_cfg=cfg.aux if get_algo(cfg.algo).aux else None,
                      intrinsic_cfg=cfg.intrinsic, device=device, seed=cfg.train.seed)


@dataclass
class TrainingParts:
    """A training's parts besides its config and run directory: what :func:`build_training`
    makes at agent step 0 and a checkpoint saves (:class:`~imssr.training.checkpointing.Checkpointer`)."""

    env: Any
    """The training env (training footage)."""
    eval_envs: dict[str, Any]
    """The evaluation env of each scene of ``train.eval_modes`` (test footage), in that order."""
    agent: SACAgent
    """The agent."""
    replay: Any
    """The replay buffer (:func:`imssr.replay.make_replay_buffer`)."""
    state: RunState
    """The loop's counters, schedules and seed-phase generator."""

    def close(self) -> None:
        """Close the envs and the replay buffer (a frames file on disk is removed)."""
        try:
            close_envs(self.env, self.eval_envs)
        finally:
            self.replay.close()


def build_training(cfg: RunConfig, device: torch.device, replay_placement, frames_file: str,
                   reserve_slots: int) -> TrainingParts:
    """The envs, the agent, the replay buffer (where ``replay_placement`` says; frames on disk go
    in ``frames_file``, with disk space set aside for ``reserve_slots`` of them) and the loop's
    state of a training at agent step 0, in the order their random draws have always had (the
    global seed, the envs, the weights, SODA's image pool, then the streams spawned from the seed)."""
    seed_everything(cfg.train.seed)
    e = cfg.env
    # Each env in a process of its own (train.env_workers), or here.
    make = (lambda **kw: EnvWorker(functools.partial(env_from_config, e, **kw))) if cfg.train.env_workers \
        else (lambda **kw: env_from_config(e, **kw))
    # Training footage and evaluation footage come from disjoint pools.
    env = make(seed=cfg.train.seed, footage_split="train")
    eval_envs: dict[str, Any] = {}
    try:
        for mode in cfg.train.eval_mode_list(e.mode):
            eval_envs[mode] = make(seed=cfg.train.seed + TRAINING_EVAL_SEED_OFFSET, mode=mode, footage_split="test")
        if torch.cuda.is_available() and not cfg.train.env_workers:
            # On a GPU machine, a warning when MuJoCo renders through EGL on the CPU (llvmpipe).
            warning = software_rendering_warning(os.environ.get("MUJOCO_GL", "egl"), gl_renderer(env.physics),
                                                 gpu=True)
            if warning:
                print(warning, flush=True)
        action_dim = env.action_space.shape[0]
        agent = build_agent(cfg, env.observation_space.shape, action_dim, device)
        if agent.aux is not None:
            # SODA's overlay images: a bad folder fails now, not after the seed phase.
            agent.aux.load_data(device)
        # Independent streams for the replay sampler and the seed-phase actions.
        replay_seq, action_seq = np.random.SeedSequence(cfg.train.seed).spawn(2)
        if replay_placement.reason:
            print(replay_placement.reason, flush=True)
        # Each frame's physics state goes in too (float64 qpos and qvel: 32 bytes for cartpole,
        # 144 for walker): `imssr analyze` renders it again.
        replay = make_replay_buffer(replay_placement.device, cfg.train.replay_capacity,
                                    (3, e.image_size, e.image_size), action_dim, e.frame_stack,
                                    seed=replay_seq, physics_dim=env.physics_state_dim,
                                    frames_file=frames_file if replay_placement.disk else None,
                                    reserve_slots=reserve_slots)
    except BaseException:
        close_envs(env, eval_envs)
        raise
    t = cfg.train
    state = RunState.fresh(t.eval_every_steps, t.checkpoint_every_steps, t.seed_steps, action_seq)
    return TrainingParts(env, eval_envs, agent, replay, state)


def close_envs(env, eval_envs: dict) -> None:
    """Close the training env and the evaluation envs."""
    try:
        env.close()
    finally:
        for eval_env in eval_envs.values():
            eval_env.close()


def restore_agent(agent: SACAgent, ckpt: Checkpoint) -> SACAgent:
    """``agent`` with the networks of the checkpoint ``ckpt`` (a trained run's, to act and be
    evaluated: its random streams stay the agent's own); a checkpoint of another config is one
    line."""
    try:
        agent.load_state_dict(ckpt.agent, restore_rng=False)
    except (RuntimeError, KeyError, ValueError) as exc:
        raise ImssrError(f"checkpoint does not match the run's config: {str(exc).splitlines()[0]}") from None
    return agent


@dataclass
class LoadedAgent:
    """The agent of a run at one checkpoint (:func:`load_agent`)."""

    agent: SACAgent
    """The agent with the checkpoint's networks."""
    config: RunConfig
    """The run's config."""
    checkpoint: Checkpoint
    """The checkpoint as loaded."""
    note: Optional[str] = None
    """Why the checkpoint is not ``latest.pt`` when it fell back to another (None otherwise)."""
    obs_shape: tuple = ()
    """The observation shape the agent takes."""

    @property
    def step(self) -> int:
        """Agent step of the checkpoint."""
        return int(self.checkpoint.step)

    @property
    def frame(self) -> int:
        """Environment frame of the checkpoint."""
        return int(self.checkpoint.frame)


def load_agent(run: RunDir, checkpoint: Optional[str] = None, device: str = "cpu", env=None,
               verb: str = "evaluating") -> LoadedAgent:
    """The agent of the run in ``run`` at ``checkpoint`` (:meth:`RunDir.checkpoint`'s ``spec``;
    None: the latest that verifies) on ``device`` (``auto`` allowed).  ``env`` is one of the run's
    envs, whose spaces shape the agent; None builds one for that and closes it.  A checkpoint of
    another config is a one-line error."""
    run.require()
    cfg = run.read_config()
    ckpt = run.checkpoint(None if checkpoint is None else str(checkpoint), verb=verb)
    return agent_at(ckpt.checkpoint, cfg, device=device, env=env, note=ckpt.note)


def agent_at(ckpt: Checkpoint, cfg: RunConfig, device: str = "cpu", env=None,
             note: Optional[str] = None) -> LoadedAgent:
    """The agent of ``cfg`` with the networks of the loaded checkpoint ``ckpt`` (see
    :func:`load_agent`)."""
    torch_device = resolve_device(device)
    own = env is None
    if own:
        env = env_from_config(cfg.env, seed=evaluation_seed(cfg.train.seed), mode=cfg.env.mode,
                              footage_split="test")
    try:
        obs_shape = tuple(env.observation_space.shape)
        action_dim = env.action_space.shape[0]
    finally:
        if own:
            env.close()
    agent = restore_agent(build_agent(cfg, obs_shape, action_dim, torch_device), ckpt)
    return LoadedAgent(agent, cfg, ckpt, note, obs_shape)
