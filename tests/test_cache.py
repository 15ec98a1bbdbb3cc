"""The on-disk prediction cache: hits equal fresh predictions, keys follow the weights and the pixels, and nothing
unreadable or foreign is trusted."""

import logging

import numpy as np
import pytest
import torch
from test_inference import CountingModel, views

import pointmap as pm
from pointmap.cache import PredictionCache, model_fingerprint


def same(a: dict, b: dict, exact: bool = True):
    """Equal predictions: bit for bit (read back), or to float rounding (predicted in another batch)."""
    assert list(a) == list(b)
    for e in a:
        for name, t in a[e].as_dict().items():
            o = getattr(b[e], name)
            assert torch.equal(o, t) if exact else torch.allclose(o, t, atol=1e-5), (e, name)


def test_a_second_run_reads_every_pair_from_the_cache_without_the_encoder_and_gets_the_same_predictions(tiny_model,
                                                                                                        tmp_path):
    vs = views(4, [(48, 64), (48, 64), (64, 48), (48, 64)])
    pairs = [(0, 1), (1, 2), (3, 2), (0, 3)]
    fresh = pm.predict_pairs(tiny_model, vs, pairs, quiet=True)
    first = PredictionCache(tmp_path, tiny_model)
    same(fresh, pm.predict_pairs(tiny_model, vs, pairs, quiet=True, cache=first))
    assert (first.hits, first.misses) == (0, 8) and len(list(first.dir.glob("*.safetensors"))) == 8
    model = CountingModel(tiny_model)
    model.cfg = tiny_model.cfg
    model.state_dict = tiny_model.state_dict  # the wrapper fingerprints as the model it wraps
    again = PredictionCache(tmp_path, model)
    same(fresh, pm.predict_pairs(model, vs, pairs, quiet=True, cache=again))
    assert (again.hits, again.misses, model.encoded_images) == (8, 0, 0)
    half = pm.predict_pairs(tiny_model, vs, pairs, quiet=True, cache=tmp_path, store_dtype=torch.float16,
                            keep_desc=False)
    assert half[(0, 1)].pts1_cam1.dtype == torch.float16 and half[(0, 1)].desc1 is None


def test_a_pose_head_models_transform_is_cached_and_kept_without_the_descriptors(tmp_path):
    torch.manual_seed(0)
    model = pm.PointmapNet(pm.PRESETS["test"].replace(pose_head=True)).eval()
    with torch.no_grad():
        model.pose_head.out.weight.normal_(0, 0.3)  # far from the identity it starts at
    vs = views(3, [(48, 64)] * 3)
    pairs = [(0, 1), (2, 1)]
    fresh = pm.predict_pairs(model, vs, pairs, quiet=True, keep_desc=False)
    assert fresh[(0, 1)].desc1 is None and fresh[(0, 1)].cam2_to_cam1.shape == (1, 4, 4)
    assert not torch.allclose(fresh[(0, 1)].cam2_to_cam1, torch.eye(4))
    cache = PredictionCache(tmp_path, model)
    pm.predict_pairs(model, vs, pairs, quiet=True, cache=cache)
    back = pm.predict_pairs(model, vs, pairs, quiet=True, cache=PredictionCache(tmp_path, model), keep_desc=False)
    same(fresh, back)


def test_a_changed_image_or_other_weights_miss_and_only_the_missing_pairs_are_predicted(tiny_model, tmp_path):
    vs = views(4)
    pairs = [(0, 1), (1, 2), (2, 3)]
    pm.predict_pairs(tiny_model, vs, pairs, quiet=True, cache=tmp_path)
    vs[3].img[0, 0, 0] += 0.5  # one pixel of image 3
    model = CountingModel(tiny_model)
    model.cfg, model.state_dict = tiny_model.cfg, tiny_model.state_dict
    cache = PredictionCache(tmp_path, model)
    out = pm.predict_pairs(model, vs, pairs, quiet=True, cache=cache)
    assert (cache.hits, cache.misses, model.encoded_images) == (4, 2, 2)  # (2, 3) and (3, 2): images 2 and 3
    same({e: out[e] for e in [(2, 3), (3, 2)]}, pm.predict_pairs(tiny_model, vs, [(2, 3)], quiet=True), exact=False)
    other = pm.PointmapNet(pm.PRESETS["test"]).eval()
    with torch.no_grad():
        next(other.parameters()).copy_(next(tiny_model.parameters()) + 1e-3)
    assert model_fingerprint(other) != model_fingerprint(tiny_model)
    cache = PredictionCache(tmp_path, other)
    pm.predict_pairs(other, vs, pairs, quiet=True, cache=cache)
    assert cache.hits == 0 and cache.dir != PredictionCache(tmp_path, tiny_model).dir


