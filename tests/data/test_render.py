import re

import numpy as np
import pytest

from data.geom import intrinsics_from_fov, look_at
from data.render import cv_to_gl_pose, gl_to_cv_pose
from data.scene import SCENE_VERSIONS, Light, Material, Scene, Surface, plane_scene
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


def _tilted_plane_error(renderer, K, w, h):
    """The largest relative depth error over the plane z = 3 seen by a camera turned 35 degrees, against
    depth_z(u, v) = 3 / (R[2] . ray(u, v)) at every pixel centre."""
    a = np.radians(35)
    T = look_at([0, 0, 0], [np.sin(a), 0.1, np.cos(a)], up=(0, -1, 0), roll=0.2)
    _, depth = renderer.render(plane_scene(3.0), K, T, w, h)
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1)
    return np.abs(depth / (3.0 / (rays @ T[2, :3])) - 1).max()


def test_tilted_plane_renders_analytic_depth_at_every_pixel_centre(renderer):
    # exact at pixel centres (no MSAA sub-sample offset, no half-pixel shift) up to 24-bit depth quantisation
    assert _tilted_plane_error(renderer, intrinsics_from_fov(72, 56, 60.0, cx_offset=2.0), 72, 56) < 5e-5


def test_non_square_pixels_render_the_analytic_depth_of_a_tilted_plane(renderer):
    K = np.array([[70.0, 0.0, 37.5], [0.0, 45.0, 26.0], [0.0, 0.0, 1.0]])
    assert _tilted_plane_error(renderer, K, 72, 56) < 5e-5


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


def test_renderer_switches_image_sizes_stays_exact_and_frees_the_buffers_it_outgrew(renderer):
    from OpenGL import GL

    for w, h in ((64, 48), (48, 64), (64, 48)):
        K = intrinsics_from_fov(w, h, 60.0)
        _, depth = renderer.render(plane_scene(1.5), K, np.eye(4), w, h)
        assert depth.shape == (h, w) and np.abs(depth - 1.5).max() < 1e-4
    assert _tilted_plane_error(renderer, intrinsics_from_fov(1024, 768, 60.0), 1024, 768) < 5e-5  # larger than before
    old = renderer._plain
    renderer.render(plane_scene(1.5), intrinsics_from_fov(40, 30, 60.0), np.eye(4), 40, 30)
    renderer._r._platform.make_current()
    assert renderer._plain[0] == old[0] or not GL.glIsFramebuffer(old[0])  # deleted (or its name reused)
    assert all(rb in renderer._plain[1:3] or not GL.glIsRenderbuffer(rb) for rb in old[1:3])


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
    for w, h in ((32, 0), (8193, 32), (32.0, 32), (True, True)):
        with pytest.raises(ShapeError, match=f"image size expected ints in \\[1, 8192\\], got {w!r}x{h!r}"):
            renderer.render(plane_scene(1.0), K, np.eye(4), w, h)
    for znear in (0.0, -1.0, float("nan"), 500.0, "0.1", True):  # 0 or NaN rendered everything as background
        with pytest.raises(ShapeError, match="znear expected a distance in metres above 0 and below the far plane"):
            renderer.render(plane_scene(1.0), K, np.eye(4), 32, 32, znear=znear)
    for direction in ([0.0, 0.0, 0.0], [np.nan, 0.0, -1.0]):
        scene = plane_scene(1.0)
        scene.lights = [Light("directional", np.ones(3), 1.0, direction=np.array(direction))]
        with pytest.raises(ValueError, match="a light's direction expected a finite non-zero 3-vector"):
            renderer.render(scene, K, np.eye(4), 32, 32)
    # and the scene rendered next is not drawn the refused one's way; 4 is no version make_scene draws (yet)
    kept = plane_scene(1.0)
    renderer.render(kept, K, np.eye(4), 32, 32)
    for version in ("2", 2.0, 0, None, 4):
        scene = plane_scene(1.0)
        scene.version = version
        with pytest.raises(ValueError, match=re.escape(f"a scene's version expected a generator version (one of "
                                                       f"{SCENE_VERSIONS}), got {version!r}")):
            renderer.render(scene, K, np.eye(4), 32, 32)
        assert renderer._scene_key[0] is kept  # the refused scene is not kept as the built one, to be drawn some other way
    scene = plane_scene(1.0)
    scene.lights = [Light("area", np.ones(3), 1.0)]
    with pytest.raises(ValueError, match="light kind expected directional/point/spot, got 'area'"):
        renderer.render(scene, K, np.eye(4), 32, 32)


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


