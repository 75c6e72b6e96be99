"""Test scenes: DMControl-GB colour/video modes and Distracting-Control-style shifts.

Only pixels change: a :class:`Scene` edits material colours, the skybox texture and the camera
pose of one render, never the physics state, so rewards and dynamics equal ``training``.

* ``color_easy`` / ``color_hard``: per episode, new colours for every material
  (agent, target, decorations, floor tint) and a tinted sky; easy stays within
  +-0.25 of the default colours, hard draws them uniformly.
* ``video_easy``: natural footage replaces the sky (background pixels);
  ``video_hard``: it replaces the whole background, floor included.  Frames
  are composited after rendering using a segmentation render of the same camera.
* ``distracting_{easy,medium,hard}``: the camera drifts around the agent during
  the episode, colours drift step by step, and footage plays in the background
  (sky only for easy; sky and floor otherwise); intensities grow with the level.

All randomness comes from the scene's own generator, seeded from the env seed.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from imssr.data import footage_pool
from imssr.errors import ImssrError


@dataclass(frozen=True)
class ModeSpec:
    name: str
    description: str
    color: float = 0.0
    """Per-episode colour change: 0 none, in (0, 1) +-color around the defaults, 1 uniform."""
    color_drift: float = 0.0
    """Per-step random-walk standard deviation of every colour channel."""
    video: str = ""
    """Footage in the background: '' none, 'sky' background only, 'all' background and floor."""
    camera_degrees: float = 0.0
    """Largest camera rotation (yaw; pitch half of it) around the agent while drifting."""


MODES: dict[str, ModeSpec] = {m.name: m for m in (
    ModeSpec("training", "the unmodified scene"),
    ModeSpec("color_easy", "random colours near the defaults, per episode", color=0.25),
    ModeSpec("color_hard", "uniformly random colours of agent, floor and sky, per episode", color=1.0),
    ModeSpec("video_easy", "natural footage as the sky", video="sky"),
    ModeSpec("video_hard", "natural footage replaces the whole background, floor included", video="all"),
    ModeSpec("distracting_easy", "drifting camera (10 deg), colour drift, footage sky",
             color=0.1, color_drift=0.01, video="sky", camera_degrees=10.0),
    ModeSpec("distracting_medium", "drifting camera (20 deg), colour drift, footage background",
             color=0.2, color_drift=0.02, video="all", camera_degrees=20.0),
    ModeSpec("distracting_hard", "drifting camera (30 deg), strong colour drift, footage background",
             color=0.3, color_drift=0.04, video="all", camera_degrees=30.0),
)}


def get_mode(name: str) -> ModeSpec:
    if name not in MODES:
        raise ImssrError(f"unknown mode {name!r}; valid modes: {', '.join(MODES)}")
    return MODES[name]


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / (np.linalg.norm(axis) + 1e-12)
    x, y, z = axis
    c, s, C = np.cos(angle), np.sin(angle), 1 - np.cos(angle)
    return np.array([[c + x * x * C, x * y * C - z * s, x * z * C + y * s],
                     [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
                     [z * x * C - y * s, z * y * C + x * s, c + z * z * C]])


class Scene:
    """Applies one mode to one dm_control physics; see the module docstring."""

    def __init__(self, physics, mode: str, seed: int, image_size: int, camera_id: int,
                 footage_split: str = "train", footage_path: str = ""):
        import mujoco

        self.spec = get_mode(mode)
        self.physics = physics
        self.camera_id = camera_id
        self.reseed(seed)
        model = physics.model
        self.mat_rgba0 = np.array(model.mat_rgba, copy=True)
        skies = np.flatnonzero(np.asarray(model.tex_type) == mujoco.mjtTexture.mjTEXTURE_SKYBOX)
        self.sky_id: Optional[int] = int(skies[0]) if len(skies) else None
        if self.sky_id is not None:
            t = self.sky_id
            n = int(model.tex_height[t] * model.tex_width[t] * model.tex_nchannel[t])
            self.sky_slice = slice(int(model.tex_adr[t]), int(model.tex_adr[t]) + n)
            self.sky0 = np.array(model.tex_data[self.sky_slice], copy=True)
        self.plane_geoms = np.flatnonzero(np.asarray(model.geom_type) == mujoco.mjtGeom.mjGEOM_PLANE)
        self.geom_type = int(mujoco.mjtObj.mjOBJ_GEOM)
        self.clips: tuple[np.ndarray, ...] = ()
        if self.spec.video:
            self.clips = footage_pool(image_size, footage_split, footage_path)
        self.colors = self.mat_rgba0[:, :3].copy()
        self.base_colors = self.colors.copy()
        self.clip, self.frame_index = 0, 0
        self.angles = np.zeros(2)  # yaw, pitch (radians)
        self.angle_velocity = np.zeros(2)

    # -- episode and step --------------------------------------------------------
    def reset(self) -> None:
        s, rng = self.spec, self.rng
        if s.color > 0:
            n = len(self.mat_rgba0)
            if s.color >= 1.0:
                self.base_colors = rng.uniform(0.0, 1.0, (n, 3))
                sky_scale = rng.uniform(0.0, 2.0, 3)
            else:
                self.base_colors = np.clip(self.mat_rgba0[:, :3] + rng.uniform(-s.color, s.color, (n, 3)), 0, 1)
                sky_scale = 1.0 + rng.uniform(-2 * s.color, 2 * s.color, 3)
            self.colors = self.base_colors.copy()
            self._write_colors()
            self._tint_sky(sky_scale)
        if self.clips:
            self.clip = int(rng.integers(len(self.clips)))
            self.frame_index = int(rng.integers(len(self.clips[self.clip])))
        if s.camera_degrees > 0:
            limit = np.radians([s.camera_degrees, s.camera_degrees / 2])
            self.angles = rng.uniform(-limit, limit)
            self.angle_velocity = np.zeros(2)

    def step(self) -> None:
        s, rng = self.spec, self.rng
        if s.color_drift > 0:
            drift = rng.normal(0.0, s.color_drift, self.colors.shape)
            self.colors = np.clip(self.colors + drift, np.clip(self.base_colors - s.color, 0, 1),
                                  np.clip(self.base_colors + s.color, 0, 1))
            self._write_colors()
        if self.clips:
            self.frame_index += 1
        if s.camera_degrees > 0:
            limit = np.radians([s.camera_degrees, s.camera_degrees / 2])
            self.angle_velocity = 0.9 * self.angle_velocity + rng.normal(0.0, 0.02, 2) * limit
            self.angles = self.angles + self.angle_velocity
            over = np.abs(self.angles) > limit
            self.angles = np.clip(self.angles, -limit, limit)
            self.angle_velocity[over] *= -1.0  # bounce off the range limit

    # -- rendering -----------------------------------------------------------------
    def render(self, camera) -> np.ndarray:
        """An ``(H, W, 3)`` frame of ``camera`` (a reused dm_control Camera) in this scene."""
        data = self.physics.data
        moved = self.spec.camera_degrees > 0 and self.camera_id >= 0
        if moved:
            pos0 = np.array(data.cam_xpos[self.camera_id])
            mat0 = np.array(data.cam_xmat[self.camera_id])
            self._move_camera(pos0, mat0.reshape(3, 3))
        try:
            frame = camera.render().copy()
            if self.clips:
                seg = camera.render(segmentation=True)
                ids, types = seg[..., 0], seg[..., 1]
                mask = ids == -1
                if self.spec.video == "all" and len(self.plane_geoms):
                    mask |= (types == self.geom_type) & np.isin(ids, self.plane_geoms)
                clip = self.clips[self.clip]
                background = clip[self.frame_index % len(clip)]
                frame[mask] = background[mask]
        finally:
            if moved:  # the physics state stays exactly as the simulator left it
                data.cam_xpos[self.camera_id] = pos0
                data.cam_xmat[self.camera_id] = mat0
        return frame

    def _move_camera(self, pos: np.ndarray, mat: np.ndarray) -> None:
        # Rotate the camera about a pivot on its viewing axis, level with the
        # agent's root body: yaw about the world's vertical, pitch about the
        # camera's right axis, so the agent stays near the centre of view.
        data = self.physics.data
        forward, right = -mat[:, 2], mat[:, 0]
        root = np.array(data.subtree_com[1]) if len(data.subtree_com) > 1 else pos + forward
        depth = float(np.dot(root - pos, forward))
        pivot = pos + forward * (depth if depth > 1e-3 else 1.0)
        rot = _rotation(np.array([0.0, 0.0, 1.0]), self.angles[0]) @ _rotation(right, self.angles[1])
        data.cam_xpos[self.camera_id] = pivot + rot @ (pos - pivot)
        data.cam_xmat[self.camera_id] = (rot @ mat).reshape(-1)

    def _write_colors(self) -> None:
        self.physics.model.mat_rgba[:, :3] = self.colors

    def _tint_sky(self, scale: np.ndarray) -> None:
        if self.sky_id is None:
            return
        import mujoco

        model = self.physics.model
        channels = int(model.tex_nchannel[self.sky_id])
        sky = self.sky0.reshape(-1, channels).astype(np.float32)
        sky[:, :3] *= scale[: min(3, channels)]
        model.tex_data[self.sky_slice] = np.clip(sky, 0, 255).astype(np.uint8).reshape(-1)
        ctx = self.physics.contexts
        with ctx.gl.make_current() as gl:
            gl.call(mujoco.mjr_uploadTexture, model.ptr, ctx.mujoco.ptr, self.sky_id)

    # -- reproducibility -------------------------------------------------------------
    def reseed(self, seed: int) -> None:
        self.rng = np.random.default_rng([seed, list(MODES).index(self.spec.name)])

    def get_rng_state(self) -> dict[str, Any]:
        return self.rng.bit_generator.state

    def set_rng_state(self, state: dict[str, Any]) -> None:
        self.rng.bit_generator.state = state
