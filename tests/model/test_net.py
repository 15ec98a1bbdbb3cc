"""The forward contract of PointmapNet: shapes, ranges, input checks, batching invariance."""

import pytest
import torch

import pointmap as pm
from pointmap.model.net import PointmapNet


def test_forward_returns_channels_last_maps_for_views_of_different_orientation(tiny_model):
    img1, img2 = torch.rand(2, 3, 32, 48), torch.rand(2, 3, 48, 32)
    with torch.no_grad():
        p = tiny_model(img1, img2)
    assert p.pts1_cam1.shape == (2, 32, 48, 3) and p.pts2_cam1.shape == (2, 48, 32, 3)
    assert p.conf1.shape == (2, 32, 48) and p.conf2.shape == (2, 48, 32)
    assert p.desc1.shape == (2, 32, 48, 8) and p.desc_conf2.shape == (2, 48, 32)
    assert (p.conf1 >= 1).all() and (p.desc_conf1 > 0).all()
    assert torch.allclose(p.desc1.norm(dim=-1), torch.ones(2, 32, 48), atol=1e-5)


def test_models_without_descriptor_head_return_none_descriptors():
    cfg = pm.PRESETS["test"].replace(head="linear", desc_dim=0)
    with torch.no_grad():
        p = PointmapNet(cfg).eval()(torch.rand(1, 3, 32, 32), torch.rand(1, 3, 32, 32))
    assert p.desc1 is None and p.desc_conf2 is None


def test_each_batch_element_is_independent_of_the_others(tiny_model):
    torch.manual_seed(0)
    a, b = torch.rand(3, 3, 32, 32), torch.rand(3, 3, 32, 32)
    with torch.no_grad():
        full = tiny_model(a, b)
        one = tiny_model(a[1:2], b[1:2])
    assert torch.allclose(full.pts2_cam1[1:2], one.pts2_cam1, atol=1e-5)


def test_cached_encoder_path_equals_the_plain_forward(tiny_model):
    a, b = torch.rand(1, 3, 32, 48), torch.rand(1, 3, 32, 48)
    with torch.no_grad():
        ref = tiny_model(a, b)
        got = tiny_model.decode_pair(tiny_model.encode(a), tiny_model.encode(b))
    for name, t in ref.as_dict().items():
        assert torch.allclose(t, getattr(got, name), atol=1e-5), name


@pytest.mark.parametrize("shape", [(1, 3, 30, 32), (1, 1, 32, 32), (3, 32, 32), (1, 3, 0, 32)])
def test_wrong_image_shapes_raise_a_shape_error_naming_the_expected_layout(tiny_model, shape):
    with pytest.raises(pm.ShapeError, match=r"expected \[B, 3, H, W\]"):
        tiny_model(torch.rand(shape), torch.rand(1, 3, 32, 32))


def test_checking_images_that_require_grad_gives_no_autograd_warning(tiny_model):
    import warnings

    img = torch.rand(1, 3, 32, 32, requires_grad=True)  # an image optimised through the network, say
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tiny_model.check_images("img", img)
    with pytest.raises(pm.ShapeError, match=r"\[0, 1\]"):
        tiny_model.check_images("img", (img * 3).detach().requires_grad_())


def test_out_of_range_or_nan_or_integer_images_are_refused(tiny_model):
    ok = torch.rand(1, 3, 32, 32)
    with pytest.raises(pm.ShapeError, match=r"\[0, 1\]"):
        tiny_model(ok * 255, ok)
    bad = ok.clone()
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(pm.ShapeError):
        tiny_model(bad, ok)
    with pytest.raises(pm.ShapeError, match="float"):
        tiny_model((ok * 255).to(torch.uint8), ok)
    with pytest.raises(pm.ShapeError, match="batch size"):
        tiny_model(torch.rand(2, 3, 32, 32), ok)


def test_official_presets_have_the_published_parameter_counts():
    # counts of the official implementation with random weights (anchors-spec 1.7), minus mask_token (768)
    expected = {"dust3r_224_linear": 532_342_784 - 768, "dust3r_512_dpt": 571_171_208 - 768,
                "mast3r_512": 688_638_856 - 768}
    with torch.device("meta"):
        got = {k: sum(p.numel() for p in PointmapNet(pm.PRESETS[k]).parameters()) for k in expected}
    assert got == expected


