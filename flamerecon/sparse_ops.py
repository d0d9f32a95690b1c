"""Old import path of :mod:`flamerecon.operators.sparse` (the CSR operator), kept for a while."""

from .operators.sparse import CsrOperator, csr_matmul  # noqa: F401
