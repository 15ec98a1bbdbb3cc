"""Unit tests for pointmap/video.py written from a mutation review: each closes a gap the existing tests left open.

Self-contained: every video is written here with OpenCV under tmp_path (the MJPG helpers of tests/test_video.py,
10 frames per second). The tests at the end, under their own comment, are of bugs the review found: sharpness
crashed inside OpenCV on a frame that is not HxWx3 instead of refusing it in one line, and extract_frames took any
truthy value for its flags (``pick_sharpest="no"`` kept the sharpest frame).
"""

import math
import os
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

import pointmap.video as vid
from pointmap.errors import ImageError
from pointmap.video import count_frames, extract_frames, is_video, sharpness
from tests.test_video import _avi_stating, _video


def _names(frames):
    return [f.name for f in frames]


def _still_video(path, n, value=None):
    """An MJPG video of ``n`` identical frames: one random texture, or a flat ``value`` when given."""
    frame = np.random.default_rng(0).integers(0, 255, (64, 96, 3), dtype=np.uint8)
    if value is not None:
        frame[:] = value
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (96, 64))
    assert writer.isOpened()
    for _ in range(n):
        writer.write(frame)
    writer.release()
    return path


# --- is_video ----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("suffix", [".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v"])
def test_every_video_suffix_in_any_case_names_a_video_even_before_the_file_exists(tmp_path, suffix):
    for name in ("clip" + suffix, "CLIP" + suffix.upper(), "Clip" + suffix.capitalize()):
        assert is_video(tmp_path / name) and is_video(str(tmp_path / name)), name


def test_a_folder_with_a_video_suffix_and_other_files_are_not_videos(tmp_path):
    (tmp_path / "scene.mp4").mkdir()
    assert not is_video(tmp_path / "scene.mp4")
    for name in ("a.png", "a.JPG", "mp4", "a.mp4.png", "a.gif"):
        assert not is_video(tmp_path / name), name


# --- sharpness ---------------------------------------------------------------------------------------------------

def test_sharpness_is_the_variance_of_the_four_neighbour_laplacian_of_the_grey_frame_as_a_float():
    frame = np.zeros((5, 5, 3), np.uint8)
    frame[2, 2] = 100  # grey 100: a Laplacian of -400 on the dot, 100 on its four neighbours, 0 elsewhere (mean 0)
    assert sharpness(frame) == pytest.approx((400 ** 2 + 4 * 100 ** 2) / 25)
    assert type(sharpness(frame)) is float
    assert sharpness(np.full((8, 8, 3), 90, np.uint8)) == 0.0  # a flat frame has no edge at all


def test_sharpness_reads_the_frame_as_blue_green_red():
    red, blue = np.zeros((5, 5, 3), np.uint8), np.zeros((5, 5, 3), np.uint8)
    red[2, 2, 2] = 200  # OpenCV frames are BGR: channel 2 is red, 0.299 of the grey; channel 0 is blue, 0.114
    blue[2, 2, 0] = 200
    assert sharpness(red) > 5 * sharpness(blue) > 0


def test_sharpness_still_takes_the_frames_opencv_decodes_and_their_bgra_and_16_bit_forms():
    frame = np.zeros((5, 5, 3), np.uint8)
    frame[2, 2] = 100
    bgra = np.concatenate([frame, np.full((5, 5, 1), 255, np.uint8)], axis=2)
    assert sharpness(frame) == sharpness(bgra) == sharpness(frame.astype(np.uint16)) == pytest.approx(8000.0)


# --- extract_frames: refusals ------------------------------------------------------------------------------------

def test_a_video_path_given_as_bytes_or_a_folder_given_as_the_video_is_refused(tmp_path):
    video = _video(tmp_path / "clip.avi", n=3)
    with pytest.raises(ImageError, match="expected a video path and a folder path"):
        extract_frames(bytes(video), tmp_path / "f")
    (tmp_path / "scene.mp4").mkdir()
    with pytest.raises(ImageError, match="video not found: .*scene.mp4"):
        extract_frames(tmp_path / "scene.mp4", tmp_path / "f")
    assert not (tmp_path / "f").exists()


def test_a_video_without_any_frame_is_refused_naming_it_with_or_without_a_stride(tmp_path):
    _still_video(tmp_path / "empty.avi", n=0)
    for kw in ({}, {"stride": 2}):
        with pytest.raises(ImageError, match="no frame could be decoded from .*empty.avi"):
            extract_frames(tmp_path / "empty.avi", tmp_path / "f", **kw)


def test_a_frame_that_cannot_be_written_is_an_image_error_naming_it_and_leaves_no_file(tmp_path, monkeypatch):
    video = _video(tmp_path / "v.avi", n=4)
    monkeypatch.setattr(cv2, "imwrite", lambda *a, **k: False)
    with pytest.raises(ImageError, match="could not write frame 0 of .*v.avi to .*v_000000.png"):
        extract_frames(video, tmp_path / "f", stride=2, pick_sharpest=False)
    assert list((tmp_path / "f").iterdir()) == []


