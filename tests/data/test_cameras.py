import numpy as np
import pytest

from data.cameras import (
    MOVES,
    CameraConfig,
    View,
    _acceptable,
    _first_pose,
    _focus_point,
    _related_pose,
    _roll,
    image_size,
    sample_K,
    sample_views,
)
from data.generate import GenConfig, parse_moves
from data.geom import look_at, overlap
from pointmap.errors import ShapeError


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


@pytest.mark.parametrize("kw", [{"fov_deg": (5.0, 90.0)}, {"fov_deg": (40.0, 170.0)}, {"fov_deg": (90.0, 40.0)},
                                {"overlap": (0.6, 0.2)}, {"overlap": (-0.1, 0.9)}, {"overlap": (0.1, 1.2)},
                                {"move_weights": (1.0, -0.5, 0.0, 0.0, 0.0, 0.0)}, {"min_valid": 1.5},
                                {"same_camera": 1.5}])
def test_impossible_camera_settings_are_refused(kw):
    with pytest.raises(ValueError):
        CameraConfig(**kw)


def test_image_sizes_follow_the_orientation_and_round_the_short_side_to_16():
    one = dict(short_side_ratios=(5 / 7,))
    rng = np.random.default_rng(0)
    assert image_size(rng, 64, CameraConfig(orientation_weights=(1, 0, 0), **one)) == (64, 64)
    assert image_size(rng, 64, CameraConfig(orientation_weights=(0, 1, 0), **one)) == (64, 48)  # 45.7 -> 48
    assert image_size(rng, 64, CameraConfig(orientation_weights=(0, 0, 1), **one)) == (48, 64)
    assert image_size(rng, 224, CameraConfig(orientation_weights=(0, 1, 0), short_side_ratios=(0.75,))) == (224, 176)
    for bad in (8, 64.0):
        with pytest.raises(ShapeError):
            image_size(rng, bad, CameraConfig())


def test_principal_points_jitter_by_up_to_3_percent_of_each_side():
    rng = np.random.default_rng(0)
    cfg = CameraConfig()
    K = np.stack([sample_K(rng, 64, 48, cfg) for _ in range(2000)])
    dx, dy = K[:, 0, 2] - 31.5, K[:, 1, 2] - 23.5
    assert np.abs(dx).max() <= 0.03 * 64 and np.abs(dy).max() <= 0.03 * 48
    assert np.abs(dx).max() > 0.9 * 0.03 * 64 and np.abs(dy).max() > 0.9 * 0.03 * 48
    fov = np.degrees(2 * np.arctan(0.5 * 64 / K[:, 0, 0]))  # on the longer side
    assert fov.min() >= 40 - 1e-9 and fov.max() <= 90 + 1e-9 and np.allclose(K[:, 0, 0], K[:, 1, 1])


def test_rolls_are_within_8_degrees_but_for_a_tenth_within_30():
    rng = np.random.default_rng(0)
    r = np.degrees([_roll(rng, CameraConfig()) for _ in range(5000)])
    assert np.abs(r).max() <= 30
    big = float((np.abs(r) > 8).mean())
    assert 0.04 < big < 0.11, big  # 0.1 * 22/30 = 0.073 expected


class _Scene:
    """No obstacles, one target at the origin of radius 1; cameras must stay at x <= 0."""
    targets = np.zeros((1, 3))
    target_radius = np.ones(1)
    camera_lo, camera_hi = np.full(3, -1e3), np.full(3, 1e3)

    def __init__(self, extent=1000.0):
        self.extent = extent

    def inside_obstacle(self, p, margin=0.0):
        return bool(p[0] > 0)