def test_invalid_configs_are_refused_with_the_reason():
    with pytest.raises(pm.CheckpointError, match="head expected"):
        pm.PRESETS["test"].replace(head="mlp")
    with pytest.raises(pm.CheckpointError, match="desc_dim"):
        pm.PRESETS["test"].replace(head="catmlp+dpt", desc_dim=0)


def test_a_model_first_run_in_inference_mode_can_then_be_trained():
    # the RoPE tables of a grid are cached on first use; inference tensors must not leak into training
    model = PointmapNet(pm.PRESETS["test"])
    a, b = torch.rand(1, 3, 48, 32), torch.rand(1, 3, 48, 32)
    with torch.inference_mode():
        model(a, b)
    model.train()
    pred = model(a, b)
    pred.pts1_cam1.sum().backward()
    assert model.patch_embed.proj.weight.grad is not None


def _pose_pair(seed=0):
    """A pose-head model and the same weights without the pose head (view 2's points in its own frame)."""
    torch.manual_seed(seed)
    with_pose = PointmapNet(pm.PRESETS["test"].replace(pose_head=True)).eval()
    local = PointmapNet(pm.PRESETS["test"]).eval()
    local.load_state_dict({k: v for k, v in with_pose.state_dict().items() if not k.startswith("pose_head")})
    return with_pose, local


def test_a_fresh_pose_head_predicts_the_identity_so_the_trunk_starts_where_it_was():
    with_pose, local = _pose_pair()
    img1, img2 = torch.rand(2, 3, 32, 48), torch.rand(2, 3, 32, 48)
    with torch.no_grad():
        a, b = with_pose(img1, img2), local(img1, img2)
    assert torch.equal(a.pts1_cam1, b.pts1_cam1) and torch.allclose(a.pts2_cam1, b.pts2_cam1, atol=1e-6)


def test_the_pose_head_moves_view_twos_own_points_rigidly_into_view_one():
    with_pose, local = _pose_pair(1)
    with torch.no_grad():
        with_pose.pose_head.out.weight.normal_(0, 0.5)  # a trained-looking head: a far-from-identity pose
    img1, img2 = torch.rand(1, 3, 32, 32), torch.rand(1, 3, 32, 32)
    with torch.no_grad():
        pred = with_pose(img1, img2)
        moved, own = pred.pts2_cam1[0].reshape(-1, 3), local(img1, img2).pts2_cam1[0].reshape(-1, 3)
    assert not torch.allclose(moved, own, atol=1e-3)
    assert local(img1, img2).cam2_to_cam1 is None  # no pose head, no transform
    T = pred.cam2_to_cam1[0].double()  # the transform the prediction carries is the one that moved them
    assert torch.allclose(moved.double(), own.double() @ T[:3, :3].T + T[:3, 3], atol=1e-5)
    dist = lambda p: (p.double()[:, None] - p.double()[None]).norm(dim=-1)  # noqa: E731
    assert torch.allclose(dist(moved), dist(own), atol=1e-5)  # all distances kept: a rigid motion


def test_under_bf16_autocast_the_heads_run_in_float32_as_the_heads_of_a_float32_run():
    # before, autocast ran the heads' linear layers in bf16: float32 tokens, bf16 points and a pose 8e-3 from rigid
    with_pose, _ = _pose_pair(1)
    with torch.no_grad():
        with_pose.pose_head.out.weight.normal_(0, 0.5)
    img1, img2 = torch.rand(1, 3, 32, 32), torch.rand(1, 3, 32, 32)
    with torch.no_grad():
        e1, e2 = with_pose.encode(img1), with_pose.encode(img2)
        t1, t2 = with_pose.decode(e1, e2)
        want = with_pose.heads(t1, t2, e1.grid, e2.grid)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            got = with_pose.heads(t1, t2, e1.grid, e2.grid)
    for a, b in ((got.pts1_cam1, want.pts1_cam1), (got.pts2_cam1, want.pts2_cam1), (got.cam2_to_cam1, want.cam2_to_cam1)):
        assert a.dtype == torch.float32 and torch.equal(a, b)


