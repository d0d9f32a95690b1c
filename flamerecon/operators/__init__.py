"""Linear operators from voxels (M, C) to measurements (N, C): the protocol, the dot test, the
cached operator norm, the assembled CSR operator and the finite differences on the hull. The
projector's own operators (:mod:`flamerecon.operators.projector`) follow the same protocol."""

from flamerecon.operators.base import LinearOperator, dottest, norm, norm_sq, residual_gradient
from flamerecon.operators.differences import (
           HullGradient,
           StackedOperator,
           forward_neighbours,
           hull_gradient,
)
from flamerecon.operators.sparse import CsrOperator, csr_matmul

__all__ = ["CsrOperator", "HullGradient", "LinearOperator", "StackedOperator", "csr_matmul",
           "dottest", "forward_neighbours", "hull_gradient", "norm", "norm_sq", "residual_gradient"]
