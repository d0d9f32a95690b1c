"""CsrOperator: the assembled operator agrees with a dense reference in every direction
(its dot test is in test_operators.py)."""

from __future__ import annotations

import numpy as np
import torch

from tests.helpers import random_coo


def test_forward_adjoint_match_dense_with_duplicates_summed():
    op, dense = random_coo()
    x, y = torch.rand(40, 3), torch.rand(50, 3)
    torch.testing.assert_close(op.forward(x), torch.tensor(dense) @ x, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(op.adjoint(y), torch.tensor(dense).T @ y, rtol=1e-5, atol=1e-5)


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