def test_rotation_from_6d_returns_the_rotation_its_first_two_columns_came_from():
    from pointmap.model.heads import rotation_from_6d

    torch.manual_seed(0)
    q = torch.nn.functional.normalize(torch.randn(5, 4), dim=-1)
    w, x, y, z = q.unbind(-1)
    R = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                     2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                     2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1).reshape(5, 3, 3)
    six = torch.cat([R[..., 0], R[..., 1]], -1)
    assert torch.allclose(rotation_from_6d(six), R, atol=1e-5)
    any_r = rotation_from_6d(torch.randn(100, 6))
    assert torch.allclose(any_r @ any_r.transpose(1, 2), torch.eye(3).expand(100, 3, 3), atol=1e-5)
    assert torch.allclose(torch.linalg.det(any_r), torch.ones(100), atol=1e-5)


def test_a_pose_head_model_saves_and_loads_and_its_pose_head_is_a_head_for_fine_tuning(tmp_path):
    from pointmap.checkpoint import load_trunk, save_model

    with_pose, local = _pose_pair(2)
    path = save_model(with_pose, tmp_path / "m.safetensors")
    back = pm.load_model(str(path))
    assert back.cfg.pose_head and torch.equal(back.pose_head.out.weight, with_pose.pose_head.out.weight)
    fresh = load_trunk(PointmapNet(pm.PRESETS["test"].replace(pose_head=True)), local.state_dict())
    assert fresh and all(k.startswith("pose_head.") for k in fresh)


def test_a_pose_head_checkpoint_is_refused_as_the_trunk_of_a_model_without_one():
    from pointmap.checkpoint import load_trunk
    from pointmap.errors import CheckpointError

    with_pose, _ = _pose_pair(3)
    with pytest.raises(CheckpointError, match="has a pose head"):
        load_trunk(PointmapNet(pm.PRESETS["test"]), with_pose.state_dict())


def test_the_pose_heads_translation_follows_the_scale_of_the_predicted_points():
    from pointmap.model.heads import PoseHead

    torch.manual_seed(4)
    head = PoseHead(pm.PRESETS["test"]).eval()
    with torch.no_grad():
        head.out.weight.normal_(0, 0.5)
    tok1, tok2, pts1 = torch.randn(1, 4, 32), torch.randn(1, 4, 32), torch.rand(1, 32, 32, 3) + 1
    with torch.no_grad():
        T, T3 = head(tok1, tok2, (2, 2), (2, 2), pts1), head(tok1, tok2, (2, 2), (2, 2), 3 * pts1)
    assert torch.allclose(T[:, :3, :3], T3[:, :3, :3], atol=1e-5)  # the rotation ignores the scale
    assert torch.allclose(3 * T[:, :3, 3], T3[:, :3, 3], atol=1e-5) and T[:, :3, 3].abs().max() > 1e-3


def _stem_model(channels: int = 4, fuse_std: float = 0.0):
    torch.manual_seed(0)
    model = PointmapNet(pm.PRESETS["test"].replace(desc_stem=channels)).eval()
    if fuse_std:
        with torch.no_grad():
            for head in (model.downstream_head1, model.downstream_head2):
                head.desc_fuse.weight.normal_(0, fuse_std)
    return model


def test_a_model_gaining_a_descriptor_stem_starts_as_the_model_it_was(tiny_model):
    from pointmap.checkpoint import load_trunk

    stem = PointmapNet(tiny_model.cfg.replace(desc_stem=4)).eval()
    fresh = load_trunk(stem, tiny_model.state_dict())
    assert fresh and all(k.startswith(("desc_stem.", "downstream_head1.desc_fuse", "downstream_head2.desc_fuse"))
                         for k in fresh)
    a, b = torch.rand(1, 3, 32, 48), torch.rand(1, 3, 32, 48)
    with torch.no_grad():
        ref, got = tiny_model(a, b), stem(a, b)
    for name, t in ref.as_dict().items():
        assert torch.equal(t, getattr(got, name)), name


def test_the_descriptor_stem_changes_only_descriptors():
    model = _stem_model(fuse_std=0.5)
    plain = PointmapNet(model.cfg.replace(desc_stem=0)).eval()
    plain.load_state_dict({k: v for k, v in model.state_dict().items() if k in plain.state_dict()})
    a, b = torch.rand(1, 3, 32, 32), torch.rand(1, 3, 32, 48)
    with torch.no_grad():
        got, ref = model(a, b), plain(a, b)
    assert torch.equal(got.pts1_cam1, ref.pts1_cam1) and torch.equal(got.conf2, ref.conf2)
    assert float((got.desc1 - ref.desc1).norm(dim=-1).min()) > 1e-4
    assert float((got.desc_conf2 - ref.desc_conf2).abs().max()) > 1e-4


