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
