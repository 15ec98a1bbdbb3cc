import numpy as np
import pytest

import pointmap as pm


def test_complete_graph_has_every_unordered_pair_once():
    assert pm.make_pairs(4) == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]


def test_sliding_windows_wrap_around_unless_noncyclic():
    cyclic = pm.make_pairs(7, "swin-2")
    assert len(cyclic) == 14 and (0, 6) in cyclic and (0, 5) in cyclic and (0, 4) not in cyclic
    assert pm.make_pairs(7, "swin-2-noncyclic") == sorted({(i, i + s) for i in range(7) for s in (1, 2) if i + s < 7})


def test_log_windows_link_powers_of_two_apart():
    assert pm.make_pairs(9, "logwin-3-noncyclic") == sorted(
        {(i, i + s) for i in range(9) for s in (1, 2, 4) if i + s < 9})


def test_oneref_links_everything_to_the_reference():
    assert pm.make_pairs(4, "oneref-2") == [(0, 2), (1, 2), (2, 3)]


@pytest.mark.parametrize("graph", ["star", "swin", "swin-x", "oneref-9", "swin-0", "swin-2-cyclic"])
def test_unknown_or_malformed_graphs_are_refused(graph):
    with pytest.raises(pm.GraphError):
        pm.make_pairs(5, graph)


def test_a_single_image_has_no_pairs():
    with pytest.raises(pm.GraphError, match="at least 2"):
        pm.make_pairs(1)


def test_a_disconnected_graph_is_reported_with_its_components():
    with pytest.raises(pm.GraphError, match="2 components"):
        pm.check_connected(4, [(0, 1), (2, 3)])
    pm.check_connected(4, [(0, 1), (1, 2), (2, 3)])


def test_numpy_image_counts_are_taken_and_other_types_are_refused_naming_them():
    assert pm.make_pairs(np.int64(3)) == [(0, 1), (0, 2), (1, 2)]
    with pytest.raises(pm.GraphError, match="expected a number of images \\(an int\\), got float 3.0"):
        pm.make_pairs(3.0)
    with pytest.raises(pm.GraphError, match="graph expected a name .*got int 5"):
        pm.make_pairs(3, 5)
