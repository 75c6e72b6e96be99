"""A direct dm_control wrapper with the gymnasium API and pixel observations.

Design choices, each for speed or faithfulness:
* one ``mujoco.engine.Camera`` per environment, reused for every frame (``physics.render``
  builds and frees a scene per call); only the last physics sub-step of an action repeat is
  rendered, with a 512 px shadow map instead of the suite's 2048 (``shadow_size``);
* rewards are summed per sub-step (after the task's reward transform);
* the frame stack is channels-first and repeats the first frame after reset;
* test scenes (``mode``) change pixels only, through :class:`imssr.envs.scenes.Scene`;
* any recorded physics state can be rendered again in any scene (:meth:`DMCEnv.render_stack`).
"""
from __future__ import annotations

import os
import sys
from collections import deque
from typing import Any, Optional

import gymnasium as gym
import numpy as np

from imssr._gl import (check_gl, egl_device_error, egl_vendor_hint, load_triton_first, nvidia_driver_loaded,
                       unpin_refused_egl_device)
from imssr.envs.scenes import Scene, get_mode
from imssr.envs.tasks import TaskSpec, get_task
from imssr.errors import ImssrError
from imssr.memlimit import check_room_to_render, raise_limit_text
from imssr.rng import random_state_from_plain, random_state_to_plain
from imssr.settings import MAX_SHADOW_SIZE, EnvConfig