def test_the_descriptor_stem_sees_a_pixel_within_its_15_pixel_receptive_field_only():
    from pointmap.model.heads import DescStem

    torch.manual_seed(0)
    stem = DescStem(4, 16).eval()
    a = torch.rand(1, 3, 48, 48)
    b = a.clone()
    b[0, :, 20, 30] += 0.5
    with torch.no_grad():  # back to [B, C, H, W] from the token layout
        fa, fb = (torch.nn.functional.pixel_shuffle(stem(x).transpose(1, 2).reshape(1, 4 * 256, 3, 3), 16)
                  for x in (a, b))
    changed = (fa - fb).abs().amax(dim=1)[0] > 0
    ys, xs = torch.nonzero(changed, as_tuple=True)
    assert changed[20, 30]
    assert int(ys.min()) == 20 - 7 and int(ys.max()) == 20 + 7 and int(xs.min()) == 30 - 7 and int(xs.max()) == 30 + 7


def test_the_descriptor_stem_learns_from_the_first_step():
    model = _stem_model().train()
    p = model(torch.rand(2, 3, 32, 32), torch.rand(2, 3, 32, 32))
    (p.desc1.sum() + p.desc2.square().sum() + p.desc_conf1.sum()).backward()
    assert model.downstream_head1.desc_fuse.weight.grad.abs().sum() > 0  # zero-init fuse, non-zero gradient
    assert model.desc_stem.convs[0].weight.grad is not None


def test_cached_encodings_of_a_stem_model_carry_its_local_features_through_batching():
    from pointmap.model.net import Encoded

    model = _stem_model(fuse_std=0.5)
    a, b, c = (torch.rand(1, 3, 32, 48) for _ in range(3))
    with torch.no_grad():
        ea, eb, ec = model.encode(a), model.encode(b), model.encode(c)
        assert ea.local.shape == (1, 2 * 3, 4 * 16 * 16)
        both = model.decode_pair(Encoded.cat([ea, eb]), Encoded.cat([eb, ec]))
        ref = model(torch.cat([a, b]), torch.cat([b, c]))
        views = [a[0], b[0], c[0]]
        preds = pm.predict_pairs(model, views, [(0, 1), (1, 2)], batch_size=2, quiet=True)
    for name, t in ref.as_dict().items():
        assert torch.allclose(t, getattr(both, name), atol=1e-5), name
    assert torch.allclose(preds[(1, 2)].desc1, ref.desc1[1:2], atol=1e-5)
    with pytest.raises(pm.ShapeError, match="different grids"):
        Encoded.cat([ea, model.encode(torch.rand(1, 3, 32, 32))])


def test_a_stem_model_refuses_encodings_without_local_features():
    from pointmap.model.net import Encoded

    model = _stem_model()
    enc = model.encode(torch.rand(1, 3, 32, 32))
    with pytest.raises(pm.ShapeError, match="local features"):
        model.decode_pair(Encoded(enc.tokens, enc.grid), enc)


@pytest.mark.parametrize("kw", [dict(desc_stem=-1), dict(desc_stem=8, head="linear", desc_dim=0)])
def test_invalid_descriptor_stems_are_refused_by_the_config(kw):
    with pytest.raises(pm.CheckpointError, match="desc_stem"):
        pm.PRESETS["test"].replace(**kw)


def test_images_of_another_dtype_than_the_models_are_refused_naming_both(tiny_model):
    x = torch.rand(1, 3, 32, 32)
    with pytest.raises(pm.ShapeError, match="img1 expected the model's torch.float32 on cpu, got torch.float64"):
        tiny_model(x.double(), x.double())
    with torch.inference_mode():  # lower precisions promote to the model's: as before, they run
        half = tiny_model(x.half(), x.half()).pts1_cam1
        full = tiny_model(x.half().float(), x.half().float()).pts1_cam1
    assert torch.equal(half, full)


