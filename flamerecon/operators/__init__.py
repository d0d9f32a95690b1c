"""Linear operators from voxels (M, C) to measurements (N, C): the protocol, the dot test, the
cached operator norm, the assembled CSR operator and the finite differences on the hull. The
projector's own operators (:mod:`flamerecon.projector`) follow the same protocol."""

from .base import LinearOperator, dottest, norm, norm_sq
from .differences import HullGradient, StackedOperator, forward_neighbours, hull_gradient
from .sparse import CsrOperator, csr_matmul

__all__ = ["CsrOperator", "HullGradient", "LinearOperator", "StackedOperator", "csr_matmul",
           "dottest", "forward_neighbours", "hull_gradient", "norm", "norm_sq"]
