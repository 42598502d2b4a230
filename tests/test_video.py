"""`sage eval --video`: one deployed episode rendered to MP4/GIF (common/evaluation/video.py).

The top-down view needs no OpenGL and always runs; the camera view (MuJoCo offscreen,
EGL when headless) is tested where OpenGL works and skipped elsewhere. Episodes are a few
steps long and frames small.
"""
import dataclasses
import json
import math

import numpy as np
import pytest

from common.audit.synthetic import random_team_params
from common.env.config import EnvConfig
from common.env.observations import OBS_DIM
from common.evaluation import video as video_lib
from common.evaluation.deployment import evaluate_policy
from common.evaluation.video import VideoConfig, VideoRecorder, frame_size
from sage.cli import main

pytest.importorskip("imageio")
pytest.importorskip("imageio_ffmpeg")
pytest.importorskip("PIL")

# random trees that keep the payload for 9 steps of narrow_gate (seed 0) with QP corrections
PARAMS = random_team_params(obs_dim=OBS_DIM, depth=2, seed=3, gain=0.5)
ENV = EnvConfig(scenario="narrow_gate", max_steps=10)
HOLD_S = 0.3


def read_frames(path) -> np.ndarray:
    """[F, H, W, 3] uint8 frames of an MP4 (imageio-ffmpeg) or GIF (Pillow) file."""
    if path.suffix == ".gif":
        from PIL import Image, ImageSequence

        with Image.open(path) as img:
            return np.stack([np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(img)])
    import imageio.v2 as imageio

    return np.stack(imageio.mimread(path, memtest=False))


def render(tmp_path, suffix: str, view: str, every: int = 1):
    path = tmp_path / f"episode{suffix}"
    rec = VideoRecorder(path, VideoConfig(view=view, width=192, every=every, hold_s=HOLD_S))
    evaluate_policy(PARAMS, ENV, 1, seed=0, shielded=True, recorder=rec)
    return path, rec.close()


