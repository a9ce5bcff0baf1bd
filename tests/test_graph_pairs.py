"""Tiled pair convs (model/graph/pairs.py) against the twin `conv_fixed` on the same tables."""

from __future__ import annotations

import pytest
import torch
from test_graph_sparse import padded_features, random_sites

from model.geometry.rulebook import Plane
from model.graph.pairs import TILE, conv_tiles, pair_tiles
from model.graph.sparse_conv import conv_fixed, inverse_table, strided_sites, subm_table


@pytest.mark.parametrize("kernel", [(3, 3), (3, 1), (3, 5)])
@pytest.mark.parametrize("n", [0, 1, 150, 400])
def test_subm_pairs_match_implicit_gemm(kernel: tuple[int, int], n: int) -> None:
    cap = n + 13
    sites, _ = random_sites(n, cap, seed=n + kernel[1], shape=(12, 10, 7) if n < 400 else (9, 8, 7))
    table = subm_table(sites, kernel, Plane.RZ)  # (cap, KK)
    real = int((table < cap).sum())
    weight, bias = torch.randn(table.shape[1], 5, 6), torch.randn(6)
    x = padded_features(n, cap, 5)
    pairs = pair_tiles(table, cap, real)  # exactly enough room
    assert int(pairs.count) == real
    assert pairs.offset.shape[0] == -(-real // TILE) + table.shape[1]
    torch.testing.assert_close(conv_tiles(x, pairs, weight, bias), conv_fixed(x, table, weight, bias))


@pytest.mark.parametrize("n", [7, 200])
def test_inverse_pairs_match_inverse_table(n: int) -> None:
    cap = n + 11
    sites, _ = random_sites(n, cap, seed=3 * n)
    out_sites, table = strided_sites(sites, 3, (2, 2), Plane.RZ, out_cap=cap + 40)
    pairs = pair_tiles(table, cap, int((table < cap).sum()) + 5)
    x, w, b = padded_features(n, cap, 4), torch.randn(9, 4, 6), torch.randn(6)
    down = conv_tiles(x, pairs, w, b)
    torch.testing.assert_close(down, conv_fixed(x, table, w, b))
    w_up = torch.randn(9, 6, 3)
    back_ref = conv_fixed(down, inverse_table(sites, out_sites, 3, (2, 2), Plane.RZ), w_up, None)
    torch.testing.assert_close(conv_tiles(down, pairs.inverse(), w_up, None), back_ref)


def test_pair_overflow_is_counted() -> None:
    """Fewer pair slots than pairs: the count says so (the step runs again); the result stays finite."""
    n = 200
    sites, _ = random_sites(n, n, seed=9)
    table = subm_table(sites, (3, 3), Plane.RZ)
    real = int((table < n).sum())
    pairs = pair_tiles(table, n, cap=TILE)  # far too small
    assert int(pairs.count) == real > TILE
    x, w = torch.randn(n, 4), torch.randn(9, 4, 2)
    out = conv_tiles(x, pairs, w, None)
    assert out.shape == (n, 2) and bool(torch.isfinite(out).all())
    assert not torch.allclose(out, conv_fixed(x, table, w, None))  # pairs were dropped


def test_compiled_pair_conv_matches_eager() -> None:
    sites, _ = random_sites(150, 170, seed=4)
    table = subm_table(sites, (3, 3), Plane.RZ)
    x, w, b = padded_features(150, 170, 5), torch.randn(9, 5, 6), torch.randn(6)

    def run(x: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
        return conv_tiles(x, pair_tiles(table, 170, 512), w, b)

    compiled = torch.compile(run, fullgraph=True, dynamic=False)
    torch.testing.assert_close(compiled(x, table), run(x, table))
