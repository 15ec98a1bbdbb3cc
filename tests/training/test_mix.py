"""training.mix.open_pairs: what --data may name."""

from pathlib import Path

import pytest

from data.shards import ShardError
from training.mix import open_pairs


def test_a_path_object_is_read_like_its_string_and_a_folder_named_twice_is_refused(tmp_path):
    with pytest.raises(ShardError):  # the reader's own error for a folder without shards, not an AttributeError
        open_pairs(Path(tmp_path / "nowhere"))
    with pytest.raises(ValueError, match="names the same directory more than once"):
        open_pairs(f"{tmp_path}/a,{tmp_path}/a/")
    with pytest.raises(ValueError, match="expected shard directories .*got int"):
        open_pairs(3)



def test_a_mix_reads_a_negative_index_from_its_end_as_a_pair_dataset_does():
    from training.mix import PairMix

    class Part:
        aspects = [(32, 32), (32, 24)]

        def __init__(self, names):
            self.names = names

        def __len__(self):
            return len(self.names)

        def __getitem__(self, index):
            return (self.names[index[0]], index[1]) if isinstance(index, tuple) else self.names[index]

    mix = PairMix([Part(["a0", "a1"]), Part(["b0"])])
    assert [mix[i] for i in (-1, -3, 0, 2)] == ["b0", "a0", "a0", "b0"] and mix[(-2, 1)] == ("a1", 1)
    for bad in (3, -4):
        with pytest.raises(IndexError, match=f"index {bad} out of range for 3 pairs"):
            mix[bad]