def _plane_lit_by(lights, distance=2.0, material=None, size=50.0):
    """plane_scene's plane (facing a camera at the origin) lit only by ``lights`` (no ambient light), in
    ``material`` when given."""
    scene = plane_scene(distance, size)
    scene.lights, scene.ambient = lights, np.zeros(3)
    if material is not None:
        scene.surfaces[0].material = material
    return scene


def _lit_plane(distance=2.0, size=50.0, color=(1.0, 1.0, 1.0), direction=(0.0, 0.0, 1.0), ambient=0.0):
    """plane_scene's plane in ``color``, one directional light travelling along ``direction`` (None: no light),
    ``ambient`` light, a red background."""
    lights = [] if direction is None else [Light("directional", np.ones(3), 3.0, direction=np.array(direction))]
    scene = _plane_lit_by(lights, distance, Material(base_color=np.r_[color, 1.0]), size)
    scene.ambient, scene.bg_color = np.full(3, ambient), np.array([1.0, 0.0, 0.0])
    return scene


def test_near_and_far_planes_clip_only_outside_znear_and_four_extents_or_50_m(renderer):
    K = intrinsics_from_fov(32, 32, 60.0)
    close = plane_scene(0.03)
    assert (renderer.render(close, K, np.eye(4), 32, 32)[1] == 0).all()  # nearer than the default 5 cm
    assert np.abs(renderer.render(close, K, np.eye(4), 32, 32, znear=0.01)[1] - 0.03).max() < 1e-5
    for distance, extent, seen in ((30.0, 5.0, True), (70.0, 20.0, True), (90.0, 20.0, False)):
        scene = plane_scene(distance, size=200.0)
        scene.extent = extent  # the far plane: max(4 x 5, 50) = 50 m, max(4 x 20, 50) = 80 m
        depth = renderer.render(scene, K, np.eye(4), 32, 32, color=False)[1]
        if seen:
            assert np.abs(depth / distance - 1).max() < 1e-3, (distance, extent)
        else:
            assert (depth == 0).all()


def test_rendered_images_are_writable_contiguous_arrays_and_color_false_renders_none(renderer):
    K = intrinsics_from_fov(32, 24, 60.0)
    rgb, depth = renderer.render(plane_scene(2.0), K, np.eye(4), 32, 24)
    for a in (rgb, depth):
        assert a.flags.c_contiguous and a.flags.writeable
    rgb[0, 0] = 0  # a read-only view of pyrender's buffer raised here
    assert renderer.render(plane_scene(2.0), K, np.eye(4), 32, 24, color=False)[0] is None
    assert renderer.render(plane_scene(2.0), K, np.eye(4), 32, 24, depth=False)[1] is None


def test_one_renderer_per_process_keeps_one_camera_and_draws_in_insertion_order(renderer):
    from data.cameras import sample_views
    from data.render import get_renderer
    from data.scene import make_scene

    assert get_renderer() is renderer
    scene = make_scene(np.random.default_rng(3), "room", texture_size=16)
    sample_views(np.random.default_rng(0), scene, renderer, 3, 48, color=False)
    ps = renderer._pscene
    assert len(ps.camera_nodes) == 1
    for nodes in (ps.mesh_nodes, ps.light_nodes):  # a set, iterated (drawn, lit) the same way in every process
        seqs = [n._seq for n in nodes]
        assert len(seqs) >= 2 and seqs == sorted(seqs)