def test_the_first_view_frames_its_target_from_0_7_to_2_5_times_the_fitting_distance_outside_obstacles():
    for seed in range(200):
        rng = np.random.default_rng(seed)
        K = sample_K(rng, 64, 48, CameraConfig())
        T = _first_pose(rng, _Scene(), K, 64, CameraConfig())
        eye = T[:3, 3]
        assert eye[0] <= 0
        fit = 1.0 / np.tan(np.arctan(0.5 * 64 / K[0, 0]))
        assert 0.7 * fit - 0.25 <= np.linalg.norm(eye) <= 2.5 * fit + 0.25, (seed, np.linalg.norm(eye) / fit)
        T = _first_pose(rng, _Scene(extent=4.0), K, 64, CameraConfig())
        assert 0.4 - 0.25 <= np.linalg.norm(T[:3, 3]) <= 1.6 + 0.25  # clipped to [0.4, 0.4 * extent]


def _one_pixel_ref(x=40, y=20, d=4.0):
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    T = look_at([0.5, -4.0, 1.5], [0.3, 0.0, 1.2], roll=0.05)
    depth = np.zeros((48, 64), np.float32)
    depth[y, x] = d
    P = T[:3, :3] @ np.array([(x - 32) / 60 * d, (y - 24) / 60 * d, d]) + T[:3, 3]
    return View(K=K, cam2world=T, width=64, height=48, depth=depth), P


def test_the_focus_point_is_the_surface_point_seen_at_a_central_pixel():
    ref, P = _one_pixel_ref()
    got, d = _focus_point(np.random.default_rng(0), ref)
    assert np.allclose(got, P, atol=1e-9) and d == 4.0


def _az(v):
    return np.degrees(np.arctan2(v[1], v[0]))


@pytest.mark.parametrize("move, lo, hi", [("medium", 8, 30), ("wide", 30, 90)])
def test_orbits_turn_about_the_vertical_through_the_focus_point_by_their_range(move, lo, hi):
    ref, P = _one_pixel_ref()
    ratios = []
    for seed in range(30):
        eye, T = _related_pose(np.random.default_rng(seed), None, ref, move, CameraConfig())
        turn = abs((_az(eye - P) - _az(ref.cam2world[:3, 3] - P) + 180) % 360 - 180)
        assert lo - 1e-6 <= turn <= hi + 1e-6, (seed, turn)
        ratios.append(np.linalg.norm(eye - P) / np.linalg.norm(ref.cam2world[:3, 3] - P))
    assert 0.75 - 1e-9 <= min(ratios) and max(ratios) <= 1.3 + 1e-9 and max(ratios) - min(ratios) > 0.2


def test_small_moves_step_2_to_25_percent_of_the_distance_and_zooms_go_25_to_60_percent_in_or_15_to_36_out():
    ref, P = _one_pixel_ref()
    e0 = ref.cam2world[:3, 3]
    for seed in range(30):
        eye, _ = _related_pose(np.random.default_rng(seed), None, ref, "small", CameraConfig())
        assert 0.02 * 4 - 1e-9 <= np.linalg.norm(eye - e0) <= 0.25 * 4 + 1e-9
    axis = P - e0  # the share of the way to the point each zoom moves (a jitter of 0.03 x depth per axis aside)
    f = np.array([(_related_pose(np.random.default_rng(s), None, ref, "zoom", CameraConfig())[0] - e0) @ axis
                  / (axis @ axis) for s in range(60)])
    closer, back = f[f > 0], f[f < 0]
    assert len(closer) > 15 and len(back) > 15, f
    assert closer.min() > 0.25 - 0.1 and closer.max() < 0.6 + 0.1 and abs(closer.mean() - 0.425) < 0.06, closer
    assert back.min() > -0.36 - 0.1 and back.max() < -0.15 + 0.1 and abs(back.mean() + 0.255) < 0.05, back


def _heading(R):
    z = R[:, 2]
    return np.degrees(np.arctan2(z[1], z[0]))


