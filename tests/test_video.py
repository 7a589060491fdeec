"""Videos of evaluation episodes: real MuJoCo rendering (EGL or OSMesa) and H.264 MP4 files read
back, for a point-mass run through the command line and for the ant's MJCF."""
import json
import os

import jax
import numpy as np
import pytest

from dscpp_jax import checkpoint as ck
from dscpp_jax import trainer as T
from dscpp_jax import video
from dscpp_jax.cli import main
from dscpp_jax.evaluate import evaluate_episodes
from dscpp_jax.run_logging import write_config
from tests.trainer_fixtures import tiny


@pytest.fixture(scope="module")
def gl():
    try:
        return video.select_gl_backend()
    except video.VideoError as e:   # nothing can render on this machine: say what to install
        pytest.skip(str(e))


def _gold(frames):
    """Pixels of the goal marker's colour (gold: strong red and green, little blue)."""
    f = frames.astype(int)
    return (f[..., 0] > 200) & (f[..., 1] > 150) & (f[..., 2] < 100)


def _greenish(frames):
    """Pixels of option 2's colour (tab:green); the floor is pale green, far less saturated."""
    f = frames.astype(int)
    return (f[..., 1] > f[..., 0] + 60) & (f[..., 1] > f[..., 2] + 60)


def test_frame_indices_always_end_on_the_last_step():
    assert video.frame_indices(5, 1) == [0, 1, 2, 3, 4, 5]
    assert video.frame_indices(5, 2) == [0, 2, 4, 5]
    assert video.frame_indices(0, 3) == [0]
    assert video.num_frames([5, 4], every=2, hold=3) == (4 + 3) + (3 + 3)
    with pytest.raises(video.VideoError, match="even"):
        video.check_options(width=63, height=64)
    with pytest.raises(video.VideoError, match="camera"):
        video.check_options(cameras=["side"])


def test_point_run_video_from_the_command_line(tmp_path, gl):
    cfg = tiny("td3_her")   # flat: the cheapest policy to compile; options are drawn alike
    run = str(tmp_path / "run")
    state = T.init(jax.random.PRNGKey(0), cfg)
    os.makedirs(run)
    write_config(run, cfg.to_dict())
    ck.save_state(run, 0, state)
    W, H, fps, steps = 128, 96, 10.0, 7
    rc = main(["video", "--run", run, "--episodes", "2", "--max-steps", str(steps), "--width",
               str(W), "--height", str(H), "--fps", str(fps), "--every", "2",
               "--compile-cache", "off"])
    assert rc == 0
    summary = json.load(open(os.path.join(run, "videos", "eval_video.json")))
    eps = summary["episodes"]
    assert len(eps) == 2 and all(1 <= e["steps"] <= steps for e in eps)
    assert summary["gl_backend"] == gl
    hold = int(round(0.5 * fps))
    expect = video.num_frames([e["steps"] for e in eps], every=2, hold=hold)
    assert summary["frames"] == expect
    for cam in video.CAMERAS:
        path = os.path.join(run, "videos", f"eval_{cam}.mp4")
        frames, got_fps = video.read_mp4(path)
        assert frames.shape == (expect, H, W, 3) and got_fps == fps
        assert frames.std() > 10, f"{cam}: blank frames"
    top, _ = video.read_mp4(os.path.join(run, "videos", "eval_topdown.mp4"))
    assert _gold(top).sum(axis=(1, 2)).min() > 0, "the goal marker is missing from a frame"

    # the per-step record is what evaluation sees, and without `record` it is not kept
    key = jax.random.PRNGKey(0)
    rec = evaluate_episodes(state, key, 2, None, record=True, num_steps=steps)
    plain = evaluate_episodes(state, key, 2, None, num_steps=steps)
    assert plain.obs_seq is None and plain.qpos_seq is None and plain.subgoal_seq is None
    np.testing.assert_array_equal(np.asarray(rec.xy), np.asarray(plain.xy))
    np.testing.assert_array_equal(np.asarray(rec.obs_seq)[..., :2], np.asarray(rec.xy))
    assert rec.obs_seq.shape == (steps + 1, 2, 4) and rec.subgoal_seq.shape == (steps, 2, 2)
    ep = video.episodes_from_result(rec)[0]
    assert ep.steps == int(rec.steps[0]) and ep.option.shape == (ep.steps + 1,)
    assert (ep.option == 0).all()   # the flat agent runs the global option throughout


