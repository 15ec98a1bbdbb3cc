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