def test_descriptors_are_cached_even_when_not_kept_and_a_file_without_them_misses_when_they_are_needed(tiny_model,
                                                                                                       tmp_path):
    from pointmap.cache import image_digest

    vs = views(2)
    pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=tmp_path, keep_desc=False)
    cache = PredictionCache(tmp_path, tiny_model)
    out = pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=cache)
    assert cache.hits == 2 and out[(0, 1)].has_desc  # written with them although the first run dropped them
    key = cache.key(image_digest(vs[0].img), image_digest(vs[1].img))
    p = out[(0, 1)]
    cache.put(key, pm.PairPrediction(p.pts1_cam1, p.pts2_cam1, p.conf1, p.conf2))  # a file without descriptors
    cache = PredictionCache(tmp_path, tiny_model)
    imgs = [v.img for v in vs]
    assert cache.present(imgs, [(0, 1), (1, 0)], desc=True) == 1 and cache.present(imgs, [(0, 1), (1, 0)]) == 2
    out = pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=cache)
    assert (cache.hits, cache.misses) == (1, 1) and out[(0, 1)].has_desc
    cache = PredictionCache(tmp_path, tiny_model)
    pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=cache, keep_desc=False)
    assert cache.hits == 2  # rewritten with them; read without them


def test_a_cache_refuses_another_model_and_its_own_model_after_an_in_place_change(tiny_model, tmp_path):
    vs = views(2)
    cache = PredictionCache(tmp_path, tiny_model)
    pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=cache)
    other = pm.PointmapNet(pm.PRESETS["test"]).eval()
    with pytest.raises(pm.PointmapError, match="made for other weights than the model given"):
        pm.predict_pairs(other, vs, [(0, 1)], quiet=True, cache=cache)
    weight = next(tiny_model.parameters())
    kept = weight.detach().clone()
    with torch.no_grad():
        weight.add_(1e-3)
    with pytest.raises(pm.PointmapError, match="made for other weights"):
        pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=cache)
    with torch.no_grad():
        weight.copy_(kept)  # back: the fingerprint matches again (re-hashed)
    pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=cache)
    assert cache.hits == 2


def test_a_corrupt_truncated_or_foreign_file_is_reported_predicted_again_and_replaced(tiny_model, tmp_path, caplog):
    from safetensors.torch import save_file

    vs = views(2)
    fresh = pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=tmp_path)
    cache = PredictionCache(tmp_path, tiny_model)
    files = sorted(cache.dir.glob("*.safetensors"))
    files[0].write_bytes(b"not a safetensors file")
    data = files[1].read_bytes()
    files[1].write_bytes(data[: len(data) // 2])
    with caplog.at_level(logging.WARNING, logger="pointmap.cache"):
        same(fresh, pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=cache))
    assert cache.hits == 0 and caplog.text.count("is unreadable") == 2
    from safetensors.torch import load_file

    tensors = load_file(str(files[0]))
    tensors["conf1"][0, 0, 0] += 1.0  # a flipped value, the header intact
    from safetensors import safe_open

    with safe_open(str(files[0]), framework="pt") as f:
        header = f.metadata()
    save_file(tensors, str(files[0]), metadata=header)
    cache = PredictionCache(tmp_path, tiny_model)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pointmap.cache"):
        pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=cache)
    assert cache.misses == 1 and "do not match the checksum" in caplog.text
    save_file({"pts1_cam1": torch.zeros(1, 48, 64, 3)}, str(files[0]), metadata={"format": "something else"})
    cache = PredictionCache(tmp_path, tiny_model)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pointmap.cache"):
        same(fresh, pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=cache), exact=False)  # one alone
    assert (cache.hits, cache.misses) == (1, 1) and "not a pointmap pair prediction" in caplog.text
    cache = PredictionCache(tmp_path, tiny_model)
    pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=cache)
    assert cache.hits == 2 and not list(cache.dir.glob(".*"))  # replaced; no temporary file left behind


