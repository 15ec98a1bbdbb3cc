import numpy as np
import pytest
import torch

import pointmap as pm


class CountingModel(torch.nn.Module):
    """Wraps a model and counts encoder calls per image."""

    def __init__(self, inner):
        super().__init__()
        self.inner, self.encoded_images = inner, 0
        self.check_images, self.decode_pair = inner.check_images, inner.decode_pair

    def encode(self, img):
        self.encoded_images += img.shape[0]
        return self.inner.encode(img)


def views(n, shapes=None):
    rng = np.random.default_rng(0)
    shapes = shapes or [(48, 64)] * n
    return [pm.View(torch.from_numpy(rng.random((3, *s), dtype=np.float32)), (s[1], s[0]), (1, 1, 0, 0), f"{k}.png", k)
            for k, s in enumerate(shapes)]


def test_every_pair_is_predicted_in_both_orders_with_each_image_encoded_once(tiny_model):
    model = CountingModel(tiny_model)
    vs = views(4)
    preds = pm.predict_pairs(model, vs, pm.make_pairs(4), batch_size=3, quiet=True)
    assert set(preds) == {(i, j) for i in range(4) for j in range(4) if i != j}
    assert model.encoded_images == 4
    with torch.no_grad():
        ref = tiny_model(vs[3].img[None], vs[1].img[None])
    for name, t in ref.as_dict().items():
        assert torch.allclose(getattr(preds[(3, 1)], name), t, atol=1e-5), name


def test_views_of_different_shapes_are_batched_separately(tiny_model):
    vs = views(3, shapes=[(48, 64), (64, 48), (48, 64)])
    preds = pm.predict_pairs(tiny_model, vs, [(0, 1), (1, 2)], quiet=True)
    assert preds[(0, 1)].pts2_cam1.shape == (1, 64, 48, 3)
    assert preds[(2, 1)].pts1_cam1.shape == (1, 48, 64, 3)


def test_storage_options_shrink_what_is_kept(tiny_model):
    preds = pm.predict_pairs(tiny_model, views(2), [(0, 1)], keep_desc=False, store_dtype=torch.float16, quiet=True)
    assert preds[(0, 1)].desc1 is None and preds[(0, 1)].pts1_cam1.dtype == torch.float16


def test_invalid_pairs_are_refused(tiny_model):
    with pytest.raises(pm.GraphError):
        pm.predict_pairs(tiny_model, views(2), [(0, 0)], quiet=True)
    with pytest.raises(pm.GraphError):
        pm.predict_pairs(tiny_model, views(2), [(0, 5)], quiet=True)
    with pytest.raises(pm.GraphError):
        pm.predict_pairs(tiny_model, views(2), [], quiet=True)
    with pytest.raises(pm.ShapeError):
        pm.predict_pairs(tiny_model, [torch.rand(4, 4)], [(0, 1)], quiet=True)


def test_pairs_that_are_not_index_pairs_a_fractional_batch_size_and_a_non_model_are_refused(tiny_model):
    for bad in [(0.5, 1), (0, 1, 2), "01"]:
        with pytest.raises(pm.GraphError, match="pairs expected \\(i, j\\) pairs of image indices"):
            pm.predict_pairs(tiny_model, views(2), [bad], quiet=True)
    assert set(pm.predict_pairs(tiny_model, views(2), [(np.int64(0), np.int64(1))], quiet=True)) == {(0, 1), (1, 0)}
    for rows in (np.array([[0, 1], [1, 0]]), torch.tensor([[0, 1], [1, 0]])):  # as pairs_from_list takes them
        assert set(pm.predict_pairs(tiny_model, views(2), rows, quiet=True)) == {(0, 1), (1, 0)}
    with pytest.raises(pm.GraphError, match=r"pairs expected an \[M, 2\] array of image indices, got shape \[3\]"):
        pm.predict_pairs(tiny_model, views(2), np.array([0, 1, 1]), quiet=True)
    with pytest.raises(pm.ShapeError, match="batch_size expected an int >= 1, got 2.5"):
        pm.predict_pairs(tiny_model, views(2), [(0, 1)], batch_size=2.5, quiet=True)
    with pytest.raises(pm.CheckpointError, match="expected a model .*got NoneType"):
        pm.predict_pairs(None, views(2), [(0, 1)], quiet=True)
    for bad in (torch.int64, "half"):  # int64 truncated every pointmap to whole numbers
        with pytest.raises(pm.ShapeError, match="store_dtype expected None or a floating torch dtype"):
            pm.predict_pairs(tiny_model, views(2), [(0, 1)], store_dtype=bad, quiet=True)


def test_image_similarity_is_the_share_of_mutual_nearest_tokens_counted_one_by_one(tiny_model):
    from pointmap.inference import image_similarity

    vs = views(4, [(48, 64), (48, 64), (64, 48), (48, 64)])
    sim = image_similarity(tiny_model, vs, batch_size=3)
    assert sim.shape == (4, 4) and torch.equal(sim, sim.T) and torch.equal(sim.diagonal(), torch.ones(4, dtype=sim.dtype))
    with torch.inference_mode():  # the slow reference: each image encoded alone, every token's nearest by a loop
        toks = [tiny_model.encode(v.img[None]).tokens[0].float() for v in vs]

    def nearest(t, others):
        return [max(range(len(others)), key=lambda q: float(torch.cosine_similarity(t[p], others[q], dim=0)))
                for p in range(len(t))]

    for i in range(4):
        for j in range(i + 1, 4):
            ij, ji = nearest(toks[i], toks[j]), nearest(toks[j], toks[i])
            mutual = sum(ji[q] == p for p, q in enumerate(ij))
            assert float(sim[i, j]) == pytest.approx(mutual / min(len(toks[i]), len(toks[j])))
    assert 0 <= float(sim.min()) and float(sim.max()) <= 1


