import pytest

from training.mix import PairMix


class Fake:
    def __init__(self, name, n, aspects=((32, 32), (16, 32))):
        self.name, self.n, self.aspects = name, n, list(aspects)

    def __len__(self):
        return self.n

    def __getitem__(self, index):
        return (self.name, index)


def test_a_mix_concatenates_its_parts_and_passes_the_aspect_through():
    mix = PairMix([Fake("a", 3), Fake("b", 2)])
    assert len(mix) == 5 and mix.aspects == [(32, 32), (16, 32)]
    assert [mix[i] for i in range(5)] == [("a", 0), ("a", 1), ("a", 2), ("b", 0), ("b", 1)]
    assert mix[(4, 1)] == ("b", (1, 1))
    with pytest.raises(IndexError, match="out of range"):
        mix[5]


def test_parts_with_different_aspect_ratios_are_refused():
    with pytest.raises(ValueError, match="share their aspect ratios"):
        PairMix([Fake("a", 3), Fake("b", 2, aspects=((64, 64),))])


def test_a_subset_keeps_the_chosen_pairs_and_the_aspect_index():
    from training.mix import PairSubset

    sub = PairSubset(Fake("a", 5), [4, 1])
    assert len(sub) == 2 and sub.aspects == [(32, 32), (16, 32)]
    assert sub[0] == ("a", 4) and sub[(1, 1)] == ("a", (1, 1))
    with pytest.raises(ValueError, match="at least one pair"):
        PairSubset(Fake("a", 5), [])


def test_the_rotation_curriculum_keeps_exactly_the_pairs_under_the_limit(tmp_path):
    import numpy as np

    from training.mix import limit_rotation, relative_rotations_deg

    class Reader:
        def meta(self, scene):
            def rot(deg):
                a = np.radians(deg)
                return [[np.cos(a), 0, np.sin(a), 0], [0, 1, 0, 0], [-np.sin(a), 0, np.cos(a), 0], [0, 0, 0, 1]]
            return {"views": [{"cam2world": rot(0)}, {"cam2world": rot(10)}, {"cam2world": rot(50)}]}

    class Store:
        def reader(self, k):
            return Reader()

    ds = Fake("a", 3)
    ds.items, ds._store = [(0, "s", 0, 1), (0, "s", 0, 2), (0, "s", 1, 2)], Store()
    assert np.allclose(relative_rotations_deg(ds), [10, 50, 40])
    sub = limit_rotation(ds, 45)
    assert [sub[i] for i in range(len(sub))] == [("a", 0), ("a", 2)]
    assert limit_rotation(ds, 0) is ds