def test_a_cache_path_that_is_a_file_and_a_model_without_weights_are_refused(tiny_model, tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(pm.PointmapError, match="cache expected a directory, got .*which is a file"):
        pm.predict_pairs(tiny_model, views(2), [(0, 1)], quiet=True, cache=tmp_path / "f")
    with pytest.raises(pm.PointmapError, match="cache expected a directory path, got int"):
        PredictionCache(3, tiny_model)
    with pytest.raises(pm.CheckpointError, match="needs a PyTorch model or an ONNX export directory.*got object"):
        PredictionCache(tmp_path, object())


def test_an_onnx_export_fingerprints_by_its_files(split_export, full_export):
    a, b = pm.load_model(split_export), pm.load_model(split_export)
    assert model_fingerprint(a) == model_fingerprint(b) != model_fingerprint(pm.load_model(full_export))


def test_two_exports_side_by_side_in_one_folder_are_two_models_and_external_weights_count(full_export, tmp_path):
    # before, a lone .onnx file was fingerprinted by every graph of its folder: v1.onnx and v2.onnx shared one key,
    # and a cache gave v2 the predictions of v1
    import onnx
    from onnx import numpy_helper

    proto = onnx.load(str(full_export / "model.onnx"))
    onnx.save_model(proto, str(tmp_path / "v1.onnx"))
    init = next(t for t in proto.graph.initializer if t.data_type == onnx.TensorProto.FLOAT and len(t.dims) == 2)
    init.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(init) * 1.5, init.name))
    onnx.save_model(proto, str(tmp_path / "v2.onnx"))
    v1, v2 = pm.load_model(tmp_path / "v1.onnx"), pm.load_model(tmp_path / "v2.onnx")
    assert v1.files_used() == [tmp_path / "v1.onnx"] and v2.files_used() == [tmp_path / "v2.onnx"]
    assert model_fingerprint(v1) != model_fingerprint(v2)
    assert model_fingerprint(v1) == model_fingerprint(pm.load_model(tmp_path / "v1.onnx"))
    (tmp_path / "ext").mkdir()
    onnx.save_model(proto, str(tmp_path / "ext" / "v2.onnx"), save_as_external_data=True, location="w.bin")
    ext = pm.load_model(tmp_path / "ext" / "v2.onnx")
    assert ext.files_used() == [tmp_path / "ext" / "v2.onnx", tmp_path / "ext" / "w.bin"]
    before = model_fingerprint(ext)
    with open(tmp_path / "ext" / "w.bin", "r+b") as f:  # other weights in the external file: another model
        f.seek(100)
        byte = f.read(1)
        f.seek(100)
        f.write(bytes([byte[0] ^ 1]))
    assert model_fingerprint(ext) != before


def test_reconstruct_with_a_cache_runs_the_network_once_and_aligns_the_same(tiny_model, tmp_path):
    rng = np.random.default_rng(5)
    images = [rng.integers(0, 255, (48, 64, 3), dtype=np.uint8) for _ in range(3)]
    kw = dict(size=64, quiet=True, epipolar=False, align=pm.AlignConfig(niter=20, quiet=True))
    first = pm.reconstruct(tiny_model, images, cache=tmp_path / "c", **kw)
    model = CountingModel(tiny_model)
    model.cfg, model.state_dict = tiny_model.cfg, tiny_model.state_dict
    second = pm.reconstruct(model, images, cache=tmp_path / "c", **kw)
    assert model.encoded_images == 0
    assert first.info["pipeline"]["cache"]["misses"] == 6 and second.info["pipeline"]["cache"]["hits"] == 6
    assert torch.allclose(torch.as_tensor(first.cam2world), torch.as_tensor(second.cam2world))


def test_the_inference_estimate_falls_by_the_share_of_directed_pairs_already_in_the_cache(tiny_model, tmp_path):
    rng = np.random.default_rng(6)
    images = [rng.integers(0, 255, (48, 64, 3), dtype=np.uint8) for _ in range(4)]
    kw = dict(size=64, quiet=True, epipolar=False, graph="complete", align=pm.AlignConfig(niter=5, quiet=True))
    pm.reconstruct(tiny_model, images[:3], cache=tmp_path / "c", **kw)  # 3 of the 6 pairs: 6 of 12 directed
    fresh = pm.reconstruct(tiny_model, images, **kw).info["pipeline"]["estimate"]
    half = pm.reconstruct(tiny_model, images, cache=tmp_path / "c", **kw).info["pipeline"]["estimate"]
    assert half["cached_pairs"] == 6
    assert half["inference_seconds"] == pytest.approx(fresh["inference_seconds"] * (1 - 6 / 12), rel=1e-9)


