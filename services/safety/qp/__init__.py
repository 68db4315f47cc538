"""QP backends for the CBF-QP (paper eq. 8), one per file behind :class:`QPBackend`.

Problem: min_u ½ (u − u_ref)ᵀ W (u − u_ref)  s.t.  A u ≥ b,  u_min ≤ u ≤ u_max, with W diagonal.
"""

from services.safety.qp.base import QPBackend, QPProblem, QPSolution, QPStatus
from services.safety.qp.daqp_backend import DaqpBackend
from services.safety.qp.osqp_backend import OsqpBackend

BACKENDS: dict[str, type[QPBackend]] = {"daqp": DaqpBackend, "osqp": OsqpBackend}


def make_backend(name: str) -> QPBackend:
    """A fresh backend instance by name (``daqp`` or ``osqp``)."""
    try:
        return BACKENDS[name]()
    except KeyError:
        raise ValueError(f"unknown QP backend {name!r}; known: {', '.join(BACKENDS)}") from None


__all__ = ["BACKENDS", "QPBackend", "QPProblem", "QPSolution", "QPStatus", "make_backend"]
