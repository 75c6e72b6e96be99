"""Test scenes: only pixels change, seeded randomness, footage loaders, clear errors."""
import numpy as np
import pytest
from PIL import Image

from imssr.data import builtin_footage, footage_pool, load_footage
from imssr.data.footage import footage_sources
from imssr.envs import MODES, make_env
from imssr.errors import ImssrError

ACTIONS = np.random.default_rng(0).uniform(-1, 1, (6, 1)).astype(np.float32)


def _rollout(mode, seed=0, task="cartpole_swingup_sparse", **kw):
    env = make_env(task, seed=seed, mode=mode, image_size=64, **kw)
    try:
        obs, _ = env.reset()
        frames, rewards, qpos = [obs], [], [env.physics.data.qpos.copy()]
        rng = np.random.default_rng(0)
        actions = ACTIONS if env.action_space.shape == (1,) else \
            rng.uniform(-1, 1, (len(ACTIONS),) + env.action_space.shape).astype(np.float32)
        for a in actions:
            obs, r, *_ = env.step(a)
            frames.append(obs)
            rewards.append(r)
            qpos.append(env.physics.data.qpos.copy())
        return np.stack(frames), rewards, np.stack(qpos)
    finally:
        env.close()


@pytest.fixture(scope="module")
def training():
    return _rollout("training")


@pytest.mark.parametrize("mode", [m for m in MODES if m != "training"])
def test_mode_changes_pixels_but_not_physics_or_rewards(mode, training):
    frames, rewards, qpos = _rollout(mode)
    t_frames, t_rewards, t_qpos = training
    assert frames.shape == t_frames.shape and frames.dtype == np.uint8
    assert rewards == t_rewards
    np.testing.assert_array_equal(qpos, t_qpos)
    changed = np.mean(frames != t_frames)
    assert changed > 0.05, f"{mode} changed only {changed:.1%} of the pixels"


@pytest.mark.parametrize("mode", ["color_hard", "distracting_hard"])
def test_same_seed_same_pixels(mode):
    env = make_env("cartpole_swingup_sparse", seed=0, mode=mode, image_size=64)
    try:  # reset(seed=...) reseeds the scene too
        first, _ = env.reset(seed=5)
        again, _ = env.reset(seed=5)
        assert np.array_equal(first, again)
    finally:
        env.close()
    a, _, _ = _rollout(mode, seed=3)
    b, _, _ = _rollout(mode, seed=3)
    c, _, _ = _rollout(mode, seed=4)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_distracting_scenes_move_within_an_episode():
    frames, _, _ = _rollout("distracting_medium", task="walker_walk")
    # Camera, colours and footage drift: consecutive frames differ even where
    # the walker does not move much.
    assert all(not np.array_equal(frames[i], frames[i + 1]) for i in range(len(frames) - 1))


def test_camera_pose_is_restored_after_rendering():
    env = make_env("walker_walk", seed=0, mode="distracting_hard", image_size=32)
    try:
        env.reset()
        env.step(np.zeros(env.action_space.shape, np.float32))
        cam = env.camera_id
        pos = env.physics.data.cam_xpos[cam].copy()
        env._render()
        np.testing.assert_array_equal(env.physics.data.cam_xpos[cam], pos)
    finally:
        env.close()


def test_unknown_mode_is_a_one_line_error():
    with pytest.raises(ImssrError, match="unknown mode 'video_medium'"):
        make_env("cartpole_swingup_sparse", mode="video_medium")


def test_builtin_footage_moves_and_has_disjoint_train_and_test_pools():
    train, test = builtin_footage(32, "train"), builtin_footage(32, "test")
    assert len(train) == len(test) >= 4
    clip = train[0]
    assert clip.ndim == 4 and clip.shape[1:] == (32, 32, 3) and clip.dtype == np.uint8
    assert np.mean(np.abs(clip[1:].astype(int) - clip[:-1].astype(int))) > 0.5  # it moves
    from imssr.data.images import source_files

    train_src, test_src, overlay_src = (set(footage_sources("train")), set(footage_sources("test")),
                                        set(source_files("overlay")))
    assert len(train_src) >= 4 and len(test_src) >= 4  # photographs plus dm_control's sky boxes
    # Nothing seen in training (training footage, overlay images) is test footage.
    assert not test_src & (train_src | overlay_src)
    assert not {p.parent for p in test_src if "sky_" in str(p)} & {p.parent for p in train_src}
    assert not {c[0].tobytes() for c in train} & {c[0].tobytes() for c in test}


