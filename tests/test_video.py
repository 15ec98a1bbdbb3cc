"""Frames from a video: the window stride, the sharpest frame of each window, refusals; and the command line."""

import math
import sys

import cv2
import numpy as np
import pytest

from pointmap.errors import ImageError
from pointmap.video import extract_frames, sharpness


def _video(path, n=30, sharp=(), size=(96, 64), seed=0):
    """An MJPG video of ``n`` frames of one random texture: blurred, except the indices in ``sharp``."""
    rng = np.random.default_rng(seed)
    texture = rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, size)
    assert writer.isOpened()
    for i in range(n):
        frame = np.roll(texture, i, axis=1)
        writer.write(frame if i in sharp else cv2.GaussianBlur(frame, (9, 9), 3))
    writer.release()
    return path


def test_one_frame_per_window_and_the_sharpest_of_each(tmp_path):
    video = _video(tmp_path / "walk.avi", n=30, sharp=(3, 13, 27))
    frames = extract_frames(video, tmp_path / "frames", stride=10)
    assert [f.name for f in frames] == ["walk_000003.png", "walk_000013.png", "walk_000027.png"]
    first = extract_frames(video, tmp_path / "first", stride=10, pick_sharpest=False)
    assert [f.name for f in first] == ["walk_000000.png", "walk_000010.png", "walk_000020.png"]
    assert sharpness(cv2.imread(str(frames[1]))) > 2 * sharpness(cv2.imread(str(first[1])))


