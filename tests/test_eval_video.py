"""Evaluation videos during training (train.eval_video_every): files at every k-th evaluation,
and nothing else changes: the same evaluation returns, training logs and weights as without."""
import os

from conftest import assert_same_nets, tiny_config, train_run, without_timing

from imssr.training.logger import read_csv


def small(**train):
    return tiny_config("curl", steps=130, eval_every_steps=65, checkpoint_every_steps=0, **train)


def test_videos_every_second_evaluation_change_nothing_else(tmp_path, capsys):
    plain = train_run(small(), tmp_path / "plain")
    filmed = train_run(small(eval_video_every=2, eval_video_format="gif", tensorboard=True), tmp_path / "filmed")
    # Evaluations at agent steps 65 and 130: only the second one is filmed.
    assert sorted(os.listdir(tmp_path / "filmed" / "videos")) == ["step_000000130_training.gif"]
    assert not os.path.exists(tmp_path / "plain" / "videos")
    for name in ("eval.csv", "eval_episodes.csv", "train.csv"):
        assert without_timing(read_csv(tmp_path / "filmed" / name)) == \
            without_timing(read_csv(tmp_path / "plain" / name)), name
    assert_same_nets(plain.agent, filmed.agent)
    # Without moviepy TensorBoard gets no video, and one line says so.
    out = capsys.readouterr().out
    try:
        import moviepy.editor  # noqa: F401
    except ImportError:
        assert out.count("evaluation videos go to RUN/videos only, not to TensorBoard") == 1, out


def test_bad_video_settings_are_refused(tmp_path):
    import pytest

    from imssr.errors import ImssrError

    for field, value, message in (("eval_video_every", -1, "train.eval_video_every must be >= 0"),
                                  ("eval_video_format", "avi", "train.eval_video_format must be one of gif, mp4")):
        cfg = tiny_config("curl", **{field: value})
        with pytest.raises(ImssrError, match=message):
            cfg.validate()