def test_record_here_render_elsewhere_equals_direct_render(tmp_path, gl):
    """`video --record-only` (no GL, no ffmpeg) then `video --from-record` on a copy of the run
    holding only its config draws the same frames as `video` straight from the checkpoint."""
    cfg = tiny("td3_her")
    run = str(tmp_path / "run")
    os.makedirs(run)
    write_config(run, cfg.to_dict())
    ck.save_state(run, 0, T.init(jax.random.PRNGKey(0), cfg))
    common = ["--episodes", "2", "--max-steps", "5", "--width", "64", "--height", "48",
              "--camera", "topdown", "--compile-cache", "off"]
    assert main(["video", "--run", run, "--out", str(tmp_path / "direct")] + common) == 0
    assert main(["video", "--run", run, "--record-only"] + common) == 0
    rec = os.path.join(run, "videos", video.RECORD_FILE)
    eps, meta = video.load_record(rec)
    assert len(eps) == 2 and meta["env"] == cfg.env and meta["max_options"] == cfg.chain.max_options
    assert not os.path.exists(os.path.join(run, "videos", "eval_topdown.mp4"))
    elsewhere = str(tmp_path / "elsewhere")   # the config alone: no checkpoint to load
    os.makedirs(elsewhere)
    write_config(elsewhere, cfg.to_dict())
    assert main(["video", "--run", elsewhere, "--from-record", rec] + common) == 0
    a, _ = video.read_mp4(str(tmp_path / "direct" / "eval_topdown.mp4"))
    b, _ = video.read_mp4(os.path.join(elsewhere, "videos", "eval_topdown.mp4"))
    np.testing.assert_array_equal(a, b)
    d1 = json.load(open(tmp_path / "direct" / "eval_video.json"))
    d2 = json.load(open(os.path.join(elsewhere, "videos", "eval_video.json")))
    assert d1["episodes"] == d2["episodes"] and d1["frames"] == d2["frames"]
    with pytest.raises(ValueError, match="not a recording"):
        video.load_record(os.path.join(run, "config.json"))


def test_ant_video_draws_the_maze_goal_and_option_colour(tmp_path, gl):
    import mujoco

    from dscpp_jax import envs
    env = envs.make("u_maze")
    d = mujoco.MjData(env.mj_model)
    env.set_proxies_c(d)
    mujoco.mj_forward(env.mj_model, d)
    rng = np.random.default_rng(0)
    qpos = [d.qpos.copy()]
    for _ in range(4):
        env.mujoco_c_step(d, rng.uniform(-1.0, 1.0, env.action_size))
        qpos.append(d.qpos.copy())
    qpos = np.stack(qpos)
    n = len(qpos)
    ep = video.Episode(xy=qpos[:, :2], option=np.full(n, 2), subgoal=np.tile([[4.0, 0.0]], (n, 1)),
                       qpos=qpos, success=False, steps=n - 1)
    W, H = 80, 64
    paths = video.render_episodes(env, [ep], str(tmp_path), max_options=4, width=W, height=H,
                                  fps=10.0, hold_s=0.0)
    top, _ = video.read_mp4(paths["topdown"])
    follow, _ = video.read_mp4(paths["follow"])
    assert top.shape == (n, H, W, 3) and follow.shape == (n, H, W, 3)
    assert _gold(top).sum(axis=(1, 2)).min() > 0, "the goal marker is missing"
    # the torso and its halo take option 2's colour, large in the following camera
    assert _greenish(follow).mean(axis=(1, 2)).min() > 0.02
    ep.option[:] = 0   # option 0 is tab:blue: no green left
    paths = video.render_episodes(env, [ep], str(tmp_path / "blue"), max_options=4, width=W,
                                  height=H, fps=10.0, hold_s=0.0, cameras=["follow"])
    follow, _ = video.read_mp4(paths["follow"])
    assert _greenish(follow).mean() < 0.002