def test_extracted_frames_keep_the_videos_colours_red_stays_red(tmp_path):
    from pointmap.images import read_rgb

    writer = cv2.VideoWriter(str(tmp_path / "rgb.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    assert writer.isOpened()
    for bgr in ((0, 0, 255), (0, 255, 0), (255, 0, 0)):  # red, green, blue frames (OpenCV writes BGR)
        writer.write(np.full((48, 64, 3), bgr, np.uint8))
    writer.release()
    frames = extract_frames(tmp_path / "rgb.avi", tmp_path / "frames", stride=1, pick_sharpest=False)
    assert len(frames) == 3
    for k, path in enumerate(frames):
        rgb = read_rgb(path).astype(np.float64)
        mean = rgb.reshape(-1, 3).mean(0)
        assert mean.argmax() == k and mean[k] > 200 and np.delete(mean, k).max() < 60, (path.name, mean)


def test_without_a_stride_at_most_max_frames_are_kept_and_a_last_partial_window_counts(tmp_path):
    video = _video(tmp_path / "v.avi", n=25)
    assert len(extract_frames(video, tmp_path / "a", max_frames=10)) == 9  # stride 3: 8 full windows + 1 partial
    assert len(extract_frames(video, tmp_path / "b", max_frames=30)) == 25


def test_missing_and_undecodable_videos_and_bad_strides_are_refused(tmp_path):
    with pytest.raises(ImageError, match="video not found"):
        extract_frames(tmp_path / "none.mp4", tmp_path)
    (tmp_path / "junk.mp4").write_bytes(b"not a video at all")
    with pytest.raises(ImageError, match="junk.mp4"):
        extract_frames(tmp_path / "junk.mp4", tmp_path / "f")
    video = _video(tmp_path / "v.avi", n=3)
    for bad in (0, -2, 1.5, True):
        with pytest.raises(ImageError, match="stride expected a positive integer"):
            extract_frames(video, tmp_path / "f", stride=bad)
    for bad in (0, -1, 2.5):
        with pytest.raises(ImageError, match="max_frames expected an integer >= 1"):
            extract_frames(video, tmp_path / "f", max_frames=bad)
    assert len(extract_frames(video, tmp_path / "one", max_frames=1)) == 1  # one frame is enough to localize
    (tmp_path / "taken").write_text("a file where the frames would go")
    with pytest.raises(ImageError, match="expected a folder for the frames, got .*taken, which is a file"):
        extract_frames(video, tmp_path / "taken")
    for args in ((None, tmp_path / "f"), (video, None)):
        with pytest.raises(ImageError, match="expected a video path and a folder path"):
            extract_frames(*args)


@pytest.mark.parametrize("suffix", [".mp4", ".mkv"])
def test_an_unreadable_video_is_refused_in_one_line_without_ffmpegs_own_complaint(tmp_path, capfd, suffix):
    from pointmap.cli import main

    junk = tmp_path / f"junk{suffix}"
    junk.write_bytes(b"not a video at all")
    capfd.readouterr()
    with pytest.raises(ImageError, match="not a readable video"):
        extract_frames(junk, tmp_path / "f")
    assert capfd.readouterr().err == ""  # FFmpeg wrote "moov atom not found" / "EBML header parsing failed" to fd 2
    assert main(["reconstruct", str(junk), "-o", str(tmp_path / "out"), "--quiet"]) == 2
    err = capfd.readouterr().err
    assert err.count("\n") == 1 and err.startswith("pointmap: error: not a readable video:"), err
    print("still writable", file=sys.stderr)  # file descriptor 2 is back
    assert "still writable" in capfd.readouterr().err


def test_splat_takes_a_video_of_test_views_and_localize_refuses_a_bad_max_frames_by_its_flag(tmp_path, monkeypatch,
                                                                                             capsys):
    import torch

    import pointmap as pm
    import pointmap.localization
    import pointmap.splat
    from pointmap.cli import main

    torch.manual_seed(0)
    weights = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "tiny.safetensors")
    rec = tmp_path / "rec"
    assert main(["--quiet", "reconstruct", str(_video(tmp_path / "clip.avi", n=8)), "--model", str(weights), "--size",
                 "64", "-o", str(rec), "--stride", "4", "--export", "npz"]) == 0
    assert main(["localize", str(rec), str(tmp_path / "clip.avi"), "-o", str(tmp_path / "loc"), "--max-frames",
                 "0"]) == 2
    assert "--max-frames >= 1, got None and 0" in capsys.readouterr().err
    seen = {}

    def localize(model, recon, images, **kw):  # the views' frames reach localize; none posed ends the command
        seen["names"] = [v.name for v in images]
        raise pm.PointmapError("none posed")

    monkeypatch.setattr(pointmap.localization, "localize", localize)
    monkeypatch.setattr(pointmap.splat, "run", lambda recon, out_dir, **kw: {"fit": "the fit"})
    walk = _video(tmp_path / "walk.avi", n=8)
    assert main(["--quiet", "splat", str(rec), "-o", str(tmp_path / "splat"), "--test", str(walk), "--model",
                 str(weights)]) == 2
    assert seen["names"] == [f"walk_{k:06d}.png" for k in range(8)]  # every frame of the 8: at most 30 are kept
    assert sorted(p.name for p in (tmp_path / "splat" / "test_frames").iterdir()) == seen["names"]


def test_the_reconstruct_command_takes_a_video_and_pairs_its_frames_in_time_order(tmp_path, capsys):
    import torch

    import pointmap as pm
    from pointmap.cli import main
    from pointmap.io import load_npz

    torch.manual_seed(0)
    weights = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "tiny.safetensors")
    video = _video(tmp_path / "clip.avi", n=14)
    out = tmp_path / "out"
    assert main(["reconstruct", str(video), "-o", str(out), "--model", str(weights), "--size", "64", "--stride", "1",
                 "--export", "npz"]) == 0
    err = capsys.readouterr().err
    assert "14 images, graph logwin-3-noncyclic" in err  # no pair of the last frame with the first
    assert len(list((out / "frames").glob("clip_*.png"))) == 14
    rec = load_npz(out / "reconstruction.npz")
    assert rec.names[:2] == ["clip_000000.png", "clip_000001.png"]
    assert float(rec.K[:, 0, 0].max() - rec.K[:, 0, 0].min()) == 0.0  # a video is one camera: one focal
    assert main(["--quiet", "reconstruct", str(video), "-o", str(out), "--model", str(weights), "--size", "64",
                 "--stride", "3", "--export", "npz", "--no-shared-focal"]) == 0
    f = load_npz(out / "reconstruction.npz").K[:, 0, 0]
    assert len(f) == 5 and len(set(f.tolist())) == 5  # one focal per frame, as asked


