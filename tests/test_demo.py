"""README command 1, `imssr demo`: its preset, and the whole command on a tiny budget."""
import subprocess
import sys

from PIL import Image

from conftest import tiny_sets
from imssr.presets import demo_config, make_config
from imssr.training.logger import read_csv


def test_demo_preset_is_im_ssr_on_dense_cartpole_with_the_fused_schedule():
    cfg = demo_config()
    paper = make_config("im-curl", "cartpole_swingup")
    assert cfg.algo == "im-curl" and cfg.intrinsic.enabled and cfg.intrinsic.beta0 > 0
    assert cfg.env.task == "cartpole_swingup" and cfg.env.action_repeat == 8
    assert cfg.agent.update_schedule == "fused" and paper.agent.update_schedule == "sequential"
    # Learning shows after ~500 updates in every measured seed (docs/performance.md, "The demo"):
    # the demo gives twice that, and evaluates at least three times after its burst.
    updates = cfg.train.steps - cfg.train.seed_steps + cfg.train.burst_updates
    assert updates >= 2 * 500
    assert (cfg.train.steps - cfg.train.seed_steps) // cfg.train.eval_every_steps >= 3
    # The network is the authors', only the batch shrinks.
    assert (cfg.agent.feature_dim, cfg.agent.projection_tanh, cfg.agent.final_relu) == \
        (paper.agent.feature_dim, paper.agent.projection_tanh, paper.agent.final_relu)


def test_demo_end_to_end_leaves_curve_gif_and_the_paper_command(tmp_path):
    out = tmp_path / "demo"
    proc = subprocess.run(
        [sys.executable, "-m", "imssr", "demo", "--out", str(out), "--steps", "40", "--seed-steps", "20",
         "--eval-every", "20", "--eval-episodes", "1", "--no-progress", "--set", "train.burst_updates=5",
         *tiny_sets()],
        capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert [r["step"] for r in read_csv(out / "eval.csv")] == ["20", "40"]
    assert (out / "learning_curve.png").stat().st_size > 0
    gif = Image.open(out / "episode.gif")
    # One cartpole episode in real time: 125 agent steps of 80 ms (action repeat 8 x 10 ms) plus the
    # reset frame.  The GIF writer merges identical consecutive frames, so count time, not frames.
    durations = []
    for i in range(gif.n_frames):
        gif.seek(i)
        durations.append(gif.info["duration"])
    assert gif.n_frames > 1 and abs(sum(durations) - 126 * 80) < 0.02 * 126 * 80
    last = proc.stdout.strip().splitlines()[-1]
    print(last)
    assert last.startswith("imssr: demo done") and "cartpole_swingup" in last
    assert "imssr train --algo im-curl --task cartpole_swingup_sparse" in last and "GPU" in last