def _davis(root, videos=3, frames=4):
    rng = np.random.default_rng(0)
    for v in range(videos):
        d = root / "JPEGImages" / "480p" / f"video{v}"
        d.mkdir(parents=True)
        for f in range(frames):
            Image.fromarray(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)).save(d / f"{f:05d}.jpg")


def test_davis_layout_and_split(tmp_path):
    _davis(tmp_path)
    clips = load_footage(str(tmp_path), 16)
    assert len(clips) == 3 and all(c.shape == (4, 16, 16, 3) for c in clips)
    assert len(footage_pool(16, "train", str(tmp_path))) == 2
    assert len(footage_pool(16, "test", str(tmp_path))) == 1
    # The JPEGImages/480p folder itself works too.
    assert len(load_footage(str(tmp_path / "JPEGImages" / "480p"), 16)) == 3


def test_video_files(tmp_path):
    import imageio.v2 as imageio

    rng = np.random.default_rng(1)
    frames = [rng.integers(0, 256, (32, 48, 3), dtype=np.uint8) for _ in range(5)]
    imageio.mimsave(tmp_path / "a.gif", frames, duration=40)
    with imageio.get_writer(tmp_path / "b.mp4", fps=10, macro_block_size=16) as w:
        for f in frames:
            w.append_data(f)
    clips = load_footage(str(tmp_path), 16)
    assert len(clips) == 2 and clips[0].shape == (5, 16, 16, 3) and clips[1].shape[1:] == (16, 16, 3)
    assert load_footage(str(tmp_path / "b.mp4"), 16)[0].shape[0] >= 4


def test_footage_errors(tmp_path):
    with pytest.raises(ImssrError, match="footage not found"):
        load_footage(str(tmp_path / "nope"), 16)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ImssrError, match="no videos or frame folders"):
        load_footage(str(tmp_path / "empty"), 16)
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(ImssrError, match="is not a video"):
        load_footage(str(tmp_path / "notes.txt"), 16)
    (tmp_path / "broken.mp4").write_bytes(b"not a video")
    with pytest.raises(ImssrError, match="cannot read video"):
        load_footage(str(tmp_path / "broken.mp4"), 16)


def test_user_footage_reaches_the_scene(tmp_path):
    _davis(tmp_path, videos=1, frames=3)
    env = make_env("cartpole_swingup_sparse", seed=0, mode="video_hard", image_size=16,
                   footage_path=str(tmp_path))
    try:
        assert len(env.scene.clips) == 1 and env.scene.clips[0].shape == (3, 16, 16, 3)
        obs, _ = env.reset()
        assert obs.shape == (9, 16, 16)
    finally:
        env.close()


def test_training_in_a_scene_and_evaluating_in_several(tmp_path):
    from conftest import tiny_config
    from imssr.training import Trainer
    from imssr.rundir import RunDir
    from imssr.rundir.checkpoint import load_checkpoint
    from imssr.training.logger import read_csv

    cfg = tiny_config("im-curl", seed_steps=8, steps=25, eval_every_steps=0)  # 200 frames
    cfg.env.mode = "distracting_easy"
    cfg.train.eval_modes = "training,video_hard"
    trainer = Trainer(cfg, str(tmp_path))
    try:
        assert trainer.env.scene is not None and trainer.env.mode == "distracting_easy"
        # Evaluation footage comes from the unseen test pool.
        assert trainer.eval_envs["video_hard"].scene.clips == builtin_footage(cfg.env.image_size, "test")
        assert trainer.env.scene.clips == builtin_footage(cfg.env.image_size, "train")
        trainer.train()
    finally:
        trainer.close()
    rows = read_csv(tmp_path / "eval.csv")
    assert [(r["frame"], r["mode"]) for r in rows] == [("200", "training"), ("200", "video_hard")]
    state = load_checkpoint(RunDir(str(tmp_path)).latest)
    assert set(state.eval_env_rngs) == {"training", "video_hard"}
    assert "scene" in state.eval_env_rngs["video_hard"] and "scene" in state.env_rng