def test_a_videos_frames_share_one_focal_beside_photographs_of_another_size_that_keep_their_own(tmp_path, capsys):
    import torch

    import pointmap as pm
    from pointmap.cli import main
    from pointmap.io import load_npz

    torch.manual_seed(0)
    weights = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "tiny.safetensors")
    video = _video(tmp_path / "clip.avi", n=6)
    rng = np.random.default_rng(2)
    photos = [str(tmp_path / f"p{k}.png") for k in range(2)]
    for p in photos:
        cv2.imwrite(p, rng.integers(0, 255, (90, 120, 3), dtype=np.uint8))
    out = tmp_path / "out"
    assert main(["reconstruct", str(video), *photos, "-o", str(out), "--model", str(weights), "--size", "64",
                 "--stride", "2", "--export", "npz"]) == 0
    assert "one estimated focal per camera: the 3 frames of clip.avi; the other 2 image(s) each its own" in \
        capsys.readouterr().err
    rec = load_npz(out / "reconstruction.npz")
    f = rec.K[:, 0, 0].tolist()
    assert rec.names[3:] == ["p0.png", "p1.png"] and f[0] == f[1] == f[2] and len(set(f)) == 3
    assert rec.info["align"]["config"]["shared_focal"] == [0, 0, 0, 1, 2]  # (a tuple, saved as a list)


def test_a_video_that_states_no_frame_count_is_counted_frame_by_frame(tmp_path, monkeypatch):
    from pointmap.video import count_frames

    video = _video(tmp_path / "v.avi", n=17)
    assert count_frames(video) == 17
    monkeypatch.setattr(cv2, "CAP_PROP_FRAME_COUNT", cv2.CAP_PROP_GAMMA)  # a property this file does not state
    assert cv2.VideoCapture(str(video)).get(cv2.CAP_PROP_FRAME_COUNT) <= 0
    assert count_frames(video) == 17
    assert len(extract_frames(video, tmp_path / "f", max_frames=5)) == 5  # stride 4 from the counted 17


def _avi_stating(data: bytes, n: int) -> bytes:
    """An AVI file's bytes with its headers' frame counts (avih dwTotalFrames, strh dwLength) set to ``n``."""
    import struct

    b = bytearray(data)
    struct.pack_into("<I", b, b.find(b"avih") + 8 + 16, n)
    struct.pack_into("<I", b, b.find(b"strh") + 8 + 32, n)
    return bytes(b)


def test_a_header_that_under_or_over_states_the_frames_or_a_cut_file_still_gives_max_frames(tmp_path):
    from pointmap.video import count_frames

    data = _video(tmp_path / "full.avi", n=60).read_bytes()
    (tmp_path / "under.avi").write_bytes(_avi_stating(data, 6))
    (tmp_path / "over.avi").write_bytes(_avi_stating(data, 600))
    (tmp_path / "cut.avi").write_bytes(data[:int(len(data) * 0.4)])
    assert count_frames(tmp_path / "under.avi") == 6 and count_frames(tmp_path / "over.avi") == 600  # as stated
    full = [f.name for f in extract_frames(tmp_path / "full.avi", tmp_path / "full", max_frames=10)]
    assert len(full) == 10
    for name in ("under", "over"):  # the same frames as the truthful file, and nothing else left in the folder
        frames = extract_frames(tmp_path / f"{name}.avi", tmp_path / name, max_frames=10, with_times=True)
        assert [f.name.replace(name, "full") for f, _ in frames] == full
        assert sorted(p.name for p in (tmp_path / name).iterdir()) == [f.name for f, _ in frames]
        assert [round(t, 3) for _, t in frames] == [int(f[-10:-4]) / 10 for f in full]  # 10 fps
    decodable = 0
    cap = cv2.VideoCapture(str(tmp_path / "cut.avi"))
    while cap.grab():
        decodable += 1
    cap.release()
    assert 10 < decodable < 60
    cut = extract_frames(tmp_path / "cut.avi", tmp_path / "cut", max_frames=10)
    assert len(cut) == math.ceil(decodable / math.ceil(decodable / 10))  # the stride of the frames it holds
    assert len(list((tmp_path / "cut").iterdir())) == len(cut)


def test_two_videos_of_one_file_name_are_refused_before_their_frames_overwrite_each_other(tmp_path):
    from pointmap.cli import expand_images
    from pointmap.errors import PointmapError

    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a, b = _video(tmp_path / "a" / "walk.avi", n=6), _video(tmp_path / "b" / "walk.avi", n=6, seed=1)
    with pytest.raises(PointmapError, match="videos named \\['walk'\\] more than once"):
        expand_images([str(a), str(b)], tmp_path / "frames", stride=2)
    assert not (tmp_path / "frames").exists()


