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
    for k in range(3):  # smooth random "photographs"
        img = cv2.resize(rng.integers(0, 255, (6, 8, 3), dtype=np.uint8), (160, 120), interpolation=cv2.INTER_CUBIC)
        cv2.imwrite(str(d / f"p{k}.jpg"), img)
    (d / "notes.txt").write_text("not a photo")
    return d


def test_photo_textures_are_seamless_deterministic_crops_of_the_collection(photo_dir):
    photos = PhotoCollection([photo_dir])
    assert len(photos) == 3 and len(photos.fingerprint) == 16
    for seed in range(8):
        a = photo_texture(np.random.default_rng(seed), photos, 64)
        assert a.shape == (64, 64, 3) and a.dtype == np.uint8 and a.std() > 1
        assert np.array_equal(a, photo_texture(np.random.default_rng(seed), photos, 64))
        f = a.astype(np.float32)
        inner = max(np.abs(np.diff(f, axis=1)).mean(), np.abs(np.diff(f, axis=0)).mean())
        wrap = max(np.abs(f[:, 0] - f[:, -1]).mean(), np.abs(f[0] - f[-1]).mean())
        assert wrap < 3 * inner + 1  # tiles without a visible seam
    assert photo_texture(np.random.default_rng(0), photos, 33).shape == (33, 33, 3)


def test_photo_sources_are_directories_searched_recursively_or_glob_patterns(photo_dir):
    (photo_dir / "sub").mkdir()
    cv2.imwrite(str(photo_dir / "sub" / "q_by_me.png"), np.full((40, 50, 3), 90, np.uint8))
    assert len(PhotoCollection([photo_dir])) == 4
    assert [p.name for p in PhotoCollection([str(photo_dir / "*" / "*_by_*.png")]).files] == ["q_by_me.png"]


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

    def textures(s):
        return [m.material.texture for m in s.surfaces]

    assert len(textures(plain)) == len(textures(zero))
    assert all((x is None and y is None) or np.array_equal(x, y) for x, y in zip(textures(plain), textures(zero)))
    some = make_scene(np.random.default_rng(4), photos=PhotoCollection([photo_dir]), photo_share=1.0)
    assert any(t is not None for t in textures(some))


def test_a_photo_run_records_its_collection_and_is_reproducible(photo_dir, tmp_path):
    for name in ("a", "b"):
        assert main(["--out", str(tmp_path / name), *ARGS, "--photo-share", "0.7", "--photo-dirs", str(photo_dir)]) == 0
    cfg = json.loads((tmp_path / "a" / "config.json").read_text())
    assert cfg["photo_share"] == 0.7 and cfg["photo_fingerprint"] == PhotoCollection([photo_dir]).fingerprint

    def files(d):
        return {p.name: p.read_bytes() for p in sorted(d.iterdir()) if p.suffix == ".tar"}

    assert files(tmp_path / "a") == files(tmp_path / "b")
    assert main(["--out", str(tmp_path / "plain"), *ARGS]) == 0
    assert "photo_share" not in json.loads((tmp_path / "plain" / "config.json").read_text())


def test_a_zero_photo_share_renders_the_same_bytes_as_a_run_without_photos(photo_dir, tmp_path):
    assert main(["--out", str(tmp_path / "plain"), *ARGS]) == 0
    assert main(["--out", str(tmp_path / "zero"), *ARGS, "--photo-share", "0", "--photo-dirs", str(photo_dir)]) == 0

    def files(d):
        return {p.name: p.read_bytes() for p in sorted(d.iterdir())}

    assert files(tmp_path / "plain") == files(tmp_path / "zero")


def test_resuming_with_a_different_photo_collection_is_refused(photo_dir, tmp_path, capsys):
    args = ["--out", str(tmp_path / "a"), *ARGS, "--photo-share", "0.5", "--photo-dirs", str(photo_dir)]
    assert main(args) == 0
    cv2.imwrite(str(photo_dir / "p9.jpg"), np.zeros((10, 10, 3), np.uint8))
    assert main(args) == 2
    assert "photo_fingerprint" in capsys.readouterr().err
