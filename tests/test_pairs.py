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


@pytest.mark.parametrize("graph", ["star", "swin", "swin-x", "oneref-9", "swin-0", "swin-2-cyclic", "retrieval-0",
                                   "retrieval-2-noncyclic", "retrieval", "oneref-1-noncyclic"])
def test_unknown_or_malformed_graphs_are_refused(graph):
    with pytest.raises(pm.GraphError):
        pm.make_pairs(5, graph)


def test_auto_is_a_graph_name_only_where_the_caller_takes_it_and_is_then_named_among_the_expected():
    from pointmap.pairs import parse_graph

    assert parse_graph("auto", auto=True) == ("auto", None, True)
    with pytest.raises(pm.GraphError, match="unknown graph 'auto'; expected one of: complete,"):
        parse_graph("auto")
    with pytest.raises(pm.GraphError, match="unknown graph 'bogus'; expected one of: auto, complete,"):
        parse_graph("bogus", auto=True)


def test_a_single_image_has_no_pairs():
    with pytest.raises(pm.GraphError, match="at least 2"):
        pm.make_pairs(1)


def test_a_disconnected_graph_is_reported_with_its_components():
    with pytest.raises(pm.GraphError, match="2 components"):
        pm.check_connected(4, [(0, 1), (2, 3)])
    pm.check_connected(4, [(0, 1), (1, 2), (2, 3)])
    for n, pairs, named in ((3, None, "expected \\(i, j\\) pairs of image indices, got NoneType"),
                            (-1, [], "expected a number of images \\(an int >= 1\\), got -1"),
                            (3.0, [(0, 1)], "got 3.0"), (3, [(0.5, 1)], "got \\(0.5, 1\\)")):
        with pytest.raises(pm.GraphError, match=named):
            pm.check_connected(n, pairs)


def test_numpy_image_counts_are_taken_and_other_types_are_refused_naming_them():
    assert pm.make_pairs(np.int64(3)) == [(0, 1), (0, 2), (1, 2)]
    with pytest.raises(pm.GraphError, match="expected a number of images \\(an int\\), got float 3.0"):
        pm.make_pairs(3.0)
    with pytest.raises(pm.GraphError, match="graph expected a name .*got int 5"):
        pm.make_pairs(3, 5)


def _max_spanning_weight(n, pairs, s):
    """Kruskal's maximum spanning tree over ``pairs`` (the slow reference): its total similarity, or None when the
    pairs do not connect the n images."""
    parent = list(range(n))

    def find(a):
        while parent[a] != a:
            a = parent[a]
        return a

    total, used = 0.0, 0
    for i, j in sorted(pairs, key=lambda p: -s[p[0], p[1]]):
        a, b = find(i), find(j)
        if a != b:
            parent[a] = b
            total, used = total + s[i, j], used + 1
    return total if used == n - 1 else None


def test_the_retrieval_graph_holds_each_images_nearest_and_a_maximum_spanning_tree_of_the_similarity():
    from pointmap.pairs import pairs_from_similarity

    rng = np.random.default_rng(0)
    for n, k in [(2, 1), (5, 1), (7, 2), (9, 3), (12, 1)]:
        x = rng.normal(size=(n, 6))
        s = x @ x.T
        pairs = pairs_from_similarity(s, k)
        assert pairs == sorted(set(pairs)) and all(i < j for i, j in pairs)
        everything = [(i, j) for i in range(n) for j in range(i + 1, n)]
        # its best spanning tree is as good as the complete graph's: a maximum spanning tree is in it
        assert _max_spanning_weight(n, pairs, s) == pytest.approx(_max_spanning_weight(n, everything, s))
        for i in range(n):  # each image's k most similar others
            others = sorted((j for j in range(n) if j != i), key=lambda j: -s[i, j])[:k]
            assert all((min(i, j), max(i, j)) in pairs for j in others)
        assert len(pairs) <= k * n + n - 1
        assert pairs_from_similarity(s, k) == pairs  # deterministic


