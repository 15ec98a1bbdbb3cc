"""Unit tests of pointmap/reconstruction.py from a mutation review (session 90; each fast, each pinned to a mutant
the other tests let through), and, last, tests of the bugs it found."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent / "io"))
from recon_factory import make_recon  # noqa: E402

from pointmap.errors import ShapeError  # noqa: E402
from pointmap.geometry.cameras import crop_intrinsics, scale_intrinsics  # noqa: E402
from pointmap.geometry.rotations import axis_angle_to_matrix  # noqa: E402
from pointmap.reconstruction import K_to_map, K_to_original, Reconstruction, check_colour_range, to_canvas  # noqa: E402


def _plain(n=2, h=4, w=6, **over):
    """A small hand-made reconstruction at the original resolution (identity map_from_original)."""
    K = torch.tensor([[5.0, 0, 2.5], [0, 6.0, 1.5], [0, 0, 1]]).repeat(n, 1, 1)
    kw = dict(images=torch.full((n, h, w, 3), 0.5), cam2world=torch.eye(4).repeat(n, 1, 1), K=K,
              depth_z=torch.ones(n, h, w), conf=torch.ones(n, h, w))
    kw.update(over)
    return Reconstruction(**kw)


def _kwargs(recon):
    return dict(images=recon.images, cam2world=recon.cam2world, K=recon.K, depth_z=recon.depth_z, conf=recon.conf)


# ---- construction checks -------------------------------------------------------------------------------------------

def test_a_missing_required_tensor_is_refused_with_a_shape_error_naming_it():
    with pytest.raises(ShapeError, match="images expected a torch.Tensor"):
        _plain(images=None)


@pytest.mark.parametrize("name,value", [("masks", [[True]]), ("map_from_original", [[1.0, 1.0, 0.0, 0.0]] * 2)])
def test_an_optional_field_that_is_not_a_tensor_is_refused_with_a_shape_error_naming_it(name, value):
    with pytest.raises(ShapeError, match=f"{name} expected a torch.Tensor"):
        _plain(**{name: value})


def test_a_depth_map_with_an_extra_dimension_is_refused_with_a_shape_error():
    with pytest.raises(ShapeError, match=r"depth_z expected \[N, h, w\]"):
        _plain(depth_z=torch.ones(2, 4, 6, 1))


@pytest.mark.parametrize("name", ["cam2world", "K", "depth_z", "conf"])
def test_integer_geometry_or_confidence_is_refused(name):
    r = _plain()
    with pytest.raises(ShapeError, match=f"{name} expected a floating-point tensor"):
        _plain(**{name: getattr(r, name).long()})


def test_info_none_becomes_an_empty_dict_and_info_of_another_type_is_refused():
    assert _plain(info=None).info == {}
    with pytest.raises(ShapeError, match="info expected a dict"):
        _plain(info=[("a", 1)])


@pytest.mark.parametrize("name,shape", [("images", (2, 4, 6, 4)), ("images", (2, 6, 4, 3)), ("conf", (2, 4, 5)),
                                        ("cam2world", (2, 3, 4)), ("K", (1, 3, 3))])
def test_a_tensor_whose_shape_disagrees_with_depth_z_is_refused(name, shape):
    with pytest.raises(ShapeError, match=f"{name} expected"):
        _plain(**{name: torch.ones(shape)})


def test_uint8_images_become_float32_colours_in_zero_one():
    img = torch.zeros(2, 4, 6, 3, dtype=torch.uint8)
    img[0, 0, 0] = 255
    img[0, 0, 1] = 51
    r = _plain(images=img)
    assert r.images.dtype == torch.float32
    assert r.images[0, 0, 0].tolist() == [1.0, 1.0, 1.0] and r.images[0, 0, 1, 0] == pytest.approx(0.2)


def test_integer_images_other_than_uint8_are_refused():
    with pytest.raises(ShapeError, match="images expected floats"):
        _plain(images=torch.zeros(2, 4, 6, 3, dtype=torch.int32))


@pytest.mark.parametrize("name,index", [("images", (0, 1, 1, 0)), ("cam2world", (1, 0, 3)), ("K", (0, 0, 2)),
                                        ("depth_z", (1, 2, 3)), ("conf", (0, 0, 0))])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_values_are_refused_naming_the_tensor(name, index, bad):
    t = getattr(_plain(), name).clone()
    t[index] = bad
    with pytest.raises(ShapeError, match=f"{name} contains NaN or inf"):
        _plain(**{name: t})


def test_colours_are_checked_against_zero_one_with_a_one_percent_tolerance():
    for ok in (-0.009, 1.009, 0.0, 1.0):
        _plain(images=torch.full((2, 4, 6, 3), ok))
    for bad in (-0.02, 1.02, 255.0):
        with pytest.raises(ShapeError, match=r"images: expected colours in \[0, 1\]"):
            _plain(images=torch.full((2, 4, 6, 3), bad))


def test_an_empty_image_passes_the_colour_check():
    check_colour_range(torch.zeros(0, 3), "empty")


@pytest.mark.parametrize("name", ["depth_z", "conf"])
def test_negative_depth_or_confidence_is_refused_while_zero_means_no_value(name):
    t = torch.ones(2, 4, 6)
    t[1, 1, 1] = 0
    assert _plain(**{name: t}) is not None
    t[1, 1, 1] = -0.5
    with pytest.raises(ShapeError, match=f"{name} expected values >= 0"):
        _plain(**{name: t})


def test_the_default_map_from_original_is_the_identity_for_every_view():
    r = _plain(n=3)
    assert r.map_from_original.tolist() == [[1.0, 1.0, 0.0, 0.0]] * 3
    assert torch.equal(r.K_map, r.K)


@pytest.mark.parametrize("mfo", [[[1.0, 1.0, 0.0, 0.0]], [[1.0, 1.0, 0.0]] * 2, [[0.0, 1.0, 0.0, 0.0]] * 2,
                                 [[1.0, 0.0, 0.0, 0.0]] * 2, [[1.0, -1.0, 0.0, 0.0]] * 2,
                                 [[1.0, 1.0, float("nan"), 0.0]] * 2, [[1.0, 1.0, 0.0, float("inf")]] * 2])
def test_a_map_from_original_of_the_wrong_shape_or_without_positive_finite_scales_is_refused(mfo):
    with pytest.raises(ShapeError, match="map_from_original expected"):
        _plain(map_from_original=torch.tensor(mfo), original_sizes=[(6, 4)] * 2)


def test_map_sizes_default_to_the_canvas_as_width_height_pairs_and_nothing_is_padded():
    r = _plain(h=4, w=6)
    assert r.map_sizes == [(6, 4), (6, 4)] and r.original_sizes == [(6, 4), (6, 4)]
    assert not r.padded and bool(r.regions.all())


@pytest.mark.parametrize("sizes", [[(6, 4)], [(7, 4), (6, 4)], [(6, 5), (6, 4)], [(0, 4), (6, 4)], [(6, 0), (6, 4)],
                                   [(6.0, 4), (6, 4)], [(True, 4), (6, 4)], [(6, 4, 1), (6, 4)]])
def test_map_sizes_must_be_one_positive_int_pair_per_view_within_the_canvas(sizes):
    with pytest.raises(ShapeError, match="map_sizes expected 2 "):
        _plain(map_sizes=sizes)


def test_map_sizes_filling_the_canvas_exactly_are_accepted_and_stored_as_int_width_height():
    r = _plain(h=4, w=6, map_sizes=np.array([(6, 4), (3, 2)]))
    assert r.map_sizes == [(6, 4), (3, 2)] and all(type(x) is int for s in r.map_sizes for x in s)
    assert r.padded


def test_a_map_from_original_that_resizes_needs_the_original_sizes():
    with pytest.raises(ShapeError, match="original_sizes expected with a map_from_original"):
        _plain(map_from_original=torch.tensor([[0.5, 0.5, 0.0, 0.0]] * 2))


@pytest.mark.parametrize("sizes", [[(6, 4)], [(6, 4), (0, 4)], [(6, 4), (6, -1)], [(6, 4), (6.5, 4)], 7])
def test_original_sizes_must_be_one_positive_int_pair_per_view(sizes):
    with pytest.raises(ShapeError, match="original_sizes expected 2 "):
        _plain(original_sizes=sizes)


def test_default_names_are_view_000_png_onwards():
    assert _plain(n=3).names == ["view_000.png", "view_001.png", "view_002.png"]


@pytest.mark.parametrize("names,what", [(["a.png"], "names expected 2 non-empty strings"),
                                        (["a.png", "b.png", "c.png"], "names expected 2 non-empty strings"),
                                        (["a.png", ""], "names expected 2 non-empty strings"),
                                        (["a.png", 3], "names expected 2 non-empty strings"),
                                        (["a.png", "a.png"], "names expected to be unique")])
def test_names_must_be_one_non_empty_unique_string_per_view_with_a_message_saying_which_rule_failed(names, what):
    with pytest.raises(ShapeError, match=what):
        _plain(names=names)


@pytest.mark.parametrize("masks,what", [(torch.ones(2, 4, 5, dtype=torch.bool), r"masks expected \[2, 4, 6\]"),
                                        (torch.ones(2, 4, 6), "masks expected dtype bool")])
def test_masks_must_be_bools_of_the_maps_shape(masks, what):
    with pytest.raises(ShapeError, match=what):
        _plain(masks=masks)


def test_a_non_pinhole_K_is_refused_naming_the_first_bad_view_and_listing_all():
    K = _plain(n=3).K.clone()
    K[1, 0, 1] = 0.3  # skew
    K[2, 2, 0] = 2.5  # transposed
    with pytest.raises(ShapeError, match=r"K\[1\] = .*\(views \[1, 2\]\)"):
        _plain(n=3, K=K)


def test_a_non_rigid_pose_is_refused_naming_the_first_bad_view():
    c2w = torch.eye(4).repeat(3, 1, 1)
    c2w[1, :3, :3] *= 2
    c2w[2, 3, 0] = 1
    with pytest.raises(ShapeError, match=r"cam2world\[1\] = "):
        _plain(n=3, cam2world=c2w)


# ---- accessors -----------------------------------------------------------------------------------------------------

def test_len_is_the_number_of_views():
    assert len(_plain(n=3, h=5, w=7)) == 3


def test_padded_is_true_when_any_view_but_not_every_view_is_smaller_than_the_canvas():
    assert _plain(n=3, map_sizes=[(6, 4), (6, 3), (6, 4)]).padded
    assert not _plain(n=1, h=6, w=6).padded  # square canvas: (w, h) == (h, w), but also the plain case


def test_regions_and_crop_cover_exactly_each_views_width_by_height_at_the_top_left():
    r = _plain(n=2, h=4, w=6, map_sizes=[(6, 4), (5, 3)])
    reg = r.regions
    assert reg.dtype == torch.bool and reg.shape == (2, 4, 6)
    assert bool(reg[0].all()) and int(reg[1].sum()) == 15 and bool(reg[1, :3, :5].all())
    maps = torch.arange(2 * 4 * 6).reshape(2, 4, 6)
    assert torch.equal(r.crop(maps, 1), maps[1, :3, :5]) and torch.equal(r.crop(maps, 0), maps[0])
    assert r.crop(r.images, 1).shape == (3, 5, 3)


def test_K_map_is_K_resized_about_pixel_centres_then_cropped():
    recon = make_recon(n=3)
    for k in range(3):
        sx, sy, left, top = recon.map_from_original[k].tolist()
        expected = crop_intrinsics(scale_intrinsics(recon.K[k].double(), sx, sy), left, top)
        assert torch.allclose(recon.K_map[k].double(), expected, atol=1e-5)


def test_K_to_map_treats_x_and_y_and_left_and_top_separately():
    K = torch.tensor([[100.0, 0.0, 50.0], [0.0, 90.0, 40.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    out = K_to_map(K, torch.tensor([0.5, 0.25, 3.0, 7.0], dtype=torch.float64))
    expected = [[50.0, 0.0, 50.5 * 0.5 - 0.5 - 3.0], [0.0, 22.5, 40.5 * 0.25 - 0.5 - 7.0], [0.0, 0.0, 1.0]]
    assert torch.allclose(out, torch.tensor(expected, dtype=torch.float64))


def test_K_to_original_inverts_K_to_map_including_a_skew_and_unequal_scales():
    K = torch.tensor([[[100.0, 2.0, 50.0], [0.0, 90.0, 40.0], [0.0, 0.0, 1.0]]] * 2, dtype=torch.float64)
    mfo = torch.tensor([[0.5, 0.25, 3.0, 7.0], [2.0, 3.0, -1.0, 0.5]], dtype=torch.float64)
    Km = K_to_map(K, mfo)
    assert Km[0, 0, 1] == pytest.approx(1.0) and Km[1, 0, 1] == pytest.approx(4.0)  # skew follows the x scale
    assert torch.allclose(K_to_original(Km, mfo), K)
    assert torch.allclose(K_to_map(K_to_original(K, mfo), mfo), K)


def test_K_to_map_and_K_to_original_leave_their_inputs_alone():
    recon = make_recon(n=2)
    K = recon.K.clone()
    recon.K_map
    recon.K_map
    assert torch.equal(recon.K, K)
    Km = K_to_map(K, recon.map_from_original)
    Km_before = Km.clone()
    K_to_original(Km, recon.map_from_original)
    assert torch.equal(Km, Km_before)


def test_every_world_point_projects_back_onto_its_own_pixel_centre_with_K_map():
    recon = make_recon(n=2)
    pts = recon.pts_world.double()
    w2c = torch.linalg.inv(recon.cam2world.double())
    cam = pts @ w2c[:, None, :3, :3].transpose(-1, -2) + w2c[:, None, None, :3, 3]
    Km = recon.K_map.double()
    u = Km[:, 0, 0, None, None] * cam[..., 0] / cam[..., 2] + Km[:, 0, 2, None, None]
    v = Km[:, 1, 1, None, None] * cam[..., 1] / cam[..., 2] + Km[:, 1, 2, None, None]
    ok = recon.depth_z > 0
    vv, uu = torch.meshgrid(torch.arange(24.0), torch.arange(32.0), indexing="ij")
    assert torch.allclose(u[ok], uu.expand(2, -1, -1)[ok].double(), atol=1e-3)
    assert torch.allclose(v[ok], vv.expand(2, -1, -1)[ok].double(), atol=1e-3)
    assert torch.allclose(cam[..., 2][ok], recon.depth_z.double()[ok], atol=1e-5)


def test_pts_world_of_float64_depth_is_float64():
    r = _plain()
    assert _plain(depth_z=r.depth_z.double()).pts_world.dtype == torch.float64


def test_valid_needs_depth_confidence_above_min_conf_the_user_mask_and_the_views_region():
    depth = torch.ones(2, 4, 6)
    depth[0, 0, 0] = 0
    conf = torch.full((2, 4, 6), 2.0)
    conf[0, 0, 1] = 1.0
    conf[0, 0, 2] = 0.0
    masks = torch.ones(2, 4, 6, dtype=torch.bool)
    masks[0, 1, 0] = False
    r = _plain(depth_z=depth, conf=conf, masks=masks, map_sizes=[(6, 4), (5, 3)])
    v = r.valid()
    assert v.dtype == torch.bool and not v[0, 0, 0] and not v[0, 0, 2] and v[0, 0, 1] and not v[0, 1, 0]
    assert int(v[1].sum()) == 15 and bool(v[1, :3, :5].all())
    assert not r.valid(1.0)[0, 0, 1] and r.valid(0.5)[0, 0, 1]  # strictly above min_conf
    assert r.valid(masked=False)[0, 1, 0] and not r.valid(masked=False)[1, 3, 0]  # the region still applies
    assert int(r.valid().sum()) == 24 - 3 + 15


# ---- transformed ---------------------------------------------------------------------------------------------------

R1 = axis_angle_to_matrix(torch.tensor([0.3, -0.2, 0.9], dtype=torch.float64))
R2 = axis_angle_to_matrix(torch.tensor([0.1, 0.5, -0.4], dtype=torch.float64))
T1, T2 = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64), torch.tensor([0.0, 1.0, 3.0], dtype=torch.float64)


@pytest.mark.parametrize("scale,R,t,what", [
    (0.0, torch.eye(3), torch.zeros(3), "scale > 0"),
    (1.0, torch.eye(3), torch.zeros(3, 1), r"t \[3\]"),
    (1.0, torch.eye(3)[:2], torch.zeros(3), r"R \[3, 3\]"),
    (1.0, torch.tensor([[float("nan"), 0, 0], [0, 1, 0], [0, 0, 1]]), torch.zeros(3), "finite"),
    (1.0, torch.eye(3), torch.tensor([0.0, float("inf"), 0.0]), "finite"),
    (1.0, torch.diag(torch.tensor([1.0, 1.0, -1.0])), torch.zeros(3), "R to be a rotation"),  # a reflection
    (1.0, torch.eye(3) * 1.001, torch.zeros(3), "R to be a rotation"),
    (1.0, torch.tensor([[1.0, 0.01, 0], [0, 1, 0], [0, 0, 1]]), torch.zeros(3), "R to be a rotation"),
])
def test_transformed_refuses_anything_but_a_positive_scale_a_rotation_and_a_3_vector(scale, R, t, what):
    with pytest.raises(ShapeError, match=what):
        make_recon(n=1).transformed(scale, R, t)


def test_transformed_moves_every_point_by_the_similarity_and_scales_depth_only():
    recon = make_recon(n=2)
    moved = recon.transformed(2.5, R1, T1)
    ok = recon.depth_z > 0
    expected = 2.5 * recon.pts_world.double() @ R1.T + T1
    assert torch.allclose(moved.pts_world.double()[ok], expected[ok], atol=1e-4)
    assert torch.allclose(moved.depth_z, recon.depth_z * 2.5)
    assert torch.equal(moved.conf, recon.conf) and torch.equal(moved.K, recon.K)
    assert torch.equal(moved.images, recon.images)
    assert moved.cam2world.dtype == torch.float32
    assert torch.allclose(moved.cam2world[:, :3, :3].double(), R1 @ recon.cam2world[:, :3, :3].double(), atol=1e-6)


def test_transformed_keeps_float64_poses_in_full_precision():
    recon = make_recon(n=2)
    recon64 = Reconstruction(**{**_kwargs(recon), "cam2world": recon.cam2world.double()},
                             map_from_original=recon.map_from_original, original_sizes=recon.original_sizes)
    t = torch.tensor([4e6, -3e6, 123.0], dtype=torch.float64)
    moved = recon64.transformed(1.0, R1, t)
    assert moved.cam2world.dtype == torch.float64
    assert torch.allclose(moved.cam2world[:, :3, 3], recon64.cam2world[:, :3, 3] @ R1.T + t, rtol=0, atol=1e-8)


def test_transformed_records_the_similarity_and_keeps_the_other_info():
    recon = make_recon(n=2)
    moved = recon.transformed(2.0, R1, T1)
    rec = moved.info["transformed"]
    assert rec["scale"] == 2.0 and np.allclose(rec["R"], R1.numpy()) and np.allclose(rec["t"], T1.numpy())
    assert moved.info["align"] == recon.info["align"] and "transformed" not in recon.info


def test_transforming_twice_records_the_composed_similarity_from_the_original_world():
    recon = make_recon(n=2)
    twice = recon.transformed(2.0, R1, T1).transformed(0.5, R2, T2)
    rec = twice.info["transformed"]
    # x -> 0.5 R2 (2 R1 x + T1) + T2 = 1.0 (R2 R1) x + (0.5 R2 T1 + T2)
    assert rec["scale"] == pytest.approx(1.0)
    assert np.allclose(rec["R"], (R2 @ R1).numpy(), atol=1e-12)
    assert np.allclose(rec["t"], (0.5 * R2 @ T1 + T2).numpy(), atol=1e-12)


def test_transforming_twice_equals_transforming_once_by_the_composed_similarity():
    recon = make_recon(n=2)
    twice = recon.transformed(2.0, R1, T1).transformed(3.0, R2, T2)
    once = recon.transformed(6.0, R2 @ R1, 3.0 * R2 @ T1 + T2)
    assert torch.allclose(twice.cam2world, once.cam2world, atol=1e-5)
    assert torch.allclose(twice.depth_z, once.depth_z, rtol=1e-6)
    assert twice.info["transformed"]["scale"] == pytest.approx(6.0)
    assert np.allclose(twice.info["transformed"]["t"], once.info["transformed"]["t"], atol=1e-9)


# ---- to_canvas -----------------------------------------------------------------------------------------------------

def test_to_canvas_puts_each_map_at_the_top_left_of_the_largest_height_and_width_with_fill_elsewhere():
    a, b = torch.ones(3, 5, dtype=torch.int16), torch.full((4, 2), 2, dtype=torch.int16)
    out, sizes = to_canvas([a, b], fill=-1)
    assert sizes == [(5, 3), (2, 4)] and out.shape == (2, 4, 5) and out.dtype == torch.int16
    assert torch.equal(out[0, :3], a) and bool((out[0, 3] == -1).all())
    assert torch.equal(out[1, :, :2], b) and bool((out[1, :, 2:] == -1).all())


def test_to_canvas_pads_the_smaller_maps_when_one_map_already_has_the_canvas_size():
    big, small = torch.ones(4, 5), torch.full((2, 3), 2.0)
    out, sizes = to_canvas([big, small], fill=-1.0)
    assert sizes == [(5, 4), (3, 2)] and out.shape == (2, 4, 5)
    assert torch.equal(out[0], big) and torch.equal(out[1, :2, :3], small) and int((out[1] == -1).sum()) == 14


def test_to_canvas_of_maps_of_one_size_stacks_them():
    maps = [torch.rand(3, 4, 3) for _ in range(2)]
    out, sizes = to_canvas(maps, fill=7)
    assert torch.equal(out, torch.stack(maps)) and sizes == [(4, 3), (4, 3)]


def test_to_canvas_feeds_a_reconstruction_of_views_of_different_sizes():
    depth, sizes = to_canvas([torch.ones(4, 6), torch.ones(6, 4)])
    images, _ = to_canvas([torch.rand(4, 6, 3), torch.rand(6, 4, 3)])
    r = _plain(depth_z=depth, conf=depth.clone(), images=images, map_sizes=sizes)
    assert r.map_sizes == [(6, 4), (4, 6)] and r.padded and torch.equal(r.valid(), depth > 0)


@pytest.mark.parametrize("maps,what", [([], "at least one map"),
                                       ([torch.zeros(2, 2), torch.zeros(2, 2, dtype=torch.float64)], "one dtype"),
                                       ([torch.zeros(2, 2, 3), torch.zeros(2, 2, 4)], "trailing shape")])
def test_to_canvas_refuses_no_maps_or_maps_of_mixed_dtypes_or_trailing_shapes(maps, what):
    with pytest.raises(ShapeError, match=what):
        to_canvas(maps)


# --- bugs the review found ---------------------------------------------------------------------------------------

def test_numpy_images_flipped_from_bgr_to_rgb_with_a_negative_stride_are_taken():
    bgr = np.zeros((2, 4, 6, 3), np.uint8)
    bgr[..., 0] = 255  # blue in OpenCV's BGR order
    r = _plain(images=bgr[..., ::-1])  # the usual cv2 -> RGB idiom
    assert r.images[0, 0, 0].tolist() == [0.0, 0.0, 1.0]


def test_a_numpy_depth_map_flipped_upside_down_is_taken():
    depth = np.arange(2 * 4 * 6, dtype=np.float32).reshape(2, 4, 6) + 1
    r = _plain(depth_z=depth[:, ::-1])
    assert float(r.depth_z[0, 0, 0]) == float(depth[0, 3, 0])


@pytest.mark.parametrize("scale", [float("inf"), torch.tensor(float("inf"))])
def test_transformed_refuses_an_infinite_scale_with_its_own_message(scale):
    r = _plain()
    with pytest.raises(ShapeError, match="transformed expected scale > 0"):
        r.transformed(scale, torch.eye(3), torch.zeros(3))


@pytest.mark.parametrize("scale", [True, "2"])
def test_transformed_refuses_a_scale_that_is_not_a_real_number(scale):
    r = _plain()
    with pytest.raises(ShapeError, match="transformed expected scale > 0"):
        r.transformed(scale, torch.eye(3), torch.zeros(3))


def test_names_given_as_one_string_are_refused_rather_split_into_characters():
    with pytest.raises(ShapeError, match="names expected"):
        _plain(names="ab")


def test_maps_without_pixels_are_refused_naming_depth_z_not_map_sizes():
    with pytest.raises(ShapeError, match=r"depth_z expected .*at least one pixel"):
        _plain(n=1, h=4, w=0)


def test_to_canvas_refuses_maps_with_fewer_than_two_dimensions_with_a_shape_error():
    with pytest.raises(ShapeError, match="to_canvas expected maps"):
        to_canvas([torch.zeros(3), torch.zeros(4)])