def test_a_float16_cache_halves_the_files_and_reads_back_close_to_the_fresh_predictions(tiny_model, tmp_path):
    vs = views(2)
    fresh = pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=tmp_path / "full")
    half = PredictionCache(tmp_path / "half", tiny_model, dtype=torch.float16)
    pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=half)
    again = PredictionCache(tmp_path / "half", tiny_model, dtype=torch.float16)
    read = pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=again)
    assert again.hits == 2
    for e in fresh:
        for name, t in fresh[e].as_dict().items():
            o = getattr(read[e], name)
            assert o.dtype == torch.float32 and torch.allclose(o, t, rtol=1e-3, atol=1e-3), (e, name)
    size = {k: sum(p.stat().st_size for p in (tmp_path / k).rglob("*.safetensors")) for k in ("full", "half")}
    assert size["half"] < 0.55 * size["full"]
    full = PredictionCache(tmp_path / "half", tiny_model)  # a float32 cache: the float16 files are misses
    imgs = [v.img for v in vs]
    assert again.present(imgs, [(0, 1), (1, 0)]) == 2 and full.present(imgs, [(0, 1), (1, 0)]) == 0  # estimated so
    exact = pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=full)
    assert full.misses == 2 and all(torch.equal(getattr(exact[e], n), t) for e in fresh
                                     for n, t in fresh[e].as_dict().items())
    full = PredictionCache(tmp_path / "half", tiny_model)
    pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=full)
    assert full.hits == 2  # rewritten in float32
    with pytest.raises(pm.PointmapError, match="cache dtype expected torch.float32 or torch.float16, got torch.int8"):
        PredictionCache(tmp_path, tiny_model, dtype=torch.int8)


