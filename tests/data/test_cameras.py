import numpy as np
import pytest

from data.cameras import MOVES, CameraConfig, View, _related_pose
from data.generate import GenConfig, parse_moves
from data.geom import look_at


def _ref(distance=4.0):
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    T = look_at([0.0, -distance, 1.5], [0.3, 0.0, 1.2], roll=0.05)
    return View(K=K, cam2world=T, width=64, height=48, depth=np.full((48, 64), distance, np.float32))


def _angle_deg(R):
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


class _NoScene:
    pass


@pytest.mark.parametrize("seed", range(20))
def test_a_slide_keeps_the_orientation_within_3_degrees_and_moves_5_to_40_percent_sideways(seed):
    ref = _ref()
    eye, T = _related_pose(np.random.default_rng(seed), _NoScene(), ref, "slide", CameraConfig())
    R0, e0 = ref.cam2world[:3, :3], ref.cam2world[:3, 3]
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(T[:3, :3]), 1)
    assert _angle_deg(R0.T @ T[:3, :3]) <= 3.0 + 1e-9
    offset = R0.T @ (eye - e0) / 4.0  # in the reference camera's axes, in viewing distances
    assert 0.05 <= abs(offset[0]) <= 0.4 and abs(offset[2]) <= 0.15 and np.allclose(T[:3, 3], eye)


@pytest.mark.parametrize("seed", range(20))
def test_a_pan_turns_the_camera_in_place(seed):
    ref = _ref()
    eye, T = _related_pose(np.random.default_rng(seed), _NoScene(), ref, "pan", CameraConfig())
    assert np.linalg.norm(eye - ref.cam2world[:3, 3]) <= 0.04 * 4.0 + 1e-9
    assert 8.0 - 1e-6 <= _angle_deg(ref.cam2world[:3, :3].T @ T[:3, :3]) <= np.hypot(35.0, 8.0) + 1e-6
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)


def test_the_default_weights_draw_the_moves_the_four_move_engine_drew():
    # rendered data sets stay reproducible: the new moves have weight 0, and numpy draws the same index
    old = np.array([0.3, 0.25, 0.3, 0.15])
    new = np.asarray(CameraConfig().move_weights)
    a, b = np.random.default_rng(7), np.random.default_rng(7)
    assert [int(a.choice(4, p=old / old.sum())) for _ in range(500)] == \
           [int(b.choice(len(MOVES), p=new / new.sum())) for _ in range(500)]


def test_move_weights_parse_by_name_and_bad_ones_are_refused():
    assert parse_moves(None) == ()
    assert parse_moves("slide=0.5, pan=0.25,small=0.25") == (0.25, 0.0, 0.0, 0.0, 0.5, 0.25)
    assert parse_moves("small=0.3,medium=0.25,wide=0.3,zoom=0.15") == ()  # the default, stored as the default
    for bad in ("slid=1", "slide", "slide=x", "slide=-1,pan=2", "slide=0", "slide=nan", "slide=inf",
                "slide=1,slide=2"):
        with pytest.raises(ValueError, match="--moves"):
            parse_moves(bad)
    with pytest.raises(ValueError, match="move_weights expected 6"):
        GenConfig(scenes=1, moves=(1.0, 0.0))
    with pytest.raises(ValueError, match="finite non-negative"):
        CameraConfig(move_weights=(1.0, 0.0, 0.0, 0.0, float("nan"), 0.0))


def test_a_run_stores_its_move_weights_only_when_they_are_not_the_default():
    assert "moves" not in GenConfig(scenes=1).to_dict()
    cfg = GenConfig(scenes=1, moves=parse_moves("slide=1"))
    assert GenConfig.from_dict(cfg.to_dict()) == cfg and cfg.camera().move_weights == (0, 0, 0, 0, 1.0, 0)


def test_the_demo_scene_camera_config_is_valid():
    from data.demo_scenes import DEMO_CAMERA

    assert len(DEMO_CAMERA.move_weights) == len(MOVES) and DEMO_CAMERA.move_weights[MOVES.index("zoom")] == 0


def test_a_scene_taken_with_one_camera_gives_every_view_view_0s_intrinsics(renderer):
    from data.cameras import sample_views
    from data.scene import make_scene

    for share, expect_same in ((1.0, True), (0.0, False)):
        rng = np.random.default_rng(11)
        scene = make_scene(rng, kind="cluster")
        vs = sample_views(rng, scene, renderer, 3, 64, CameraConfig(same_camera=share), color=False)
        same = [np.array_equal(v.K, vs.views[0].K) for v in vs.views[1:]]
        assert all(same) if expect_same else not any(same)  # fields of view are drawn from 40-90 degrees


def test_the_same_camera_share_is_stored_only_when_used_and_bad_shares_are_refused():
    assert "same_camera" not in GenConfig(scenes=1).to_dict()  # older runs keep their stored configuration
    cfg = GenConfig(scenes=1, same_camera=0.8)
    assert GenConfig.from_dict(cfg.to_dict()) == cfg and cfg.camera().same_camera == 0.8
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="same_camera expected a share"):
            GenConfig(scenes=1, same_camera=bad)


def test_a_pair_whose_larger_overlap_exceeds_hi_is_kept_and_the_docs_say_so():
    from pathlib import Path

    from data.cameras import ViewSet

    zoomed_out = ViewSet(views=[None, None], overlap=np.array([[1.0, 0.99], [0.50, 1.0]]))
    assert zoomed_out.pairs(0.15, 0.95) == [(0, 1)]  # only the smaller direction has to be <= HI
    assert ViewSet(views=[None, None], overlap=np.array([[1.0, 0.99], [0.97, 1.0]])).pairs(0.15, 0.95) == []
    assert ViewSet(views=[None, None], overlap=np.array([[1.0, 0.5], [0.1, 1.0]])).pairs(0.15, 0.95) == []
    doc = " ".join((Path(__file__).resolve().parents[2] / "docs" / "data.md").read_text().split())
    assert "in either direction" not in doc and "(both directions) is stored" not in doc
    assert "both directions must be at least LO, and the smaller of the two at most HI" in doc