# --- extract_frames: windows -------------------------------------------------------------------------------------

def test_a_given_stride_keeps_every_window_of_the_video_whatever_max_frames_says(tmp_path):
    video = _video(tmp_path / "v.avi", n=12)
    frames = extract_frames(video, tmp_path / "f", stride=1, max_frames=5)
    assert _names(frames) == [f"v_{k:06d}.png" for k in range(12)]


def test_without_a_stride_or_max_frames_a_video_gives_at_most_30_frames(tmp_path):
    assert len(extract_frames(_video(tmp_path / "thirty.avi", n=30), tmp_path / "a")) == 30  # stride 1
    assert len(extract_frames(_video(tmp_path / "more.avi", n=31), tmp_path / "b")) == 16  # stride 2


def test_among_equally_sharp_frames_the_first_of_each_window_is_kept(tmp_path):
    video = _still_video(tmp_path / "still.avi", n=8)
    assert _names(extract_frames(video, tmp_path / "f", stride=4)) == ["still_000000.png", "still_000004.png"]


def test_without_a_stride_the_first_frame_of_each_window_is_kept_when_asked_and_else_the_sharpest(tmp_path):
    video = _video(tmp_path / "v.avi", n=20, sharp=(1, 7, 13, 19))  # max_frames 4: windows of 5 frames
    first = extract_frames(video, tmp_path / "a", max_frames=4, pick_sharpest=False)
    assert _names(first) == ["v_000000.png", "v_000005.png", "v_000010.png", "v_000015.png"]
    assert _names(extract_frames(video, tmp_path / "b", max_frames=4)) == [f"v_{k:06d}.png" for k in (1, 7, 13, 19)]


def test_a_truthful_header_is_read_in_one_pass_at_the_smallest_stride_giving_max_frames(tmp_path, monkeypatch):
    strides = []
    read = vid._read_windows
    monkeypatch.setattr(vid, "_read_windows", lambda *a: strides.append(a[2]) or read(*a))
    for n, max_frames in ((30, 10), (25, 10), (31, 10), (7, 3), (12, 12), (5, 30)):
        strides.clear()
        video = _video(tmp_path / f"v{n}_{max_frames}.avi", n=n)
        frames = extract_frames(video, tmp_path / f"f{n}_{max_frames}", max_frames=max_frames)
        step = math.ceil(n / max_frames)
        assert strides == [step] and len(frames) == math.ceil(n / step) <= max_frames, (n, max_frames, strides)


@pytest.mark.parametrize("n, stated", [(31, 6), (30, 6), (21, 600), (20, 600)])
def test_a_header_wrong_about_the_count_gives_a_truthful_files_frames_at_any_length(tmp_path, n, stated):
    data = _video(tmp_path / "true.avi", n=n).read_bytes()
    (tmp_path / "wrong.avi").write_bytes(_avi_stating(data, stated))
    truthful = _names(extract_frames(tmp_path / "true.avi", tmp_path / "a", max_frames=10))
    assert len(truthful) == math.ceil(n / math.ceil(n / 10)) <= 10
    frames = extract_frames(tmp_path / "wrong.avi", tmp_path / "b", max_frames=10, with_times=True)
    assert [f.name.replace("wrong", "true") for f, _ in frames] == truthful
    assert [round(t, 3) for _, t in frames] == [int(f[-10:-4]) / 10 for f in truthful]
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == [f.name for f, _ in frames]


@pytest.mark.parametrize("stated", [6, 600])
def test_a_re_read_at_the_true_stride_keeps_the_first_frame_of_each_window_when_asked(tmp_path, stated):
    data = _video(tmp_path / "full.avi", n=60, sharp=(3, 15, 27, 39, 51)).read_bytes()
    (tmp_path / "wrong.avi").write_bytes(_avi_stating(data, stated))
    frames = extract_frames(tmp_path / "wrong.avi", tmp_path / "f", max_frames=10, pick_sharpest=False)
    assert _names(frames) == [f"wrong_{k:06d}.png" for k in range(0, 60, 6)]


def test_a_file_holding_ten_times_the_frames_its_header_states_is_not_written_whole_before_its_re_read(
        tmp_path, monkeypatch):
    data = _video(tmp_path / "full.avi", n=60).read_bytes()
    (tmp_path / "under.avi").write_bytes(_avi_stating(data, 6))
    written = []
    imwrite = cv2.imwrite
    monkeypatch.setattr(cv2, "imwrite", lambda path, frame, *a: written.append(path) or imwrite(path, frame, *a))
    frames = extract_frames(tmp_path / "under.avi", tmp_path / "f", max_frames=10)
    assert len(frames) == 10
    assert len(written) <= 2 * 10  # the first pass stops once its 10 windows are full, the re-read writes 10


# --- times -------------------------------------------------------------------------------------------------------