def test_a_model_converted_whole_to_half_or_bfloat16_is_refused_and_a_half_backbone_runs(tiny_model):
    import copy

    from export.graphs import half_backbone

    x = torch.rand(1, 3, 32, 32)
    for dtype in (torch.float16, torch.bfloat16):
        whole = copy.deepcopy(tiny_model).to(dtype)
        with pytest.raises(pm.ShapeError, match=f"heads expected float32 weights, got {dtype}"):
            whole(x.to(dtype), x.to(dtype))
    with torch.inference_mode():
        out = half_backbone(tiny_model)(x.half(), x.half())
    assert out.pts1_cam1.dtype == torch.float32 and bool(torch.isfinite(out.pts1_cam1).all())


def test_the_stages_check_what_they_are_given(tiny_model):
    with pytest.raises(pm.ShapeError, match="positive multiples of 16, got \\[1, 3, 30, 30\\]"):
        tiny_model.encode(torch.rand(1, 3, 30, 30))
    with pytest.raises(pm.ShapeError, match="values in \\[0, 1\\]"):
        tiny_model.encode(torch.full((1, 3, 32, 32), float("nan")))
    x = torch.rand(1, 3, 32, 32)
    with pytest.raises(pm.ShapeError, match="enc1 expected this model's encode\\(\\) output .*got Tensor"):
        tiny_model.decode_pair(x, x)
    other = PointmapNet(pm.PRESETS["test"].replace(enc_dim=64, enc_heads=2)).eval()
    with pytest.raises(pm.ShapeError, match="float tokens \\[B, 2\\*2, 32\\] for its grid \\(2, 2\\)"):
        tiny_model.decode_pair(other.encode(x), other.encode(x))
    from pointmap.model.net import Encoded

    with torch.no_grad():
        enc = tiny_model.encode(x)
    for bad, message in ((Encoded(enc.tokens.half(), enc.grid), "enc1 expected tokens of the model's torch.float32"),
                         (Encoded(enc.tokens.long(), enc.grid), "float tokens .*got tokens \\[1, 4, 32\\] torch.int64"),
                         (Encoded(enc.tokens * float("nan"), enc.grid), "enc1 tokens hold NaN or inf values"),
                         (Encoded(enc.tokens, (2, 2, 1)), "enc1.grid expected \\(h, w\\), two positive ints"),
                         (Encoded(enc.tokens, (-2, -2)), "enc1.grid expected")):
        with pytest.raises(pm.ShapeError, match=message):
            tiny_model.decode_pair(bad, enc)
    stem = PointmapNet(pm.PRESETS["test"].replace(desc_stem=4)).eval()
    with torch.no_grad():
        good = stem.encode(x)
        with pytest.raises(pm.ShapeError, match="enc1.local expected the descriptor stem's local features \\[B, 2\\*2, 1024\\]"):
            stem.decode_pair(Encoded(good.tokens, good.grid, good.local[:, :, :7]), good)


@pytest.mark.parametrize("kw,message", [
    (dict(head="dpt", desc_dim=0, patch_size=8), "a DPT head needs patch_size 16"),
    (dict(img_std=(0, 0, 0)), "img_std expected positive values"),
    (dict(img_mean=(0.5, 0.5)), "img_mean expected 3 finite numbers"),
    (dict(dpt_layer_dims=(8, 16, 24)), "dpt_layer_dims expected 4 positive integers"),
    (dict(dpt_feature_dim=0), "dpt_feature_dim expected a positive integer"),
    (dict(two_confs="no"), "two_confs expected true or false"),
])
def test_configs_the_model_cannot_build_or_would_run_wrong_are_refused(kw, message):
    with pytest.raises(pm.CheckpointError, match=message):
        pm.PRESETS["test"].replace(**kw)


def test_a_model_built_from_a_name_or_nothing_is_refused_with_the_way_to_build_it():
    from pointmap.errors import CheckpointError
    from pointmap.model.config import ModelConfig

    with pytest.raises(ValueError, match=r"expected a ModelConfig, got str \(PRESETS\['small'\] is the config; "
                                         r"pm.load_model\('small'\) the trained model\)"):
        PointmapNet("small")
    with pytest.raises(ValueError, match="expected a ModelConfig, got NoneType"):
        PointmapNet(None)
    with pytest.raises(CheckpointError, match="a model config expected a dict, got NoneType"):
        ModelConfig.from_dict(None)


