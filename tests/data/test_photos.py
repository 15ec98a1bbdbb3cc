"""Photographic textures: crops of a photo collection, deterministic, fingerprinted, off by default."""

import json

import cv2
import numpy as np
import pytest

from data.generate import main
from data.scene import make_scene
from data.textures import PhotoCollection, photo_texture

ARGS = ["--scenes", "2", "--shard-size", "1", "--size", "64", "--views", "2", "--seed", "11", "--quiet"]


@pytest.fixture
def photo_dir(tmp_path):
    d = tmp_path / "photos"
    d.mkdir()
    rng = np.random.default_rng(0)
    for k in range(3):
        img = cv2.GaussianBlur(rng.integers(0, 255, (120, 160, 3), dtype=np.uint8), (5, 5), 0)
        cv2.imwrite(str(d / f"p{k}.jpg"), img)
    (d / "notes.txt").write_text("not a photo")
    return d


def test_photo_textures_are_seamless_deterministic_crops_of_the_collection(photo_dir):
    photos = PhotoCollection([photo_dir])
    assert len(photos) == 3 and len(photos.fingerprint) == 16
    a = photo_texture(np.random.default_rng(3), photos, 64)
    b = photo_texture(np.random.default_rng(3), photos, 64)
    assert a.shape == (64, 64, 3) and a.dtype == np.uint8 and np.array_equal(a, b)
    assert np.array_equal(a[:, :32], a[:, 32:][:, ::-1]) and np.array_equal(a[:32], a[32:][::-1])  # mirrored tile
    assert a.std() > 1


def test_a_collection_fingerprint_changes_when_a_photo_changes(photo_dir):
    before = PhotoCollection([photo_dir]).fingerprint
    cv2.imwrite(str(photo_dir / "p3.jpg"), np.zeros((10, 10, 3), np.uint8))
    assert PhotoCollection([photo_dir]).fingerprint != before


def test_asking_for_photos_where_there_are_none_is_a_clear_error(tmp_path, capsys):
    with pytest.raises(FileNotFoundError, match="no photographs"):
        PhotoCollection([tmp_path])
    assert main(["--out", str(tmp_path / "o"), *ARGS, "--photo-share", "0.5", "--photo-dirs", str(tmp_path)]) == 2
    assert "no photographs" in capsys.readouterr().err
    with pytest.raises(ValueError, match="needs photos"):
        make_scene(np.random.default_rng(0), photo_share=0.5)


def test_scenes_without_photos_draw_the_same_as_scenes_with_a_zero_photo_share(photo_dir):
    plain = make_scene(np.random.default_rng(4))
    zero = make_scene(np.random.default_rng(4), photos=PhotoCollection([photo_dir]), photo_share=0.0)
    textures = lambda s: [m.material.texture for m in s.surfaces]  # noqa: E731
    assert len(textures(plain)) == len(textures(zero))
    assert all((x is None and y is None) or np.array_equal(x, y) for x, y in zip(textures(plain), textures(zero)))
    some = make_scene(np.random.default_rng(4), photos=PhotoCollection([photo_dir]), photo_share=1.0)
    assert any(t is not None for t in textures(some))


def test_a_photo_run_records_its_collection_and_is_reproducible(photo_dir, tmp_path):
    for name in ("a", "b"):
        assert main(["--out", str(tmp_path / name), *ARGS, "--photo-share", "0.7", "--photo-dirs", str(photo_dir)]) == 0
    cfg = json.loads((tmp_path / "a" / "config.json").read_text())
    assert cfg["photo_share"] == 0.7 and cfg["photo_fingerprint"] == PhotoCollection([photo_dir]).fingerprint
    files = lambda d: {p.name: p.read_bytes() for p in sorted(d.iterdir()) if p.suffix == ".tar"}  # noqa: E731
    assert files(tmp_path / "a") == files(tmp_path / "b")
    assert main(["--out", str(tmp_path / "plain"), *ARGS]) == 0
    assert "photo_share" not in json.loads((tmp_path / "plain" / "config.json").read_text())
