"""The hybrid's strata of spatial bins (workers/walk/hybrid.py): a partition of the bins into k
contiguous pieces, and the size of the piece holding each bin (the density of a stratified
uniform sample, q_j = 1 / (n_j r dr dtheta), is wrong by the factor of any error here)."""

from __future__ import annotations

import pytest
import torch

from workers.walk.hybrid import _stratum_size, strata


@pytest.mark.parametrize("k", [1, 2, 3, 5])
def test_strata_partition_and_sizes(k):
    for n in range(k, 70):
        pieces = strata(n, k)
        assert pieces[0][0] == 0 and pieces[-1][1] == n
        assert all(a < b for a, b in pieces)  # nonempty
        assert all(pieces[j][1] == pieces[j + 1][0] for j in range(k - 1))  # contiguous
        want = torch.tensor([b - a for a, b in pieces for _ in range(a, b)])  # size of bin i's stratum
        assert torch.equal(_stratum_size(torch.arange(n), n, k), want), (n, k)
