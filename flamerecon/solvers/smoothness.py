"""Old import path of :mod:`flamerecon.operators.differences`, kept for a while."""

from ..operators.differences import (  # noqa: F401
    HullGradient,
    StackedOperator,
    forward_neighbours,
    hull_gradient,
)
