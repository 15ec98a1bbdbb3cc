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