def test_a_pan_turns_the_heading_about_the_vertical_both_ways_and_steps_with_the_depth():
    ref = _ref(40.0)
    T = ref.cam2world
    turns, steps = [], []
    for seed in range(40):
        eye, Tn = _related_pose(np.random.default_rng(seed), None, ref, "pan", CameraConfig())
        turns.append((_heading(Tn[:3, :3]) - _heading(T[:3, :3]) + 180) % 360 - 180)
        steps.append(np.linalg.norm(eye - T[:3, 3]))
    assert all(7 <= abs(t) <= 36 for t in turns), turns  # yaw 8-35 deg (a little pitch and roll aside)
    assert min(turns) < 0 < max(turns)
    assert max(steps) <= 0.04 * 40 + 1e-9 and max(steps) > 0.5


def test_near_geometry_and_too_few_valid_pixels_are_rejected():
    cfg = CameraConfig()
    d = np.full((50, 50), 2.0, np.float32)
    assert _acceptable(d, cfg)
    near = d.copy()
    near[:5, :10] = 0.05  # 2% of the pixels closer than min_depth
    assert not _acceptable(near, cfg)
    sparse = d.copy()
    sparse[:35] = 0  # 30% valid < min_valid
    assert not _acceptable(sparse, cfg)


class _Stop(Exception):
    pass


class _RecordingRenderer:
    def __init__(self):
        self.K = []

    def render(self, scene, K, T, w, h, color=False, depth=True):
        self.K.append(K)
        raise _Stop


def test_a_config_without_same_camera_draws_no_extra_random_number():
    for seed in range(5):
        cfg = CameraConfig()
        r = _RecordingRenderer()
        with pytest.raises(_Stop):
            sample_views(np.random.default_rng(seed), _Scene(), r, 2, 64, cfg, color=False)
        rng = np.random.default_rng(seed)
        w, h = image_size(rng, 64, cfg)
        assert np.array_equal(r.K[0], sample_K(rng, w, h, cfg))


def test_n_views_below_1_is_refused():
    with pytest.raises(ValueError, match="n_views"):
        sample_views(np.random.default_rng(0), _Scene(), _RecordingRenderer(), 0, 64)


def test_the_stored_overlaps_are_view_i_pixels_seen_in_view_j_and_each_new_view_meets_the_bounds(renderer):
    from data.scene import make_scene

    larger_above_hi = False
    for seed in range(3):
        rng = np.random.default_rng(seed)
        scene = make_scene(rng, kind="cluster")
        cfg = CameraConfig(overlap=(0.2, 0.6))
        vs = sample_views(rng, scene, renderer, 4, 64, cfg, color=False)
        for i, a in enumerate(vs.views):
            assert not scene.inside_obstacle(a.cam2world[:3, 3], margin=0.12)
            for j, b in enumerate(vs.views):
                want = 1.0 if i == j else overlap(a.depth, a.K, a.cam2world, b.depth, b.K, b.cam2world, stride=2)
                assert vs.overlap[i, j] == pytest.approx(want, abs=1e-12), (seed, i, j)
        for k, v in enumerate(vs.views[1:], 1):
            a, b = vs.overlap[v.ref, k], vs.overlap[k, v.ref]
            assert min(a, b) >= 0.2 and min(a, b) <= 0.6
            larger_above_hi |= max(a, b) > 0.6
    assert larger_above_hi  # only the smaller overlap is bounded by hi


def test_a_slide_moves_sideways_in_the_reference_cameras_own_axes_for_any_orientation():
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    T = look_at([3.0, -3.0, 2.5], [0.0, 0.0, 1.2], roll=0.5)  # diagonal heading, pitched down, rolled
    ref = View(K=K, cam2world=T, width=64, height=48, depth=np.full((48, 64), 4.0, np.float32))
    for seed in range(20):
        eye, _ = _related_pose(np.random.default_rng(seed), None, ref, "slide", CameraConfig())
        off = T[:3, :3].T @ (eye - T[:3, 3]) / 4.0
        assert 0.05 <= abs(off[0]) <= 0.4 and abs(off[2]) <= 0.15 and abs(off[1]) < abs(off[0]) + 0.2, (seed, off)