def test_a_write_that_fails_is_logged_once_and_the_predictions_are_still_returned(tiny_model, tmp_path, caplog,
                                                                                  monkeypatch):
    import pointmap.cache

    def full_disk(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(pointmap.cache, "atomic_path", full_disk)
    cache = PredictionCache(tmp_path, tiny_model)
    with caplog.at_level(logging.WARNING, logger="pointmap.cache"):
        out = pm.predict_pairs(tiny_model, views(3), [(0, 1), (1, 2)], quiet=True, cache=cache)
    assert len(out) == 4 and caplog.text.count("cannot write") == 1 and not cache.writable
    (tmp_path / "file").write_text("x")
    with pytest.raises(pm.PointmapError, match="cache expected a directory it can write"):
        PredictionCache(tmp_path / "file" / "below", tiny_model)


def test_the_fingerprint_covers_zero_dim_buffers_and_the_network_code(tiny_model, monkeypatch):
    import pointmap.cache

    bn = torch.nn.BatchNorm1d(3)  # num_batches_tracked: a 0-dim buffer
    assert len(model_fingerprint(bn)) == 64
    before = model_fingerprint(tiny_model)
    monkeypatch.setattr(pointmap.cache, "code_digest", lambda: b"an edited network")
    assert model_fingerprint(tiny_model) != before


def test_a_cache_object_serving_several_reconstructions_records_each_runs_own_counts(tiny_model, tmp_path):
    rng = np.random.default_rng(6)
    images = [rng.integers(0, 255, (48, 64, 3), dtype=np.uint8) for _ in range(3)]
    kw = dict(size=64, quiet=True, epipolar=False, align=pm.AlignConfig(niter=10, quiet=True))
    cache = PredictionCache(tmp_path, tiny_model)
    first = pm.reconstruct(tiny_model, images, cache=cache, **kw).info["pipeline"]["cache"]
    second = pm.reconstruct(tiny_model, images, cache=cache, **kw).info["pipeline"]["cache"]
    assert (first["hits"], first["misses"]) == (0, 6) and (second["hits"], second["misses"]) == (6, 0)


def test_a_full_disk_reported_by_safetensors_is_logged_too(tiny_model, tmp_path, caplog, monkeypatch):
    import safetensors.torch
    from safetensors import SafetensorError

    def full(*a, **k):
        raise SafetensorError("Error while serializing: I/O error: No space left on device (os error 28)")

    monkeypatch.setattr(safetensors.torch, "save_file", full)
    cache = PredictionCache(tmp_path, tiny_model)
    with caplog.at_level(logging.WARNING, logger="pointmap.cache"):
        out = pm.predict_pairs(tiny_model, views(2), [(0, 1)], quiet=True, cache=cache)
    assert len(out) == 2 and "No space left on device" in caplog.text and not cache.writable
    assert not list(cache.dir.iterdir())  # no half-written file


def test_an_edit_through_data_which_pytorch_does_not_count_is_refused_too(tiny_model, tmp_path):
    cache = PredictionCache(tmp_path, tiny_model)
    next(tiny_model.parameters()).data.add_(1e-3)
    with pytest.raises(pm.PointmapError, match="made for other weights"):
        pm.predict_pairs(tiny_model, views(2), [(0, 1)], quiet=True, cache=cache)


@pytest.fixture
def fingerprint_calls(monkeypatch) -> list:
    """A list that gets one entry per hash of a model's weights (``pointmap.cache.model_fingerprint`` call)."""
    import pointmap.cache as cache_mod

    calls, real = [], cache_mod.model_fingerprint
    monkeypatch.setattr(cache_mod, "model_fingerprint", lambda m: calls.append(1) or real(m))
    return calls


def test_reconstruct_hashes_the_weights_once_per_run_and_predict_pairs_still_checks_its_cache(tiny_model, tmp_path,
                                                                                             fingerprint_calls):
    calls = fingerprint_calls
    rng = np.random.default_rng(7)
    images = [rng.integers(0, 255, (48, 64, 3), dtype=np.uint8) for _ in range(3)]
    kw = dict(size=64, quiet=True, epipolar=False, align=pm.AlignConfig(niter=5, quiet=True))
    pm.reconstruct(tiny_model, images, cache=tmp_path / "c", **kw)
    assert len(calls) == 1  # the cache made from the path; no second hash inside the inference
    cache = PredictionCache(tmp_path / "c", tiny_model)
    calls.clear()
    pm.reconstruct(tiny_model, images, cache=cache, **kw)
    assert len(calls) == 1  # the given cache checked once
    views = [torch.rand(3, 32, 32) for _ in range(2)]
    with torch.no_grad():
        next(tiny_model.parameters()).data.add_(1.0)  # weights changed after the cache was made
    with pytest.raises(pm.PointmapError, match="other weights"):
        pm.predict_pairs(tiny_model, views, [(0, 1)], cache=cache, quiet=True)
    with pytest.raises(pm.PointmapError, match="other weights"):
        pm.reconstruct(tiny_model, images, cache=cache, **kw)


def test_a_vouched_check_ends_with_its_block_even_on_an_error_and_does_not_reach_another_thread(tiny_model, tmp_path,
                                                                                                 fingerprint_calls):
    import threading

    cache = PredictionCache(tmp_path, tiny_model)
    calls = fingerprint_calls
    calls.clear()  # the cache's own hash above
    with pytest.raises(RuntimeError):
        with cache._vouched(tiny_model):
            cache.check(tiny_model)
            assert calls == []
            raise RuntimeError("a stage failed inside the block")
    cache.check(tiny_model)
    assert len(calls) == 1  # hashed again once the block is left by the error
    with cache._vouched(tiny_model):
        with cache._vouched(tiny_model):
            pass
        cache.check(tiny_model)  # the outer block still vouches after the inner one ended
        assert len(calls) == 1
        other = threading.Thread(target=cache.check, args=(tiny_model,))
        other.start()
        other.join()
        assert len(calls) == 2  # another thread's check hashes
        other_cache = PredictionCache(tmp_path / "other", tiny_model)
        calls.clear()
        other_cache.check(tiny_model)
        assert len(calls) == 1  # only the cache that vouched skips


def test_the_network_code_digest_covers_every_library_module_the_forward_pass_imports():
    import ast
    from pathlib import Path

    import pointmap.cache

    root = Path(pointmap.cache.__file__).parent
    pointmap.cache.code_digest.cache_clear()
    covered = set()
    real_read = Path.read_bytes

    def recording(self):
        covered.add(self.resolve())
        return real_read(self)

    try:
        Path.read_bytes = recording
        pointmap.cache.code_digest()
    finally:
        Path.read_bytes = real_read
        pointmap.cache.code_digest.cache_clear()
    imported = set()
    for f in sorted((root / "model").rglob("*.py")):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("pointmap."):
                mod = root.parent / Path(*node.module.split("."))
                path = mod.with_suffix(".py") if mod.with_suffix(".py").exists() else mod / "__init__.py"
                if not node.module.startswith("pointmap.errors"):  # messages, not numbers
                    imported.add(path.resolve())
    assert imported and imported <= covered, sorted(str(p) for p in imported - covered)


def test_predictions_made_under_autocast_are_not_stored_as_full_precision_ones(tiny_model, tmp_path, caplog):
    vs = views(2)
    cache = PredictionCache(tmp_path, tiny_model)
    with torch.autocast("cpu", torch.bfloat16):
        pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=cache)
    assert "made under torch.autocast are not stored" in caplog.text and not list(tmp_path.rglob("*.safetensors"))
    again = PredictionCache(tmp_path, tiny_model)
    pm.predict_pairs(tiny_model, vs, [(0, 1)], quiet=True, cache=again)
    assert again.misses == 2 and len(list(tmp_path.rglob("*.safetensors"))) == 2  # written by the full-precision run
