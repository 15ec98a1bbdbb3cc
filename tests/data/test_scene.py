import numpy as np
import pytest

from data import scene as S
from data.textures import TEXTURES, random_texture


def _digest(sc):
    return [(s.mesh.vertices.round(9).tobytes(), None if s.material.texture is None else s.material.texture.tobytes())
            for s in sc.surfaces]


@pytest.mark.parametrize("kind", S.KINDS)
def test_scenes_are_a_pure_function_of_the_generator(kind):
    a = S.make_scene(np.random.default_rng(3), kind)
    b = S.make_scene(np.random.default_rng(3), kind)
    c = S.make_scene(np.random.default_rng(4), kind)
    assert _digest(a) == _digest(b) and _digest(a) != _digest(c)
    assert a.kind == kind and len(a.lights) >= 1 and len(a.targets) >= 1
    assert all(len(s.geometry()[2]) == 3 * len(s.mesh.faces) for s in a.surfaces)


def test_objects_on_the_ground_do_not_interpenetrate():
    rng = np.random.default_rng(0)
    for _ in range(5):
        objs = [S._pick(rng, S.SMALL_OBJECTS + S.FURNITURE)(rng, rng.uniform(0.3, 1.2))[0] for _ in range(10)]
        placed = []
        out = S._place_discs(rng, objs, (-3, -3), (3, 3), placed)
        assert len(out) >= 3
        for n, (parts, pose, (x, y, r)) in enumerate(out):
            for m, _, _ in parts:  # every vertex inside the object's circle...
                v = m.vertices @ pose[:3, :3].T + pose[:3, 3]
                assert (np.hypot(v[:, 0] - x, v[:, 1] - y) <= r + 1e-9).all()
            for _, _, (x2, y2, r2) in out[n + 1:]:  # ...and circles disjoint
                assert np.hypot(x - x2, y - y2) > r + r2


def test_low_texture_knob_controls_the_share_of_plain_scenes():
    low = [S.make_scene(np.random.default_rng(i), "cluster", low_texture_share=1.0) for i in range(3)]
    tex = [S.make_scene(np.random.default_rng(i), "cluster", low_texture_share=0.0) for i in range(3)]
    plain = lambda sc: np.mean([s.material.texture is None for s in sc.surfaces])  # noqa: E731
    assert all(sc.low_texture for sc in low) and not any(sc.low_texture for sc in tex)
    assert np.mean([plain(sc) for sc in low]) > np.mean([plain(sc) for sc in tex]) + 0.3


def test_uvs_follow_the_dominant_face_axis_in_metres():
    m = S._box(2.0, 2.0, 2.0)
    surf = S.Surface(m, S.Material(base_color=np.ones(4), uv_scale=0.5))
    pos, nrm, uv = surf.geometry()
    top = np.isclose(nrm[:, 2], 1)
    assert np.allclose(uv[top], pos[top][:, :2] / 0.5)


@pytest.mark.parametrize("kind", sorted(TEXTURES))
def test_every_texture_family_gives_uint8_rgb(kind):
    t = random_texture(np.random.default_rng(0), 64, kind=kind)
    assert t.shape == (64, 64, 3) and t.dtype == np.uint8 and t.std() > 0


def test_scene_and_texture_entry_points_validate_arguments():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="scene kind"):
        S.make_scene(rng, "forest")
    with pytest.raises(ValueError, match="low_texture_share"):
        S.make_scene(rng, low_texture_share=2)
    with pytest.raises(TypeError, match="Generator"):
        S.make_scene(0)
    with pytest.raises(ValueError, match="texture kind"):
        random_texture(rng, 64, kind="plaid")