def test_two_groups_of_alike_images_are_paired_within_each_group_and_joined_once():
    from pointmap.pairs import pairs_from_similarity

    s = np.full((6, 6), 0.1)
    s[:3, :3] = s[3:, 3:] = 0.9
    s[2, 4] = s[4, 2] = 0.3  # the best link between the groups
    pairs = pairs_from_similarity(s, 2)
    assert pairs == [(0, 1), (0, 2), (1, 2), (2, 4), (3, 4), (3, 5), (4, 5)]
    pm.check_connected(6, pairs)
    for diagonal in (-np.inf, np.nan):  # a common way to leave out self-pairs; the diagonal is ignored anyway
        np.fill_diagonal(s, diagonal)
        assert pairs_from_similarity(s, 2) == pairs


@pytest.mark.parametrize("sim,k,message", [
    (np.ones((3, 2)), 1, r"an \[N, N\] similarity of N >= 2 images, got shape \[3, 2\]"),
    (np.ones((1, 1)), 1, "N >= 2"),
    (np.array([[1.0, np.nan], [np.nan, 1.0]]), 1, "sim holds 2 NaN or infinite scores off its diagonal"),
    (np.eye(3), 0, "k expected an int >= 1"),
    (np.eye(3), 1.5, "k expected an int >= 1"),
    (None, 1, "numeric similarity .*got NoneType"),
    ([["a", "b"], ["c", "d"]], 1, "numeric similarity .*got list"),
    ([[1.0, 0.5], [0.5]], 1, "numeric similarity .*got list"),
])
def test_the_retrieval_graph_refuses_a_similarity_it_cannot_use(sim, k, message):
    from pointmap.pairs import pairs_from_similarity

    with pytest.raises(pm.GraphError, match=message):
        pairs_from_similarity(sim, k)


def test_a_retrieval_graph_cannot_be_made_from_a_count_alone():
    with pytest.raises(pm.GraphError, match="from the images' similarity"):
        pm.make_pairs(8, "retrieval-3")


def test_equal_scores_go_to_the_lower_index():
    from pointmap.pairs import pairs_from_similarity

    assert pairs_from_similarity(np.ones((4, 4)), 1) == [(0, 1), (0, 2), (0, 3)]


def test_given_pairs_may_be_an_index_array_and_are_checked_like_a_list():
    import torch

    from pointmap.pairs import pairs_from_list

    assert pairs_from_list(3, np.array([[1, 0], [2, 1]])) == [(0, 1), (1, 2)]
    assert pairs_from_list(3, torch.tensor([[0, 2], [2, 1]])) == [(0, 2), (1, 2)]
    with pytest.raises(pm.GraphError, match=r"an \[M, 2\] array of image indices, got shape \[2, 3\]"):
        pairs_from_list(3, np.zeros((2, 3), int))
    with pytest.raises(pm.GraphError, match="expected \\(i, j\\) pairs of image indices"):
        pairs_from_list(3, np.array([[0.5, 1.0]]))


def _windows_by_definition(n, kind, k, cyclic):
    """swin / logwin as defined: every image with the ones ``s`` ahead, s in 1..k or 2**0..2**(k-1), wrapped
    around when cyclic."""
    edges = set()
    for i in range(n):
        for s in (range(1, k + 1) if kind == "swin" else [2**e for e in range(k)]):
            j = i + s
            if j >= n and not cyclic:
                continue
            j %= n
            if i != j:
                edges.add((min(i, j), max(i, j)))
    return sorted(edges)


def test_window_graphs_equal_their_definition_for_any_window_and_a_huge_one_costs_nothing():
    for n in range(2, 30):
        for kind in ("swin", "logwin"):
            for k in range(1, 40):
                for suffix, cyclic in (("", True), ("-noncyclic", False)):
                    assert pm.make_pairs(n, f"{kind}-{k}{suffix}") == _windows_by_definition(n, kind, k, cyclic), \
                        (n, kind, k, cyclic)
    assert pm.make_pairs(3, "swin-999999999") == pm.make_pairs(3, "complete")
    assert pm.make_pairs(50, "logwin-999999999") == _windows_by_definition(50, "logwin", 200, True)
    # (before, the offsets ran to K: the first call took minutes)


@pytest.mark.parametrize("graph", ["swin- 1", "swin-\uff13", "logwin-+2"])
def test_a_window_that_is_not_plain_digits_is_refused(graph):
    with pytest.raises(pm.GraphError, match="is not a whole number"):
        pm.make_pairs(5, graph)
