"""CsrOperator: the assembled operator agrees with a dense reference in every direction."""

from __future__ import annotations

import numpy as np
import torch

from flamerecon.sparse_ops import CsrOperator


def random_coo(seed: int = 0, N: int = 50, M: int = 40, nnz: int = 300):
    g = np.random.default_rng(seed)
    rows, cols = g.integers(0, N, nnz), g.integers(0, M, nnz)  # duplicates on purpose
    vals = g.random(nnz).astype(np.float32)
    dense = np.zeros((N, M), np.float32)
    np.add.at(dense, (rows, cols), vals)
    op = CsrOperator.from_coo(torch.tensor(rows), torch.tensor(cols), torch.tensor(vals), (N, M))
    return op, dense


def test_forward_adjoint_match_dense_with_duplicates_summed():
    op, dense = random_coo()
    x, y = torch.rand(40, 3), torch.rand(50, 3)
    torch.testing.assert_close(op.forward(x), torch.tensor(dense) @ x, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(op.adjoint(y), torch.tensor(dense).T @ y, rtol=1e-5, atol=1e-5)


def test_dot_test():
    op, _ = random_coo(seed=1)
    x, y = torch.rand(40, 2, dtype=torch.float32), torch.rand(50, 2, dtype=torch.float32)
    lhs = float((op.forward(x).double() * y.double()).sum())
    rhs = float((x.double() * op.adjoint(y).double()).sum())
    assert abs(lhs - rhs) <= 1e-5 * abs(lhs)


def test_forward_backward_is_the_adjoint():
    op, dense = random_coo(seed=2)
    x = torch.rand(40, 3, requires_grad=True)
    y = torch.rand(50, 3)
    (op.forward(x) * y).sum().backward()
    torch.testing.assert_close(x.grad, torch.tensor(dense).T @ y, rtol=1e-5, atol=1e-5)
    assert not op.forward(x.detach()).requires_grad


def test_to_scipy_and_int32_indices():
    op, dense = random_coo(seed=3)
    assert op.A.col_indices().dtype == torch.int32 and op.AT.crow_indices().dtype == torch.int32
    np.testing.assert_allclose(op.to_scipy().toarray(), dense, rtol=1e-6)
    assert op.nnz == int((dense != 0).sum())
