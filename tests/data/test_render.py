import numpy as np
import pytest

from data.geom import intrinsics_from_fov, look_at
from data.render import cv_to_gl_pose, gl_to_cv_pose
from data.scene import Light, Material, Scene, Surface, plane_scene
from pointmap.errors import ShapeError


def test_opencv_pose_round_trips_through_the_gl_conversion():
    rng = np.random.default_rng(0)
    for _ in range(5):
        T = look_at(rng.normal(size=3), rng.normal(size=3) + 5, roll=rng.uniform(-1, 1))
        G = cv_to_gl_pose(T)
        assert np.allclose(gl_to_cv_pose(G), T)
        # GL camera looks down its -z axis, which is OpenCV's +z (forward); GL +y is OpenCV -y
        assert np.allclose(G[:3, 2], -T[:3, 2]) and np.allclose(G[:3, 1], -T[:3, 1])
        assert np.allclose(G[:3, 0], T[:3, 0]) and np.allclose(G[:3, 3], T[:3, 3])


def test_plane_at_known_distance_renders_analytic_depth(renderer):
    K = intrinsics_from_fov(80, 60, 70.0, cx_offset=1.3, cy_offset=-0.7)
    rgb, depth = renderer.render(plane_scene(2.5), K, np.eye(4), 80, 60)
    assert rgb.shape == (60, 80, 3) and rgb.dtype == np.uint8
    assert depth.dtype == np.float32 and depth.shape == (60, 80)
    assert np.abs(depth - 2.5).max() < 1e-4


def test_tilted_plane_renders_analytic_depth_at_every_pixel_centre(renderer):
    # the plane z = 3 seen by a camera turned 35 degrees: depth_z(u, v) = 3 / (R[2] . ray(u, v))
    w, h = 72, 56
    K = intrinsics_from_fov(w, h, 60.0, cx_offset=2.0)
    a = np.radians(35)
    T = look_at([0, 0, 0], [np.sin(a), 0.1, np.cos(a)], up=(0, -1, 0), roll=0.2)
    _, depth = renderer.render(plane_scene(3.0), K, T, w, h)
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1)
    expected = 3.0 / (rays @ T[2, :3])
    # exact at pixel centres (no MSAA sub-sample offset, no half-pixel shift) up to 24-bit depth quantisation
    assert np.abs(depth / expected - 1).max() < 5e-5


def test_a_point_lands_on_the_pixel_opencv_projection_predicts(renderer):
    # a tiny square facing the camera, centred on a world point: the depth hit must be at its projection
    p = np.array([0.4, -0.3, 4.0])
    s = 0.02
    import trimesh
    m = trimesh.Trimesh([p + [-s, -s, 0], p + [s, -s, 0], p + [s, s, 0], p + [-s, s, 0]], [[0, 2, 1], [0, 3, 2]],
                        process=False)
    scene = Scene(kind="dot", surfaces=[Surface(m, Material(base_color=np.ones(4)))],
                  lights=[Light("directional", np.ones(3), 2.0)], ambient=np.ones(3) * 0.3, bg_color=np.zeros(3),
                  camera_lo=-np.ones(3) * 9, camera_hi=np.ones(3) * 9, obstacles=np.zeros((0, 2, 3)),
                  targets=p[None], target_radius=np.ones(1))
    K = intrinsics_from_fov(96, 64, 50.0, cx_offset=3.0, cy_offset=-2.0)
    T = look_at([0.1, 0.05, 0.0], [0.0, 0.0, 5.0])
    _, depth = renderer.render(scene, K, T, 96, 64)
    pc = np.linalg.inv(T) @ np.r_[p, 1]
    u, v = K[0, 0] * pc[0] / pc[2] + K[0, 2], K[1, 1] * pc[1] / pc[2] + K[1, 2]
    ys, xs = np.nonzero(depth > 0)
    assert len(xs) > 0
    assert abs(xs.mean() - u) < 0.51 and abs(ys.mean() - v) < 0.51
    assert depth[int(round(v)), int(round(u))] == pytest.approx(pc[2], rel=1e-3)


