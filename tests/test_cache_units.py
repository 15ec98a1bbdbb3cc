"""Unit tests from a mutation review of pointmap/cache.py (session 90; stale hits first): each kills the mutants
named in its comment, which the other tests let through; last, tests of the bugs it found. Uses tests/conftest.py's
tiny_model."""

import logging
import math

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

import pointmap as pm
from pointmap.cache import PredictionCache, image_digest, model_fingerprint, tensors_checksum


def _imgs(n=2, h=48, w=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    return [torch.rand(3, h, w, generator=g) for _ in range(n)]


def _rewrite(path, tensors=None, **meta_changes):
    """Rewrite a cache file with its tensors (or ``tensors``) and its header changed by ``meta_changes`` (None:
    the entry removed); the checksum is left as it was unless ``sha256`` is among the changes."""
    with safe_open(str(path), framework="pt") as f:
        meta = dict(f.metadata())
    tensors = load_file(str(path)) if tensors is None else tensors
    for k, v in meta_changes.items():
        if v is None:
            meta.pop(k, None)
        else:
            meta[k] = v
    save_file(tensors, str(path), metadata=meta)


def _same(a, b):
    return all(torch.equal(getattr(b, k), t) for k, t in a.as_dict().items())


# --- keys follow the pixels ------------------------------------------------------------------------------------

def test_a_pixel_change_below_float16_resolution_misses_the_cache(tiny_model, tmp_path):
    # kills img_float16, img_bfloat16
    imgs = _imgs()
    pm.predict_pairs(tiny_model, imgs, [(0, 1)], quiet=True, cache=tmp_path)
    imgs[1][1, 20, 30] = torch.nextafter(imgs[1][1, 20, 30], torch.tensor(2.0))  # one float32 ulp up
    cache = PredictionCache(tmp_path, tiny_model)
    pm.predict_pairs(tiny_model, imgs, [(0, 1)], quiet=True, cache=cache)
    assert (cache.hits, cache.misses) == (0, 2)


@pytest.mark.parametrize("where", [(2, 47, 63), (2, 0, 0), (1, 0, 63), (0, 47, 0), (0, 1, 1), (1, 31, 17)])
def test_a_change_to_any_one_pixel_of_any_channel_is_another_image_digest(where):
    # kills img_first_channel, img_two_channels, img_drop_last_col, img_drop_last_row, img_subsample2, img_first_kb
    a = _imgs(1)[0]
    b = a.clone()
    b[where] = 1.0 - b[where]
    assert image_digest(a) != image_digest(b)


def test_the_same_pixel_values_in_another_arrangement_are_another_image_digest():
    # kills img_sum, img_sorted
    a = _imgs(1)[0]
    swapped = a.clone()
    swapped[0, 0, 0], swapped[0, 5, 9] = a[0, 5, 9], a[0, 0, 0]
    assert image_digest(a) != image_digest(swapped) and image_digest(a) != image_digest(a.flip(-1))


def test_images_of_the_same_bytes_in_another_shape_are_cached_apart(tiny_model, tmp_path):
    # kills img_no_shape (both directions shared one file: each read found the other's maps, logged, recomputed)
    a = _imgs(1, 48, 64)[0]
    b = a.reshape(3, 64, 48).clone()
    assert image_digest(a) != image_digest(b)
    pm.predict_pairs(tiny_model, [a, b], [(0, 1)], quiet=True, cache=tmp_path)
    cache = PredictionCache(tmp_path, tiny_model)
    pm.predict_pairs(tiny_model, [a, b], [(0, 1)], quiet=True, cache=cache)
    assert (cache.hits, cache.misses) == (2, 0)


def test_a_non_contiguous_or_offset_image_hashes_as_its_contiguous_copy():
    # kills img_storage_bytes; equal values hash equal whatever the memory layout, other values do not
    batch = torch.rand(2, 3, 32, 48, generator=torch.Generator().manual_seed(1))
    for view in (batch[1], batch[1].transpose(1, 2).contiguous().transpose(1, 2), batch[:, :, :, :].select(0, 1),
                 batch[0, :1].expand(3, 32, 48)):
        assert image_digest(view) == image_digest(view.clone(memory_format=torch.contiguous_format))
    assert image_digest(batch[1]) != image_digest(batch[0])


def test_keys_of_digests_differing_in_their_last_byte_differ_and_are_full_sha256s(tiny_model, tmp_path):
    # kills key_digest_prefix, key_short
    cache = PredictionCache(tmp_path, tiny_model)
    d1, d2 = bytes(32), bytes(31) + b"\x01"
    assert len({cache.key(d1, d1), cache.key(d1, d2), cache.key(d2, d1), cache.key(d2, d2)}) == 4
    assert len(cache.key(d1, d2)) == 64


# --- keys follow the model -------------------------------------------------------------------------------------

def test_the_same_weights_under_another_config_miss_the_cache(tiny_model, tmp_path):
    # kills fp_no_cfg, fp_cfg_type_only: conf_mode changes the confidences, not one weight
    imgs = _imgs()
    pm.predict_pairs(tiny_model, imgs, [(0, 1)], quiet=True, cache=tmp_path)
    other = pm.PointmapNet(tiny_model.cfg.replace(conf_mode=("exp", 0.0, math.inf))).eval()
    other.load_state_dict(tiny_model.state_dict())
    cache = PredictionCache(tmp_path, other)
    out = pm.predict_pairs(other, imgs, [(0, 1)], quiet=True, cache=cache)
    assert cache.hits == 0
    assert not torch.equal(out[(0, 1)].conf1, pm.predict_pairs(tiny_model, imgs, [(0, 1)], quiet=True)[(0, 1)].conf1)


def test_a_model_running_other_rotary_tables_than_its_config_says_misses_the_cache(tiny_model, tmp_path):
    # the rotary base lives in no weight: a model given tables of another base computes another prediction
    from pointmap.model.blocks import RopeCache

    imgs = _imgs()
    pm.predict_pairs(tiny_model, imgs, [(0, 1)], quiet=True, cache=tmp_path)
    other = pm.PointmapNet(tiny_model.cfg).eval()
    other.load_state_dict(tiny_model.state_dict())
    other.rope = RopeCache(tiny_model.cfg.rope_base * 3)
    cache = PredictionCache(tmp_path, other)
    out = pm.predict_pairs(other, imgs, [(0, 1)], quiet=True, cache=cache)
    assert cache.hits == 0 and model_fingerprint(other) != model_fingerprint(tiny_model)
    assert not torch.equal(out[(0, 1)].pts2_cam1, pm.predict_pairs(tiny_model, imgs, [(0, 1)], quiet=True)[(0, 1)].pts2_cam1)


def test_the_rotary_base_of_a_built_model_cannot_be_changed_in_place(tiny_model):
    # its tables are built once and cached, and the config (which checkpoints and caches record) says the base
    with pytest.raises(AttributeError, match=r"read-only \(it is 100.0, asked 200\).*rope_base"):
        tiny_model.rope.base = 200
    assert tiny_model.rope.base == tiny_model.cfg.rope_base == 100.0


@pytest.mark.parametrize("which", [0, -1])
def test_a_change_to_the_last_element_of_the_first_or_last_weight_by_one_ulp_changes_the_fingerprint(tiny_model,
                                                                                                      which):
    # kills fp_first_elem_only, fp_first_half_only, fp_skip_first_tensor, fp_skip_last_tensor, fp_float16_bytes
    before = model_fingerprint(tiny_model)
    name = sorted(tiny_model.state_dict())[which]
    with torch.no_grad():
        flat = tiny_model.get_parameter(name).view(-1)
        flat[-1] = torch.nextafter(flat[-1], torch.tensor(math.inf))
    assert model_fingerprint(tiny_model) != before


def test_a_scalar_parameter_is_fingerprinted_by_its_value():
    # kills fp_skip_scalars (a 0-dim parameter, e.g. a learned temperature, was hashed by name only)
    m = torch.nn.Module()
    m.temperature = torch.nn.Parameter(torch.tensor(1.0))
    before = model_fingerprint(m)
    with torch.no_grad():
        m.temperature.fill_(2.0)
    assert model_fingerprint(m) != before


def test_buffers_of_the_same_bytes_in_another_dtype_or_shape_are_other_fingerprints():
    # kills fp_header_no_dtype, fp_header_no_shape
    def with_buffer(t):
        m = torch.nn.Module()
        m.register_buffer("b", t)
        return model_fingerprint(m)

    assert with_buffer(torch.zeros(6)) != with_buffer(torch.zeros(6, dtype=torch.int32))
    assert with_buffer(torch.arange(6.0).view(2, 3)) != with_buffer(torch.arange(6.0).view(3, 2))


def test_a_vouched_block_passes_only_its_own_model_for_its_own_cache(tiny_model, tmp_path):
    # kills chk_vouch_any_model, chk_vouch_any_cache
    other = pm.PointmapNet(tiny_model.cfg).eval()
    mine, theirs = PredictionCache(tmp_path / "a", tiny_model), PredictionCache(tmp_path / "b", other)
    with mine._vouched(tiny_model):
        with pytest.raises(pm.PointmapError, match="made for other weights"):
            mine.check(other)
        with pytest.raises(pm.PointmapError, match="made for other weights"):
            theirs.check(tiny_model)


# --- files that must not be served ----------------------------------------------------------------------------

@pytest.fixture
def cached_pair(tiny_model, tmp_path):
    """(images, fresh predictions, cache, {edge: file}) after one cached run of the pair (0, 1)."""
    imgs = _imgs()
    fresh = pm.predict_pairs(tiny_model, imgs, [(0, 1)], quiet=True, cache=tmp_path)
    cache = PredictionCache(tmp_path, tiny_model)
    files = {e: cache.path(k) for e, k in cache.keys(imgs, [(0, 1), (1, 0)]).items()}
    return imgs, fresh, cache, files


def _read_again(tiny_model, imgs, cache_dir, caplog):
    cache = PredictionCache(cache_dir, tiny_model)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pointmap.cache"):
        out = pm.predict_pairs(tiny_model, imgs, [(0, 1)], quiet=True, cache=cache)
    return cache, out


def test_a_file_of_another_format_version_is_reported_and_predicted_again(tiny_model, tmp_path, cached_pair, caplog):
    # kills un_no_version, un_version_prefix, un_version_not_foreign
    imgs, fresh, _, files = cached_pair
    _rewrite(files[(0, 1)], version="3")
    cache, out = _read_again(tiny_model, imgs, tmp_path, caplog)
    assert (cache.hits, cache.misses) == (1, 1) and "format version '3'" in caplog.text
    assert torch.allclose(out[(0, 1)].pts1_cam1, fresh[(0, 1)].pts1_cam1, atol=1e-5)


def test_a_file_copied_onto_the_other_directions_name_is_not_served(tiny_model, tmp_path, cached_pair, caplog):
    # kills un_no_key: (1, 0) would be served (0, 1)'s maps (same shapes, a valid checksum)
    imgs, fresh, _, files = cached_pair
    files[(1, 0)].write_bytes(files[(0, 1)].read_bytes())
    cache, out = _read_again(tiny_model, imgs, tmp_path, caplog)
    assert (cache.hits, cache.misses) == (1, 1) and "not a pointmap pair prediction" in caplog.text
    assert torch.allclose(out[(1, 0)].pts1_cam1, fresh[(1, 0)].pts1_cam1, atol=1e-5)


def test_a_file_of_another_format_under_this_key_is_not_served(tiny_model, tmp_path, cached_pair, caplog):
    # kills un_no_format
    imgs, _, _, files = cached_pair
    _rewrite(files[(0, 1)], format="someone-elses-format")
    cache, _ = _read_again(tiny_model, imgs, tmp_path, caplog)
    assert (cache.hits, cache.misses) == (1, 1) and "not a pointmap pair prediction" in caplog.text


def test_a_file_without_a_checksum_in_its_header_is_not_served(tiny_model, tmp_path, cached_pair, caplog):
    # kills get_checksum_missing_ok
    imgs, _, _, files = cached_pair
    _rewrite(files[(0, 1)], sha256=None)
    cache, _ = _read_again(tiny_model, imgs, tmp_path, caplog)
    assert (cache.hits, cache.misses) == (1, 1) and "checksum" in caplog.text


def test_a_value_changed_at_the_end_of_any_stored_tensor_fails_the_checksum(tiny_model, tmp_path, cached_pair, caplog):
    # kills ck_first_tensor, ck_skip_last_tensor, ck_first_kb
    imgs, _, _, files = cached_pair
    names = sorted(load_file(str(files[(0, 1)])))
    assert {"pts1_cam1", "pts2_cam1", "conf1", "desc1"} <= set(names)
    for name in names:
        tensors = load_file(str(files[(0, 1)]))
        tensors[name].view(-1)[-1] += 1.0
        good = files[(0, 1)].read_bytes()
        _rewrite(files[(0, 1)], tensors)
        cache = PredictionCache(tmp_path, tiny_model)
        key = cache.keys(imgs, [(0, 1)])[(0, 1)]
        assert cache.get(key, (48, 64), (48, 64), True) is None, name
        files[(0, 1)].write_bytes(good)
    assert tensors_checksum(load_file(str(files[(0, 1)]))) == safe_open(str(files[(0, 1)]), "pt").metadata()["sha256"]


def test_a_directory_in_place_of_a_cache_file_is_a_reported_miss_not_an_error(tiny_model, tmp_path, cached_pair,
                                                                                caplog):
    # kills get_exc_no_oserror
    imgs, fresh, _, files = cached_pair
    files[(0, 1)].unlink()
    files[(0, 1)].mkdir()
    cache, out = _read_again(tiny_model, imgs, tmp_path, caplog)
    assert (cache.hits, cache.misses) == (1, 1) and "is unreadable" in caplog.text
    assert torch.allclose(out[(0, 1)].pts1_cam1, fresh[(0, 1)].pts1_cam1, atol=1e-5)


# --- what is written -------------------------------------------------------------------------------------------

def _pred(conf=2.0, batch=1):
    return pm.PairPrediction(torch.zeros(batch, 8, 8, 3), torch.ones(batch, 8, 8, 3),
                             torch.full((batch, 8, 8), conf), torch.full((batch, 8, 8), conf))


def test_a_float16_cache_stores_a_confidence_beyond_its_range_as_its_largest_value(tiny_model, tmp_path):
    # kills put_no_clamp (an infinite confidence was read back)
    cache = PredictionCache(tmp_path, tiny_model, dtype=torch.float16)
    key = cache.key(bytes(32), bytes(32))
    assert cache.put(key, _pred(conf=1e6)) is not None
    back = cache.get(key, (8, 8), (8, 8), False)
    assert back is not None and torch.all(back.conf1 == torch.finfo(torch.float16).max)


def test_predictions_under_cuda_autocast_are_not_stored_either(tiny_model, tmp_path, monkeypatch):
    # kills put_autocast_cpu_only, put_no_autocast_check
    import pointmap.cache

    monkeypatch.setattr(pointmap.cache, "autocast_on", lambda device: device == "cuda")
    cache = PredictionCache(tmp_path, tiny_model)
    assert cache.put(cache.key(bytes(32), bytes(32)), _pred()) is None
    assert not list(cache.dir.iterdir())


def test_put_refuses_a_batch_of_two(tiny_model, tmp_path):
    # kills put_no_batch_check
    cache = PredictionCache(tmp_path, tiny_model)
    with pytest.raises(pm.PointmapError, match="one pair per file, got a batch of 2"):
        cache.put(cache.key(bytes(32), bytes(32)), _pred(batch=2))


# --- bugs the review found ---------------------------------------------------------------------------------------

def test_a_model_whose_input_normalisation_changed_in_place_misses_the_cache(tiny_model, tmp_path):
    # img_mean / img_std are non-persistent buffers: not in state_dict(), so not in the fingerprint, yet every
    # image is normalised by them; changed in place, check() passed and the old predictions were served
    imgs = _imgs()
    cache = PredictionCache(tmp_path, tiny_model)
    pm.predict_pairs(tiny_model, imgs, [(0, 1)], quiet=True, cache=cache)
    before = model_fingerprint(tiny_model)
    with torch.no_grad():
        tiny_model.img_mean.fill_(0.3)
    assert model_fingerprint(tiny_model) != before
    fresh = PredictionCache(tmp_path, tiny_model)
    out = pm.predict_pairs(tiny_model, imgs, [(0, 1)], quiet=True, cache=fresh)
    truth = pm.predict_pairs(tiny_model, imgs, [(0, 1)], quiet=True)
    assert fresh.hits == 0 and torch.equal(out[(0, 1)].pts1_cam1, truth[(0, 1)].pts1_cam1)


def test_a_cache_object_refuses_its_model_after_its_normalisation_changed_in_place(tiny_model, tmp_path):
    cache = PredictionCache(tmp_path, tiny_model)
    with torch.no_grad():
        tiny_model.img_std.mul_(2.0)
    try:
        cache.check(tiny_model)
    except pm.PointmapError as e:
        assert "made for other weights" in str(e)
    else:
        raise AssertionError("check() passed a model whose img_std changed")


def test_an_autocast_run_does_not_stop_the_same_cache_object_storing_a_later_full_precision_run(tiny_model, tmp_path,
                                                                                               caplog):
    # the warning says "for this run", but writable stayed False on the object: a CLI run over several scenes (one
    # PredictionCache) or a loop of reconstruct calls never wrote again
    imgs = _imgs(3)
    cache = PredictionCache(tmp_path, tiny_model)
    with torch.autocast("cpu", torch.bfloat16), caplog.at_level(logging.WARNING, logger="pointmap.cache"):
        pm.predict_pairs(tiny_model, imgs, [(0, 1)], quiet=True, cache=cache)
    assert "made under torch.autocast are not stored" in caplog.text
    assert not list(tmp_path.rglob("*.safetensors"))
    pm.predict_pairs(tiny_model, imgs, [(1, 2)], quiet=True, cache=cache)  # full precision: stored
    assert len(list(tmp_path.rglob("*.safetensors"))) == 2