class DMCEnv(gym.Env):
    """Pixel-based DeepMind Control task: ``uint8`` observations ``(3 * frame_stack, H, W)``,
    actions in ``[-1, 1]^|A|`` rescaled to the task's bounds; an episode ends by time limit
    (``truncated``), ``terminated`` only when the task reports a zero discount."""

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, task: str | TaskSpec, seed: int = 0, mode: str = "training",
                 action_repeat: Optional[int] = None, image_size: int = 100, frame_stack: int = 3,
                 camera_id: Optional[int] = None, footage_split: str = "train", footage_path: str = "",
                 shadow_size: int = 512):
        get_mode(mode)
        spec = task if isinstance(task, TaskSpec) else get_task(task)
        for name, value, least in (("action_repeat", 1 if action_repeat is None else action_repeat, 1),
                                   ("image_size", image_size, 16), ("frame_stack", frame_stack, 1)):
            if value < least:
                raise ImssrError(f"{name} must be >= {least}, got {value}")
        if not 1 <= shadow_size <= MAX_SHADOW_SIZE:
            raise ImssrError(f"shadow_size must be in [1, {MAX_SHADOW_SIZE}] (MuJoCo's default; a larger map "
                             f"renders many times slower and sharpens nothing), got {shadow_size}")
        check_gl()
        suite, Camera = _import_dm_control()

        self.spec_task = spec
        self.task_name = spec.name
        self.mode = mode
        self.action_repeat = action_repeat or spec.action_repeat
        self.image_size = image_size
        self.frame_stack = frame_stack
        self.camera_id = spec.camera_id if camera_id is None else camera_id
        self._env = suite.load(spec.domain, spec.suite_task, task_kwargs={"random": seed})
        # Read when the GL context is made (by the camera below).  The suite's
        # 2048-px shadow map costs a third of a 100x100 frame; 512 px changes
        # pixels by ~0.02/255 on average (bench/render_speed.py).
        self._env.physics.model.vis.quality.shadowsize = shadow_size
        check_room_to_render()
        try:
            self._camera = Camera(self._env.physics, image_size, image_size, self.camera_id)
        except Exception as exc:  # noqa: BLE001 - GL context failures surface here
            refused = egl_device_error(str(exc))
            if refused:
                raise ImssrError(f"cannot create an OpenGL context with MUJOCO_GL=egl: {refused}") from None
            cause = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            backend = os.environ.get("MUJOCO_GL", "egl")
            # A limited address space fails the framebuffer's allocation, not a missing package.
            fix = raise_limit_text()
            if fix is None:
                fix = "install " + (egl_vendor_hint(nvidia_driver_loaded()) if backend == "egl" else
                                    "the Debian package libgl1-mesa-dri for software rendering "
                                    "(apt-get install libgl1-mesa-dri)"
                                    + (", or render headless with MUJOCO_GL=egl" if backend == "glfw" else ""))
            _drop_half_made_context_errors()
            raise ImssrError(f"cannot create an OpenGL context with MUJOCO_GL={backend} ({cause}); {fix}") from None

        # Evaluation envs draw footage from the unseen ``test`` pool.
        self.scene: Optional[Scene] = None
        if mode != "training":
            self.scene = Scene(self._env.physics, mode, seed, image_size, self.camera_id, footage_split, footage_path)
        aspec = self._env.action_spec()
        self._act_low = aspec.minimum.astype(np.float64)
        self._act_high = aspec.maximum.astype(np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=aspec.shape, dtype=np.float32)
        self.observation_space = gym.spaces.Box(0, 255, shape=(3 * frame_stack, image_size, image_size),
                                                dtype=np.uint8)
        self._frames: deque[np.ndarray] = deque(maxlen=frame_stack)
        # Filled in place by physics_state(): recording costs no allocation per step.
        self._state = np.zeros(sum(x.size for x in self.physics._physics_state_items()), np.float64)
        # Simulator steps per episode (1000 for every task of the paper).
        self.episode_sim_steps = int(round(self._env._step_limit))
        self.max_episode_steps = -(-self.episode_sim_steps // self.action_repeat)
        self.action_space.seed(seed)

    # -- gymnasium API -------------------------------------------------------
    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        # gymnasium's own generator (env.np_random); the task and scenes keep theirs (seed_task).
        super().reset(seed=seed)
        if seed is not None:
            self.seed_task(seed)
        self._env.reset()
        if self.scene is not None:
            self.scene.reset()
        frame = self._render()
        self._frames.clear()
        for _ in range(self.frame_stack):
            self._frames.append(frame)
        return self._observation(), {"frame": frame}

    def step(self, action):
        action = np.asarray(action, dtype=np.float64)
        if action.shape != self.action_space.shape:
            raise ImssrError(f"action shape {action.shape} != {self.action_space.shape}")
        action = np.clip(action, -1.0, 1.0)
        scaled = self._act_low + (action + 1.0) * 0.5 * (self._act_high - self._act_low)
        reward = 0.0
        sim_steps = 0
        for _ in range(self.action_repeat):
            time_step = self._env.step(scaled)
            sim_steps += 1
            r = time_step.reward or 0.0
            if self.spec_task.reward_fn is not None:
                r = self.spec_task.reward_fn(r)
            reward += r
            if time_step.last():
                break
        if self.scene is not None:
            self.scene.step()
        frame = self._render()
        self._frames.append(frame)
        terminated = bool(time_step.last() and time_step.discount == 0.0)
        truncated = bool(time_step.last() and not terminated)
        info = {"frame": frame, "sim_steps": sim_steps, "discount": float(time_step.discount)}
        return self._observation(), float(reward), terminated, truncated, info

    def render(self):
        return np.moveaxis(self._frames[-1], 0, -1).copy()

    def close(self):
        cam = getattr(self, "_camera", None)
        if cam is not None:
            cam._scene.free()  # release the MuJoCo scene held by the reused camera
            self._camera = None

    # -- reproducibility -------------------------------------------------------
    def seed_task(self, seed: int) -> None:
        """Reseed the task's random state (initial states of later resets) and the scene's."""
        self._env.task._random = np.random.RandomState(seed)
        if self.scene is not None:
            self.scene.reseed(seed)

    def get_rng_state(self) -> dict[str, Any]:
        state: dict[str, Any] = {"task": random_state_to_plain(self._env.task.random.get_state())}
        if self.scene is not None:
            state["scene"] = self.scene.get_rng_state()
        return state

    def set_rng_state(self, state: dict[str, Any]) -> None:
        self._env.task.random.set_state(random_state_from_plain(state["task"]))
        if self.scene is not None and "scene" in state:
            self.scene.set_rng_state(state["scene"])

    # -- physics states ------------------------------------------------------------
    @property
    def physics_state_dim(self) -> int:
        """Length of :meth:`physics_state` (cartpole 4, walker 18)."""
        return self._state.size

    def physics_state(self) -> np.ndarray:
        """The full physics state of the newest frame, float64, as dm_control's
        ``physics.get_state()`` lays it out, read without a random draw.  The array is reused by
        the next call: copy it to keep it."""
        np.concatenate(self.physics._physics_state_items(), out=self._state)
        return self._state

    def set_physics_state(self, state: np.ndarray) -> None:
        """Put the simulation in ``state`` with positions and velocities derived (``mj_forward``),
        as after a step, so that a render shows it.  Ends the current episode's consistency:
        for rendering recorded states, not for stepping on."""
        state = np.asarray(state, dtype=np.float64)
        if state.shape != self._state.shape:
            raise ImssrError(f"physics state of shape {state.shape}, expected {self._state.shape} for "
                             f"{self.task_name}")
        with self.physics.reset_context():
            self.physics.set_state(state)

    def render_stack(self, states: np.ndarray) -> np.ndarray:
        """Render recorded physics states ``(k, D)``, oldest first, as one ``(3k, H, W)`` stack:
        in a test scene a fresh episode of it, stepped between frames as :meth:`step` does (a state equal to the one
        before is copied, as after a reset); in ``training`` exactly the recorded frames."""
        states = np.asarray(states, dtype=np.float64)
        if self.scene is not None:
            self.scene.reset()
        frames: list[np.ndarray] = []
        for j, state in enumerate(states):
            if j and np.array_equal(state, states[j - 1]):
                frames.append(frames[-1])
                continue
            if j and self.scene is not None:
                self.scene.step()
            self.set_physics_state(state)
            frames.append(self._render())
        return np.concatenate(frames, axis=0)

    # -- internals -------------------------------------------------------------
    @property
    def physics(self):
        return self._env.physics

    def _render(self) -> np.ndarray:
        # (H, W, 3) -> (3, H, W); the camera reuses its buffer, so copy.
        image = self.scene.render(self._camera) if self.scene is not None else self._camera.render()
        return np.ascontiguousarray(image.transpose(2, 0, 1))

    def _observation(self) -> np.ndarray:
        return np.concatenate(self._frames, axis=0)


def _import_dm_control():
    """dm_control's ``suite`` module and ``Camera`` class, imported after Triton
    (:func:`imssr._gl.load_triton_first`).  dm_control opens its EGL display as it is imported;
    when that refuses the ``MUJOCO_EGL_DEVICE_ID`` imssr guessed, the import runs again without it."""
    load_triton_first()
    for attempt in range(2):
        try:
            from dm_control import suite
            from dm_control.mujoco.engine import Camera
            return suite, Camera
        except (ImportError, OSError, RuntimeError) as exc:  # GL or mujoco load failure
            if attempt == 0 and unpin_refused_egl_device(str(exc)) is not None:
                continue
            raise ImssrError(f"cannot load dm_control/mujoco: {egl_device_error(str(exc)) or exc}") from None
    raise AssertionError("unreachable")


def _drop_half_made_context_errors() -> None:
    """dm_control's rendering context, when its making failed, raises ``AttributeError`` from its
    ``__del__`` as it is collected (an "Exception ignored" traceback after imssr's one line): such
    reports are dropped from here on; any other goes to the hook that was there."""
    previous = sys.unraisablehook

    def hook(report) -> None:
        if not (isinstance(report.exc_value, AttributeError) and "_ptr" in str(report.exc_value)
                and "MjrContext" in repr(report.object)):
            previous(report)

    sys.unraisablehook = hook


make_env = DMCEnv
"""``make_env(task, seed=0, mode="training", **kwargs)``: a pixel DeepMind Control environment of
``task`` in scene ``mode`` (:data:`imssr.envs.scenes.MODES`), the :class:`DMCEnv` itself."""


def env_from_config(cfg: EnvConfig, *, seed: int, footage_split: str, mode: Optional[str] = None,
                    footage_path: Optional[str] = None) -> DMCEnv:
    """The env that ``cfg`` describes, seeded with ``seed``; ``mode`` and ``footage_path`` replace
    the config's scene and footage when given.  ``footage_split``: ``train`` for the training
    env, ``test`` (unseen clips) for evaluation envs."""
    return DMCEnv(cfg.task, seed=seed, mode=cfg.mode if mode is None else mode,
                  action_repeat=cfg.action_repeat, image_size=cfg.image_size,
                  frame_stack=cfg.frame_stack, shadow_size=cfg.shadow_size, footage_split=footage_split,
                  footage_path=cfg.footage_dir if footage_path is None else footage_path)