def test_frames_of_a_container_without_times_are_timed_by_their_index_over_the_stated_rate(tmp_path, monkeypatch):
    video = _video(tmp_path / "walk.avi", n=12, sharp=(3, 9))  # 10 frames per second
    monkeypatch.setattr(cv2, "CAP_PROP_POS_MSEC", cv2.CAP_PROP_GAMMA)  # a property this file does not state
    assert cv2.VideoCapture(str(video)).get(cv2.CAP_PROP_POS_MSEC) < 0
    frames = extract_frames(video, tmp_path / "f", stride=6, with_times=True)
    assert [(p.name, t) for p, t in frames] == [("walk_000003.png", pytest.approx(0.3)),
                                                ("walk_000009.png", pytest.approx(0.9))]


def test_the_containers_own_times_are_kept_when_it_states_no_rate(tmp_path, monkeypatch):
    video = _video(tmp_path / "walk.avi", n=12, sharp=(3, 9))
    monkeypatch.setattr(cv2, "CAP_PROP_FPS", cv2.CAP_PROP_GAMMA)  # a property this file does not state
    assert cv2.VideoCapture(str(video)).get(cv2.CAP_PROP_FPS) <= 0
    frames = extract_frames(video, tmp_path / "f", stride=6, with_times=True)
    assert [t for _, t in frames] == [pytest.approx(0.3), pytest.approx(0.9)]


def test_container_times_infinite_or_negative_give_way_to_the_rate_and_a_rate_not_finite_to_none():
    assert vid._frame_seconds([(3, 0.5), (9, math.inf)], 25.0) == pytest.approx([0.12, 0.36])
    assert vid._frame_seconds([(3, -0.1), (9, 0.5)], 25.0) == pytest.approx([0.12, 0.36])
    assert vid._frame_seconds([(3, 0.0), (9, 0.0)], math.inf) == [None, None]
    assert vid._frame_seconds([(3, 0.0), (9, 0.0)], math.nan) == [None, None]


# --- count_frames and the silenced FFmpeg ------------------------------------------------------------------------

def test_count_frames_takes_a_stated_count_of_one_and_counts_a_stated_zero_frame_by_frame(tmp_path):
    data = _video(tmp_path / "v.avi", n=17).read_bytes()
    (tmp_path / "one.avi").write_bytes(_avi_stating(data, 1))
    (tmp_path / "zero.avi").write_bytes(_avi_stating(data, 0))
    assert count_frames(tmp_path / "one.avi") == 1 and count_frames(tmp_path / "zero.avi") == 17


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="counts the open file descriptors in /proc")
def test_refusing_unreadable_videos_leaves_no_file_descriptor_open(tmp_path):
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"not a video at all")
    before = len(os.listdir("/proc/self/fd"))
    for _ in range(5):
        with pytest.raises(ImageError, match="not a readable video"):
            count_frames(junk)
    assert len(os.listdir("/proc/self/fd")) == before


def test_file_descriptor_2_is_back_after_an_unreadable_video_is_refused(tmp_path, capfd):
    junk = tmp_path / "junk.mkv"
    junk.write_bytes(b"not a video at all")
    with pytest.raises(ImageError, match="not a readable video"):
        count_frames(junk)
    os.write(2, b"written to fd 2 itself\n")  # past sys.stderr, as FFmpeg writes
    assert capfd.readouterr().err == "written to fd 2 itself\n"


def test_a_process_without_sys_stderr_still_gets_the_one_line_refusal(tmp_path, monkeypatch):
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"not a video at all")
    monkeypatch.setattr(sys, "stderr", None)  # pythonw, or a service that closed it
    with pytest.raises(ImageError, match="not a readable video: .*junk.mp4"):
        count_frames(junk)


# Bugs found by the mutation review

@pytest.mark.parametrize("frame, got", [(np.zeros((8, 8), np.uint8), r"shape \(8, 8\) uint8"),
                                        (np.zeros((8, 8, 1), np.uint8), r"shape \(8, 8, 1\) uint8"),
                                        (np.zeros((8, 8, 3), np.float64), r"shape \(8, 8, 3\) float64"),
                                        (np.zeros((8, 8, 3), np.float32), r"shape \(8, 8, 3\) float32"),
                                        (np.zeros((0, 8, 3), np.uint8), r"shape \(0, 8, 3\) uint8"),
                                        (None, "NoneType"), ([[[0, 0, 0]]], "list")],
                         ids=["grey", "one-channel", "float64", "float32", "empty", "none", "list"])
def test_sharpness_refuses_what_is_not_a_bgr_frame_in_one_line_naming_what_it_got(frame, got):
    with pytest.raises(ImageError, match=f"sharpness expected an HxWx3 BGR frame .*, got {got}$"):
        sharpness(frame)


@pytest.mark.parametrize("flag", ["pick_sharpest", "with_times"])
def test_extract_frames_refuses_a_flag_that_is_not_true_or_false_before_reading_anything(tmp_path, flag):
    video = _still_video(tmp_path / "v.avi", 3)
    with pytest.raises(ImageError, match=f"^{flag} expected True or False, got 'no'$"):
        extract_frames(video, tmp_path / "out", **{flag: "no"})
    assert not (tmp_path / "out").exists()