def test_colours_lights_background_and_ambient_render_as_described(renderer):
    K = intrinsics_from_fov(32, 32, 60.0)
    red = renderer.render(_lit_plane(color=(1.0, 0.1, 0.1)), K, np.eye(4), 32, 32)[0].astype(float)
    assert red[..., 0].mean() > red[..., 2].mean() + 100  # base colour in RGB order
    front = renderer.render(_lit_plane(), K, np.eye(4), 32, 32)[0].astype(float).mean()
    behind = renderer.render(_lit_plane(direction=(0.0, 0.0, -1.0)), K, np.eye(4), 32, 32)[0].astype(float).mean()
    assert front > behind + 100  # a light shines along its direction: onto the plane's front, or from behind it
    dark = renderer.render(_lit_plane(direction=None), K, np.eye(4), 32, 32)[0].astype(float).mean()
    ambient = renderer.render(_lit_plane(direction=None, ambient=0.8), K, np.eye(4), 32, 32)[0].astype(float).mean()
    assert dark < 5 and ambient > 60
    small = _lit_plane(size=0.3)
    rgb = renderer.render(small, K, np.eye(4), 32, 32)[0]
    assert (rgb[0, 0] == [255, 0, 0]).all()  # the background's colour, in RGB order
    small.bg_color, small.ambient = np.array([0.0, 0.0, 1.0]), np.full(3, 0.5)  # the same scene object, changed
    again = renderer.render(small, K, np.eye(4), 32, 32)[0]
    assert (again[0, 0] == [0, 0, 255]).all() and again[16, 16].astype(int).sum() > rgb[16, 16].astype(int).sum()


def test_a_plane_seen_from_behind_has_the_depth_of_what_the_colour_shows(renderer):
    K = intrinsics_from_fov(32, 32, 60.0)
    T = look_at([0.0, 0.0, 5.0], [0.0, 0.0, 0.0])  # behind plane_scene's plane at z = 2, looking back at it
    plane = _lit_plane(color=(0.0, 1.0, 0.0), direction=(0.0, 0.0, -1.0))
    rgb, depth = renderer.render(plane, K, T, 32, 32)
    assert (rgb[..., 1] > rgb[..., 0]).all()  # the green plane fills the view, no red background
    assert np.abs(depth - 3.0).max() < 1e-4  # pyrender's depth-only pass culled it: background (0) everywhere
    plane.version = 2  # the same scene, as versions 1-2 rendered it (their datasets hold that)
    assert (renderer.render(plane, K, T, 32, 32)[1] == 0).all()


def test_every_colour_frame_is_antialiased_and_a_smooth_flag_changed_after_a_render_is_seen(renderer):
    K = intrinsics_from_fov(48, 48, 60.0)
    T = look_at([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], roll=0.3)  # the square's edges run slanted across pixels
    scene = _lit_plane(size=0.4)
    first, second = (renderer.render(scene, K, T, 48, 48)[0] for _ in range(2))
    assert np.array_equal(first, second)
    partial = (first[..., 1] > 5) & (first[..., 1] < first[..., 1].max() - 5)  # edge pixels partly covered
    assert partial.sum() >= 20
    import trimesh
    ball = trimesh.creation.icosphere(subdivisions=1, radius=0.5)
    ball.apply_translation([0.0, 0.0, 2.0])
    scene = Scene(**{**_lit_plane().__dict__, "surfaces": [Surface(ball, Material(base_color=np.ones(4)))],
                     "lights": [Light("directional", np.ones(3), 3.0, direction=np.array([0.3, 0.3, 1.0]))]})
    faceted = renderer.render(scene, K, np.eye(4), 48, 48)[0]
    scene.surfaces[0].smooth = True
    smooth = renderer.render(scene, K, np.eye(4), 48, 48)[0]
    assert np.abs(smooth.astype(int) - faceted.astype(int)).max() > 10


def _grey(renderer, scene, size=64):
    """The mean over RGB of ``scene`` rendered by an identity camera with a 60 degree field of view, and its K."""
    K = intrinsics_from_fov(size, size, 60.0)
    return renderer.render(scene, K, np.eye(4), size, size)[0].astype(float).mean(-1), K


def _linear(v):
    """Linear light from a rendered colour: pyrender writes sRGB-like values, v = 255 * linear ** (1 / 2.2)."""
    return (np.asarray(v, float) / 255.0) ** 2.2


def test_a_point_light_falls_off_with_the_square_of_distance_and_shines_from_where_it_is(renderer):
    def centre(intensity, distance):
        return _grey(renderer, _plane_lit_by([Light("point", np.ones(3), intensity, position=np.zeros(3))],
                                             distance))[0][32, 32]

    # the plane's centre faces a light at the camera: its irradiance is intensity / distance^2
    assert _linear(centre(2.0, 2.0)) / _linear(centre(2.0, 4.0)) == pytest.approx(4.0, rel=0.15)
    assert _linear(centre(4.0, 4.0)) / _linear(centre(2.0, 4.0)) == pytest.approx(2.0, rel=0.15)
    right, _ = _grey(renderer, _plane_lit_by([Light("point", np.ones(3), 2.0, position=np.array([1.0, 0.0, 1.5]))]))
    assert right[:, 40:].mean() > 2 * right[:, :24].mean()  # a light at +x (the image's right) lights that side