def _focal_pair(seed=0):
    """A pose-head model with a focal head, and the same weights without it; its pointmaps put every point in front
    of the camera (a fresh head's are behind it: no focal to read)."""
    torch.manual_seed(seed)
    with_focal = PointmapNet(pm.PRESETS["test"].replace(pose_head=True, focal_head=True)).eval()
    with torch.no_grad():
        for h in (with_focal.downstream_head1, with_focal.downstream_head2):
            h.dpt.head[4].bias[2] += 6.0
    plain = PointmapNet(pm.PRESETS["test"].replace(pose_head=True)).eval()
    plain.load_state_dict({k: v for k, v in with_focal.state_dict().items() if not k.startswith("focal_head")})
    return with_focal, plain


def test_a_fresh_focal_head_returns_each_views_pointmap_focal_and_changes_nothing_else():
    from pointmap.geometry.cameras import invert_rigid, transform_points
    from pointmap.geometry.focal import focal_from_pointmap

    with_focal, plain = _focal_pair()
    img1, img2 = torch.rand(2, 3, 32, 48), torch.rand(2, 3, 32, 48)
    with torch.no_grad():
        a, b = with_focal(img1, img2), plain(img1, img2)
    assert torch.equal(a.pts1_cam1, b.pts1_cam1) and torch.equal(a.pts2_cam1, b.pts2_cam1)
    assert b.focal1 is None and b.focal2 is None
    own2 = transform_points(invert_rigid(b.cam2_to_cam1.double()), b.pts2_cam1.double()).float()  # view 2's frame
    usable = lambda f: torch.where(torch.isfinite(f) & (f > 0), f, torch.full_like(f, 48.0))  # noqa: E731 (max(H, W))
    f1, f2 = usable(focal_from_pointmap(b.pts1_cam1)), usable(focal_from_pointmap(own2))
    assert (f1 != 48).all()
    assert torch.allclose(a.focal1, f1, rtol=1e-5) and torch.allclose(a.focal2, f2, rtol=1e-3)


def test_a_trained_focal_head_scales_the_pointmap_focal_and_falls_back_where_the_pointmap_has_none():
    from pointmap.model.heads import FocalHead

    torch.manual_seed(1)
    head = FocalHead(pm.PRESETS["test"]).eval()
    tok, pts = torch.randn(2, 4, 32), torch.rand(2, 32, 32, 3) + torch.tensor([0.0, 0.0, 2.0])
    with torch.no_grad():
        f0 = head(tok, (2, 2), pts)
        head.out.bias.fill_(0.5)
        assert torch.allclose(head(tok, (2, 2), pts), f0 * torch.e ** 0.5, rtol=1e-5)
        head.out.bias.fill_(10.0)  # the correction is bounded: at most e^3 either way
        assert torch.allclose(head(tok, (2, 2), pts), f0 * torch.e ** 3, rtol=1e-5)
        behind = pts * torch.tensor([1.0, 1.0, -1.0])
        head.out.bias.zero_()
        assert torch.equal(head(tok, (2, 2), behind), torch.full((2,), 32.0))  # max(H, W): a 53-degree view


def test_a_focal_head_needs_a_pose_head_and_loads_into_a_model_built_with_one(tmp_path):
    from pointmap.checkpoint import load_trunk, save_model
    from pointmap.errors import CheckpointError

    with pytest.raises(CheckpointError, match="focal_head needs pose_head"):
        pm.PRESETS["test"].replace(focal_head=True)
    with_focal, plain = _focal_pair(2)
    with torch.no_grad():
        with_focal.focal_head.out.weight.normal_(0, 0.1)
    back = pm.load_model(str(save_model(with_focal, tmp_path / "f.safetensors")))
    assert back.cfg.focal_head and torch.equal(back.focal_head.out.weight, with_focal.focal_head.out.weight)
    fresh = load_trunk(PointmapNet(with_focal.cfg), plain.state_dict())  # the focal head is a head: it starts fresh
    assert fresh and all(k.startswith("focal_head.") for k in fresh)


def test_indexing_a_prediction_keeps_the_batch_dimension_and_refuses_indices_outside_it(tiny_model):
    import numpy as np

    x = torch.rand(3, 3, 32, 32)
    with torch.inference_mode():
        pred = tiny_model(x, x.flip(0))
    for idx, row in ((0, 0), (2, 2), (-1, 2), (-3, 0), (np.int64(1), 1)):
        assert torch.equal(pred[idx].pts1_cam1, pred.pts1_cam1[row:row + 1]), idx
    for idx in (3, -4):
        with pytest.raises(IndexError, match=f"index {idx} is outside its batch of 3"):
            pred[idx]