def test_renderer_switches_image_sizes_and_stays_exact(renderer):
    for w, h in ((64, 48), (48, 64), (64, 48)):
        K = intrinsics_from_fov(w, h, 60.0)
        _, depth = renderer.render(plane_scene(1.5), K, np.eye(4), w, h)
        assert depth.shape == (h, w) and np.abs(depth - 1.5).max() < 1e-4


def test_lean_passes_give_the_same_pixels_and_depth_as_pyrenders_own_renderer(renderer):
    import pyrender

    from data.cameras import sample_views
    from data.scene import make_scene

    rng = np.random.default_rng(3)
    for kind in ("room", "cluster"):  # textured and plain materials, point/spot and directional lights
        scene = make_scene(rng, kind=kind)
        vs = sample_views(rng, scene, renderer, 2, 64, color=False)
        for v in vs.views:
            lean = renderer.render(scene, v.K, v.cam2world, v.width, v.height)
            inner = renderer._r._renderer
            cls = inner.__class__
            inner.__class__ = pyrender.renderer.Renderer  # pyrender's own passes, read-backs and uniforms
            try:
                ref = renderer.render(scene, v.K, v.cam2world, v.width, v.height)
            finally:
                inner.__class__ = cls
            assert cls is not pyrender.renderer.Renderer
            assert np.array_equal(lean[0], ref[0]) and np.array_equal(lean[1], ref[1])
            assert np.array_equal(lean[1], v.depth)


def test_render_rejects_bad_camera_inputs_with_clear_errors(renderer):
    with pytest.raises(ShapeError, match="K expected"):
        renderer.render(plane_scene(1.0), np.eye(4), np.eye(4), 32, 32)
    with pytest.raises(ShapeError, match="image size"):
        renderer.render(plane_scene(1.0), np.eye(3), np.eye(4), 0, 32)
    with pytest.raises(ShapeError, match="cam2world expected"):
        cv_to_gl_pose(np.eye(3))
    # each rendered wrong ground truth without a word before: a transposed, mirrored or NaN K, a scaled pose
    K = intrinsics_from_fov(32, 32, 60.0)
    for bad in (K.T, K * np.array([[-1.0], [1.0], [1.0]]), np.where(np.eye(3) > 0, np.nan, K)):
        with pytest.raises(ShapeError, match="K expected pinhole intrinsics"):
            renderer.render(plane_scene(1.0), bad, np.eye(4), 32, 32)
    scaled = np.diag([2.0, 2.0, 2.0, 1.0])
    with pytest.raises(ShapeError, match="cam2world expected a finite rigid transform"):
        renderer.render(plane_scene(1.0), K, scaled, 32, 32)


def test_a_scene_changed_after_a_render_is_rendered_as_it_is_now(renderer):
    # the renderer kept its build of the scene object: a plane added at 1 m did not show
    K = intrinsics_from_fov(32, 32, 60.0)
    scene = plane_scene(2.0)
    assert abs(float(renderer.render(scene, K, np.eye(4), 32, 32)[1][16, 16]) - 2.0) < 1e-4
    scene.surfaces.append(plane_scene(1.0).surfaces[0])
    assert abs(float(renderer.render(scene, K, np.eye(4), 32, 32)[1][16, 16]) - 1.0) < 1e-4
    scene.surfaces.pop()
    assert abs(float(renderer.render(scene, K, np.eye(4), 32, 32)[1][16, 16]) - 2.0) < 1e-4


def test_preview_writes_a_contact_sheet_of_a_shard(tiny_pairs, tmp_path):
    import cv2

    from data.preview import main as preview_main
    out = tmp_path / "sheet.png"
    assert preview_main([str(tiny_pairs / "shard-000000.tar"), "-o", str(out)]) == 0
    img = cv2.imread(str(out))
    assert img is not None and img.shape[0] >= 2 * 160 and img.shape[1] >= 7 * 160
    assert preview_main([str(tmp_path / "missing.tar"), "-o", str(out)]) == 2
    assert preview_main([str(tiny_pairs / "shard-000000.tar"), "-o", str(tmp_path / "sheet.txt")]) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sheet.png"]  # nothing half-written beside it
    with pytest.raises(SystemExit):  # argparse's one line: no sheet of no rows
        preview_main([str(tiny_pairs / "shard-000000.tar"), "-o", str(tmp_path / "none.png"), "--rows", "0"])
    assert not (tmp_path / "none.png").exists()