def test_a_spot_light_lights_only_its_cone_and_inside_its_inner_cone_is_a_point_light(renderer):
    inner, outer = np.radians(8.0), np.radians(12.0)
    spot = Light("spot", np.ones(3), 10.0, position=np.zeros(3), direction=np.array([0.0, 0.0, 1.0]),
                 inner_cone=inner, outer_cone=outer)
    lit, K = _grey(renderer, _plane_lit_by([spot]))
    point, _ = _grey(renderer, _plane_lit_by([Light("point", np.ones(3), 10.0, position=np.zeros(3))]))
    u, v = np.meshgrid(np.arange(64), np.arange(64))
    angle = np.arctan(np.hypot(u - K[0, 2], v - K[1, 2]) / K[0, 0])  # off the spot's axis, seen from the light
    assert (lit[angle > outer + np.radians(1.5)] == 0).all() and (angle > outer + np.radians(1.5)).sum() > 2000
    assert lit[angle < inner].min() > 100
    assert np.abs(lit - point)[angle < inner - np.radians(1.5)].max() <= 2
    between = (angle > inner + np.radians(1.0)) & (angle < outer - np.radians(1.0))
    assert (lit[between] < point[between] - 5).all()  # dimmed from the inner cone to the outer one


def test_a_smooth_metal_plane_mirrors_a_directional_light_where_the_reflection_law_puts_it(renderer):
    def lit_by(a, material, intensity=1.0):
        light = Light("directional", np.ones(3), intensity, direction=np.array([np.sin(a), 0.0, np.cos(a)]))
        return _grey(renderer, _plane_lit_by([light], material=material))

    mirror = Material(np.array([0.8, 0.8, 0.8, 1.0]), metallic=1.0, roughness=0.02)
    for a in np.radians([0.0, 15.0]):
        metal, K = lit_by(a, mirror)
        # the light travels along (sin a, 0, cos a) and leaves the plane z = 2 along (sin a, 0, -cos a): into the
        # camera from the point x = -2 tan a, whose pixel is (cx - f tan a, cy)
        v, u = np.nonzero(metal > 0.5 * metal.max())
        assert metal.max() > 200 and len(u) < 200  # a small bright highlight
        assert abs(u.mean() - (K[0, 2] - K[0, 0] * np.tan(a))) < 1.5 and abs(v.mean() - K[1, 2]) < 1.5
    matte_material = Material(np.array([0.8, 0.8, 0.8, 1.0]), metallic=0.0, roughness=0.8)
    matte, _ = lit_by(np.radians(15.0), matte_material)
    assert matte.std() < 5  # a matte plane under a directional light is evenly lit, in proportion to its intensity...
    # Lambert's law in pyrender's units: radiance = albedo (0.8, less the 4% a dielectric reflects) / pi * intensity
    # * cos(incidence); the specular lobe adds about 1% at roughness 0.8
    lambert = 0.8 * 0.96 / np.pi * np.cos(np.radians(15.0))
    assert _linear(matte) == pytest.approx(np.full_like(matte, lambert), rel=0.1)
    assert _linear(lit_by(np.radians(15.0), matte_material, intensity=2.0)[0]) == pytest.approx(
        np.full_like(matte, 2 * lambert), rel=0.1)
    assert np.median(metal) < 0.25 * np.median(matte)  # ...and a metal, which has no diffuse light, dark off the highlight


def test_a_fine_texture_seen_from_afar_is_filtered_through_its_mipmaps_not_aliased(renderer):
    checker = np.where(np.add.outer(np.arange(64), np.arange(64))[..., None] % 2 == 1, 255, 0).astype(np.uint8)
    checker = np.repeat(checker, 3, axis=-1)

    def seen(distance):
        scene = plane_scene(distance, size=100.0, texture=checker)
        scene.lights, scene.ambient = [], np.ones(3)
        return _grey(renderer, scene)[0]

    # 128 texels a metre: a pixel spans about 0.2 texels at 10 cm, and about 46 at 20 m
    near, far = seen(0.1), seen(20.0)
    assert near.std() > 25  # magnified, the checker shows (blurred by linear filtering)
    assert far.std() < 3 and abs(far.mean() - near.mean()) < 10  # minified, its mean; sampled without mipmaps, std 37