def test_predictions_and_pooled_tokens_carry_no_autograd_graph(tiny_model):
    from pointmap.inference import pooled_tokens

    assert any(p.requires_grad for p in tiny_model.parameters())  # a model straight from training or load_model
    preds = pm.predict_pairs(tiny_model, views(2), [(0, 1)], quiet=True)
    assert not any(t.requires_grad for p in preds.values() for t in vars(p).values() if isinstance(t, torch.Tensor))
    assert not pooled_tokens(tiny_model, views(2)).requires_grad


def test_encodings_passed_in_give_the_same_predictions_and_similarity_without_encoding_again(tiny_model):
    from pointmap.inference import encode_views, image_similarity

    vs = views(4, [(48, 64), (48, 64), (64, 48), (48, 64)])
    pairs = [(0, 1), (1, 2), (3, 2)]
    fresh = pm.predict_pairs(tiny_model, vs, pairs, batch_size=2, quiet=True)
    sim = image_similarity(tiny_model, vs)
    model = CountingModel(tiny_model)
    encodings = encode_views(model, [v.img for v in vs], batch_size=3)
    assert torch.equal(image_similarity(model, vs, encodings=encodings), sim)
    reused = pm.predict_pairs(model, vs, pairs, batch_size=2, quiet=True, encodings=encodings)
    assert model.encoded_images == 4  # once each, by encode_views alone
    assert set(reused) == set(fresh)
    for e in fresh:
        for name, t in fresh[e].as_dict().items():
            assert torch.allclose(getattr(reused[e], name), t, atol=1e-6), (e, name)


def test_encodings_that_do_not_belong_to_the_views_are_refused(tiny_model):
    from pointmap.inference import encode_views, image_similarity

    vs = views(3, [(48, 64), (64, 48), (48, 64)])
    enc = encode_views(tiny_model, [v.img for v in vs])
    big = encode_views(tiny_model, [torch.nn.functional.interpolate(v.img[None], scale_factor=2.0)[0] for v in vs])
    for bad, message in [(big, "encodings\\[0\\] \\(grid \\(6, 8\\), 48 tokens\\) is not an encoding of image 0"),
                         (enc[:2], "one per image \\(3\\), got 2 entries"), (enc[0], "got Encoded"),
                         ([enc[1], enc[0], enc[2]], "encodings\\[0\\] \\(grid \\(4, 3\\), 12 tokens\\) is not an encoding"),
                         ([enc[0].cat([enc[0], enc[2]]), enc[1], enc[2]], "tokens \\[1, N, D\\]\\), got \\[2, 12, "),
                         ([None, enc[1], enc[2]], "got NoneType")]:
        with pytest.raises(pm.ShapeError, match=message):
            pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, encodings=bad)
        with pytest.raises(pm.ShapeError, match=message):
            image_similarity(tiny_model, vs, encodings=bad)


def test_a_device_torch_cannot_use_or_one_the_model_is_not_on_is_refused_before_any_work(tiny_model, monkeypatch):
    from pointmap.errors import PointmapError

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    vs = views(2)
    with pytest.raises(PointmapError, match="predict_pairs: device expected auto, cpu, cuda, cuda:N or mps, got 'gpu'"):
        pm.predict_pairs(tiny_model, vs, [(0, 1)], device="gpu")
    with pytest.raises(PointmapError, match="torch sees 0 CUDA device"):
        pm.predict_pairs(tiny_model, vs, [(0, 1)], device="cuda")
    with pytest.raises(PointmapError, match="reconstruct: device"):
        pm.reconstruct(tiny_model, [np.zeros((64, 64, 3), np.uint8)] * 2, device="tpu", quiet=True)
    with pytest.raises(PointmapError, match="load_model: device expected"):
        pm.load_model(tiny_model, device="gpu")
    # weights elsewhere than the device asked for (the meta device stands in for a GPU): the way out is named
    elsewhere = type(tiny_model)(tiny_model.cfg).to("meta")
    with pytest.raises(PointmapError, match=r"the model's weights are on meta, device is 'cpu'.*pm.load_model"):
        pm.predict_pairs(elsewhere, vs, [(0, 1)])
    assert set(pm.predict_pairs(tiny_model, vs, [(0, 1)], device=torch.device("cpu"))) == {(0, 1), (1, 0)}


def test_the_encoders_batch_size_is_checked_by_every_caller(tiny_model):
    from pointmap.inference import encode_views, image_similarity, pooled_tokens

    imgs = [torch.rand(3, 32, 32) for _ in range(2)]
    for bad in (0, -1, 2.0):
        with pytest.raises(pm.ShapeError, match="batch_size expected an int >= 1"):
            pooled_tokens(tiny_model, imgs, batch_size=bad)
        with pytest.raises(pm.ShapeError, match="image_similarity: batch_size"):
            image_similarity(tiny_model, imgs, batch_size=bad)
        with pytest.raises(pm.ShapeError, match="encode_views: batch_size"):
            encode_views(tiny_model, imgs, batch_size=bad)