def check_video(path, written, every: int = 1) -> None:
    """Frame count as written, frames not blank, and the scene changing over the episode."""
    assert path.exists() and written["path"] == str(path) and written["outcome"].startswith("outcome:")
    steps = written["steps"]
    assert steps >= 5   # enough motion for "frames differ"
    expected = math.ceil(steps / every) + 1   # sampled steps + the outcome frame
    if path.suffix == ".mp4":   # the outcome frame is held by repeating it (GIF: a longer duration)
        expected += round(HOLD_S / (ENV.control_dt * every))
    frames = read_frames(path)
    assert len(frames) == written["frames"] == expected
    w, scene_h, panel_h = frame_size(192)
    assert frames.shape[1:] == (scene_h + panel_h, w, 3)
    assert all(f.std() > 20 for f in frames), "a blank frame"
    scene = frames[:, scene_h // 5:scene_h].astype(np.float64)   # below the header text
    assert np.abs(scene[-1] - scene[0]).mean() > 0.5, "the scene does not change over the episode"
    assert len({f.tobytes() for f in frames[:-1]}) > steps // (2 * every)


@pytest.mark.parametrize("suffix", [".gif", ".mp4"])
def test_topdown_video_needs_no_gl(tmp_path, suffix):
    path, written = render(tmp_path, suffix, "topdown")
    check_video(path, written)


def test_every_nth_step(tmp_path):
    path, written = render(tmp_path, ".gif", "topdown", every=2)
    check_video(path, written, every=2)


@pytest.mark.skipif(video_lib.gl_unavailable() is not None, reason="no OpenGL here (EGL/OSMesa/GLFW)")
@pytest.mark.parametrize("suffix", [".gif", ".mp4"])
def test_camera_video(tmp_path, suffix):
    path, written = render(tmp_path, suffix, "camera")
    check_video(path, written)


def test_overlay_shows_the_correction():
    """Per-carrier correction and the joint leaf tuple (a human-held slot is no tree's leaf)."""
    from common.evaluation.video import Overlay, StepView

    a_st = np.zeros((3, 3))
    a_exec = a_st.copy()
    a_exec[1, 0] = 0.5
    view = StepView(step=3, limit=10, carrier_xy=np.zeros((3, 2)), carrier_yaw=np.zeros(3), payload_xy=np.zeros(2),
                    payload_yaw=0.0, goal_xy=np.ones(2), a_st=a_st, a_exec=a_exec, leaf=np.array([1, 2, 3]),
                    active_rows=2, human_slot=None, max_step_xy=0.08)
    assert view.correction.tolist() == [0.0, 0.5, 0.0] and view.leaf_tuple == "(1, 2, 3)"
    assert dataclasses.replace(view, human_slot=1).leaf_tuple == "(1, h, 3)"
    w, scene_h, panel_h = frame_size(192)
    frame = Overlay(w, panel_h, "t").compose(np.full((scene_h, w, 3), 230, np.uint8), view)
    assert frame.shape == (scene_h + panel_h, w, 3)
    with_outcome = Overlay(w, panel_h, "t").compose(np.full((scene_h, w, 3), 230, np.uint8), view, "outcome: x")
    assert np.any(with_outcome != frame)


# ------------------------------------------------------------------ the CLI
def one_usage_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("sage eval: "), err
    return err[0]


@pytest.mark.parametrize("argv, names", [
    (["--video", "out.avi"], ".mp4 or .gif"),
    (["--video", "out"], ".mp4 or .gif"),
    (["--video", "out.gif", "--episodes", "2", "--video-episode", "2"], "--video-episode 2"),
    (["--video", "out.gif", "--video-width", "2000"], "width"),
])
def test_bad_video_flags_exit_2_with_one_line(tmp_path, capsys, argv, names):
    with pytest.raises(SystemExit) as exc:
        main(["eval", str(tmp_path / "no_run"), *argv])   # checked before the run is read
    assert exc.value.code == 2
    assert names in one_usage_line(capsys)


def test_video_without_the_extra_exits_2(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(video_lib, "missing_dependency", lambda suffix: "imageio")
    with pytest.raises(SystemExit) as exc:
        main(["eval", str(tmp_path / "no_run"), "--video", "out.mp4"])
    assert exc.value.code == 2
    line = one_usage_line(capsys)
    assert "video extra" in line and "imageio" in line and "[video]" in line


def test_camera_view_without_gl_exits_2(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(video_lib, "gl_unavailable", lambda: "egl: no EGL device")
    with pytest.raises(SystemExit) as exc:
        main(["eval", str(tmp_path / "no_run"), "--video", "out.mp4", "--video-view", "camera"])
    assert exc.value.code == 2
    assert "no EGL device" in one_usage_line(capsys)


def test_sage_eval_video_falls_back_to_topdown_without_gl(tmp_path, capsys, monkeypatch, one_torch_thread):
    """The default view without OpenGL: one note, then the top-down video beside ``--record``."""
    run = tmp_path / "run"
    assert main(["train", "--updates", "1", "--envs-per-actor", "2", "--chunk-len", "8", "--eval-episodes", "0",
                 "--set", "env.max_steps=6", "--run-dir", str(run), "--quiet"]) == 0
    capsys.readouterr()
    monkeypatch.setattr(video_lib, "gl_unavailable", lambda: "egl: no EGL device")
    out, traces = tmp_path / "ep.gif", tmp_path / "rec.npz"
    assert main(["eval", str(run), "--episodes", "2", "--video", str(out), "--video-episode", "1",
                 "--video-width", "160", "--record", str(traces), "--json"]) == 0
    cap = capsys.readouterr()
    result = json.loads(cap.out)
    assert result["video"] == str(out) and result["recording"] == str(traces)   # both recorders fed
    notes = [line for line in cap.err.splitlines() if line.startswith("sage eval:")]
    assert notes[0] == "sage eval: no OpenGL for the camera view (egl: no EGL device); rendering the top-down view"
    assert "topdown view" in notes[-1]
    frames = read_frames(out)
    assert 2 <= len(frames) <= 7 and frames.std() > 20   # <= 6 steps + the outcome frame
