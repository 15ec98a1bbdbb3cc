"""Pair graphs over N images: complete, swin-k, logwin-k, oneref-i, retrieval-k; connectivity check.

Pairs are unordered ``(i, j)`` with ``i < j``; inference runs both orders of each.
"""

from __future__ import annotations

from pointmap.errors import GraphError, is_int

GRAPHS = "complete, swin-K, logwin-K, oneref-I, retrieval-K (swin/logwin take a '-noncyclic' suffix)"


def parse_graph(graph: str, *, auto: bool = False) -> tuple[str, int | None, bool]:
    """(kind, K, cyclic) of a graph name (``GRAPHS``: ``complete`` has no K); GraphError for a name that is none of
    them. Whether it suits a number of images (``oneref-I``'s reference index) is ``make_pairs``' check.

    auto: also take ``"auto"`` (``("auto", None, True)``), the pipeline's choice by image count
    (``pointmap.pipeline.auto_graph``), and name it among the expected ones when refusing."""
    expected = f"auto, {GRAPHS}" if auto else GRAPHS
    if auto and graph == "auto":
        return "auto", None, True
    if not isinstance(graph, str):
        raise GraphError(f"graph expected a name (one of: {expected}), got {type(graph).__name__} {graph!r}")
    parts = graph.split("-")
    kind = parts[0]
    cyclic = not (len(parts) == 3 and parts[2] == "noncyclic")
    if (len(parts) == 3 and parts[2] != "noncyclic") or len(parts) > 3:
        raise GraphError(f"unknown graph {graph!r}; expected one of: {expected}")
    if kind == "complete" and len(parts) == 1:
        return kind, None, cyclic
    if kind in ("retrieval", "oneref") and len(parts) == 3:
        why = "pairs by similarity, not by order" if kind == "retrieval" else "pairs every image with one reference"
        raise GraphError(f"graph {graph!r}: {kind} {why} (no '-noncyclic': only swin and logwin wrap around)")
    if kind in ("swin", "logwin", "oneref", "retrieval") and len(parts) >= 2:
        if not (parts[1].isascii() and parts[1].isdigit()):  # int() would take " 1" and full-width digits
            raise GraphError(f"graph {graph!r}: {parts[1]!r} is not a whole number (digits 0-9)")
        k = int(parts[1])
        if kind != "oneref" and k < 1:
            raise GraphError(f"{kind}-{k}: {'neighbours' if kind == 'retrieval' else 'window'} must be >= 1")
        return kind, k, cyclic
    raise GraphError(f"unknown graph {graph!r}; expected one of: {expected}")


def make_pairs(n: int, graph: str = "complete") -> list[tuple[int, int]]:
    """Unordered pairs of a named graph over ``n`` images, sorted, without duplicates.

    Example:
        >>> make_pairs(4, "swin-1-noncyclic")
        [(0, 1), (1, 2), (2, 3)]
    """
    if not is_int(n):
        raise GraphError(f"a pair graph expected a number of images (an int), got {type(n).__name__} {n!r}")
    n = int(n)
    if n < 2:
        raise GraphError(f"a pair graph needs at least 2 images, got {n}")
    kind, k, cyclic = parse_graph(graph)
    if kind == "retrieval":
        raise GraphError(f"{graph}: the pairs come from the images' similarity, not from their count: use "
                         f"pm.reconstruct(..., graph={graph!r}) or pairs_from_similarity(sim, {k})")
    if kind == "complete":
        return [(i, j) for i in range(n) for j in range(i + 1, n)]
    if kind == "oneref":
        if not 0 <= k < n:
            raise GraphError(f"oneref-{k}: reference index out of range for {n} images")
        return sorted({(min(k, j), max(k, j)) for j in range(n) if j != k})
    edges: set[tuple[int, int]] = set()
    # offsets past n - 1 add nothing new (skipped, or wrapped onto ones already there): a huge K costs O(n), not O(K)
    if kind == "swin":
        steps = range(1, min(k, n - 1 if not cyclic else n) + 1)
    elif cyclic:  # logwin: offsets 2**e modulo n repeat within n + log2(n) exponents; 0 pairs an image with itself
        steps = sorted({pow(2, e, n) for e in range(min(k, n + n.bit_length()))} - {0})
    else:
        steps = [2**e for e in range(min(k, n.bit_length())) if 2**e < n]
    for i in range(n):
        for s in steps:
            j = i + s
            if j >= n:
                if not cyclic:
                    continue
                j %= n
            if i != j:
                edges.add((min(i, j), max(i, j)))
    return sorted(edges)