def test_a_video_that_gives_one_frame_is_refused_in_its_own_terms_before_the_model_loads(tmp_path, capsys,
                                                                                          monkeypatch):
    import pointmap.checkpoint
    from pointmap.cli import main

    video = _video(tmp_path / "short.avi", n=5)
    monkeypatch.setattr(pointmap.checkpoint, "load_model", lambda *a, **k: pytest.fail("the model loaded"))
    assert main(["--quiet", "reconstruct", str(video), "-o", str(tmp_path / "out"), "--stride", "10"]) == 2  # a usage error
    err = capsys.readouterr().err
    assert "needs at least 2 images, got 1" in err and "the video gave 1 frame(s) at --stride 10" in err


def test_a_video_reconstruction_writes_its_frames_times_in_seconds_to_the_tum_trajectory(tmp_path):
    import torch

    import pointmap as pm
    from pointmap.cli import main
    from pointmap.io import load_npz

    torch.manual_seed(0)
    weights = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "tiny.safetensors")
    video = _video(tmp_path / "clip.avi", n=14, sharp=(2, 7, 12))  # 10 frames per second
    out = tmp_path / "out"
    assert main(["reconstruct", str(video), "-o", str(out), "--model", str(weights), "--size", "64", "--stride", "5",
                 "--export", "tum,npz", "--quiet"]) == 0
    rows = [line.split() for line in (out / "trajectory.txt").read_text().splitlines() if not line.startswith("#")]
    assert [float(r[0]) for r in rows] == pytest.approx([0.2, 0.7, 1.2])  # frames 2, 7 and 12, not 0, 1, 2
    assert load_npz(out / "reconstruction.npz").info["timestamps"] == pytest.approx([0.2, 0.7, 1.2])


def test_frames_carry_the_containers_times_else_index_over_the_rate_else_none(tmp_path, monkeypatch):
    from pointmap import video as vid

    video = _video(tmp_path / "walk.avi", n=12, sharp=(3, 9))  # 10 frames per second
    frames = extract_frames(video, tmp_path / "f", stride=6, with_times=True)
    assert [(p.name, t) for p, t in frames] == [("walk_000003.png", pytest.approx(0.3)),
                                                ("walk_000009.png", pytest.approx(0.9))]
    # a container whose times are missing or not increasing: the index over the stated rate; no rate either: None
    assert vid._frame_seconds([(3, 0.0), (9, 0.0)], 10.0) == pytest.approx([0.3, 0.9])
    assert vid._frame_seconds([(3, 0.5), (9, float("nan"))], 25.0) == pytest.approx([0.12, 0.36])
    assert vid._frame_seconds([(3, 0.0), (9, 0.0)], 0.0) == [None, None]
    assert vid._frame_seconds([(0, 0.0), (5, 1.0)], 0.0) == [0.0, 1.0]  # the container's own, rate or not


def test_localizing_a_videos_frames_times_the_trajectory_by_the_frames_own_times(tmp_path, monkeypatch):
    import torch

    import pointmap as pm
    import pointmap.localization
    from pointmap.cli import main

    torch.manual_seed(0)
    weights = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "tiny.safetensors")
    clip = _video(tmp_path / "clip.avi", n=8, sharp=(1, 6))  # 10 frames per second
    rec = tmp_path / "rec"
    assert main(["--quiet", "reconstruct", str(clip), "--model", str(weights), "--size", "64", "-o", str(rec),
                 "--stride", "4", "--export", "npz"]) == 0
    calls = []

    def pose_against(recon, ref, pred, rev, K_map=None, patch=16):  # the geometry: tests/align/test_localize.py
        calls.append(ref)
        pose = torch.eye(4, dtype=torch.float64) if len(calls) == 2 else torch.full((4, 4), float("nan"))
        return pose, torch.tensor([[60.0, 0, 32], [0, 60, 21], [0, 0, 1]], dtype=torch.float64), 1.0

    monkeypatch.setattr(pointmap.localization, "pose_against", pose_against)
    walk = _video(tmp_path / "walk.avi", n=8, sharp=(2, 7))
    out = tmp_path / "loc"
    assert main(["--quiet", "localize", str(rec), str(walk), "--model", str(weights), "-o", str(out),
                 "--stride", "4", "--n-refs", "1"]) == 0
    rows = [ln.split() for ln in (out / "trajectory.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(calls) == 2 and len(rows) == 1 and float(rows[0][0]) == pytest.approx(0.7)  # frame 7, not query 1