def pairs_from_similarity(sim, k: int) -> list[tuple[int, int]]:
    """The ``retrieval-K`` graph: each image paired with its ``k`` most similar others, plus the maximum spanning tree
    of the similarity so that the graph is connected whatever the scores (unordered photo collections, where the
    file order says nothing about overlap). ``sim``: [N, N] symmetric scores (e.g. ``image_similarity``), higher =
    more alike; the diagonal is ignored. Sorted unordered pairs; ties go to the lower index. GraphError otherwise."""
    import torch

    given = sim
    try:
        sim = torch.as_tensor(sim, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):  # None, strings, ragged lists: said with what was given
        raise GraphError(f"sim expected an [N, N] numeric similarity (a tensor, an array or nested lists of numbers), "
                         f"got {type(given).__name__}") from None
    if sim.ndim != 2 or sim.shape[0] != sim.shape[1] or sim.shape[0] < 2:
        raise GraphError(f"sim expected an [N, N] similarity of N >= 2 images, got shape {list(sim.shape)}")
    off = ~torch.eye(sim.shape[0], dtype=torch.bool)  # the diagonal is ignored: -inf or NaN there leaves out self-pairs
    if not bool(torch.isfinite(sim[off]).all()):
        raise GraphError(f"sim holds {int((~torch.isfinite(sim[off])).sum())} NaN or infinite scores off its diagonal")
    if not (is_int(k) and k >= 1):
        raise GraphError(f"k expected an int >= 1 (neighbours per image), got {k!r}")
    n = sim.shape[0]
    s = (sim + sim.T) / 2
    s.fill_diagonal_(-torch.inf)
    edges: set[tuple[int, int]] = set()
    order = torch.argsort(-s, dim=1, stable=True)
    for i in range(n):
        for j in order[i, : min(int(k), n - 1)].tolist():
            edges.add((min(i, j), max(i, j)))
    # Prim's maximum spanning tree: the most similar link from the connected part to each image outside it
    inside = torch.zeros(n, dtype=torch.bool)
    inside[0] = True
    best, link = s[0].clone(), torch.zeros(n, dtype=torch.long)
    for _ in range(n - 1):
        cand = torch.where(inside, torch.full_like(best, -torch.inf), best)
        j = int(torch.argmax(cand))
        edges.add((min(j, int(link[j])), max(j, int(link[j]))))
        inside[j] = True
        closer = s[j] > best
        best = torch.where(closer, s[j], best)
        link = torch.where(closer, torch.full_like(link, j), link)
    return sorted(edges)


def checked_index_pairs(n: int, pairs) -> list[tuple[int, int]]:
    """``pairs`` as (i, j) tuples of ints, in their order and direction, each index in 0..n-1 and i != j;
    GraphError naming the first bad pair otherwise (``predict_pairs`` and ``pairs_from_list`` check with this).
    An [M, 2] integer array or tensor is read as its rows."""
    if hasattr(pairs, "tolist") and hasattr(pairs, "shape"):
        if len(pairs.shape) != 2 or pairs.shape[1] != 2:
            raise GraphError(f"pairs expected an [M, 2] array of image indices, got shape {list(pairs.shape)}")
        pairs = pairs.tolist()
    out = []
    for p in pairs:
        if not (isinstance(p, (tuple, list)) and len(p) == 2 and all(is_int(k) for k in p)):
            raise GraphError(f"pairs expected (i, j) pairs of image indices, got {p!r}")
        i, j = int(p[0]), int(p[1])
        if not (0 <= i < n and 0 <= j < n) or i == j:
            raise GraphError(f"invalid pair ({i}, {j}) for {n} images: indices must differ and be in 0..{n - 1}")
        out.append((i, j))
    return out


def pairs_from_list(n: int, pairs) -> list[tuple[int, int]]:
    """A pair graph given as (i, j) index pairs (a list, or an [M, 2] integer array or tensor, e.g. from an external
    retrieval): sorted unordered pairs without duplicates ((j, i) is (i, j)), each index in 0..n-1 and i != j,
    connecting all ``n`` images; GraphError naming the first bad pair or the components otherwise."""
    if not is_int(n) or int(n) < 2:
        raise GraphError(f"a pair graph needs at least 2 images, got {n!r}")
    n = int(n)
    if isinstance(pairs, (str, bytes)) or not hasattr(pairs, "__iter__"):
        raise GraphError(f"pairs expected a list of (i, j) image index pairs, got {type(pairs).__name__}")
    out = {(min(i, j), max(i, j)) for i, j in checked_index_pairs(n, pairs)}
    if not out:
        raise GraphError("pairs expected at least one (i, j) pair, got none")
    check_connected(n, out)
    return sorted(out)


def components(n: int, pairs) -> list[list[int]]:
    """Connected components of the pair graph (lists of image indices, largest first)."""
    if not (is_int(n) and n >= 1):
        raise GraphError(f"a pair graph expected a number of images (an int >= 1), got {n!r}")
    if pairs is None or isinstance(pairs, (str, bytes)) or not hasattr(pairs, "__iter__"):
        raise GraphError(f"a pair graph expected (i, j) pairs of image indices, got {type(pairs).__name__}")
    parent = list(range(n))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for p in pairs:
        if not (isinstance(p, (tuple, list)) and len(p) == 2 and all(is_int(k) for k in p)):
            raise GraphError(f"pairs expected (i, j) pairs of image indices, got {p!r}")
        i, j = int(p[0]), int(p[1])
        if not (0 <= i < n and 0 <= j < n):
            raise GraphError(f"pair ({i}, {j}) refers to an image outside 0..{n - 1}")
        parent[find(i)] = find(j)
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(find(i), []).append(i)
    return sorted(groups.values(), key=lambda g: (-len(g), g[0]))


def check_connected(n: int, pairs) -> None:
    """Raise GraphError naming the components when the graph does not connect all ``n`` images."""
    comps = components(n, pairs)
    if len(comps) > 1:
        shown = ", ".join(str(c if len(c) <= 8 else c[:8] + ["..."]) for c in comps[:4])
        raise GraphError(f"the pair graph is disconnected: {len(comps)} components ({shown}); "
                         f"add pairs between them or use graph='complete'")
