"""QP backends for the CBF-QP (paper eq. 8), one per file behind :class:`QPBackend`.

Problem: min_u ½ (u − u_ref)ᵀ W (u − u_ref)  s.t.  A u ≥ b,  u_min ≤ u ≤ u_max, with W diagonal.
A backend's module is imported when first asked for (OSQP brings SciPy: ≈ 0.2 s of a service's start).
"""

import importlib

from services.safety.errors import SafetyConfigError
from services.safety.qp.base import QPBackend, QPProblem, QPSolution, QPStatus

#: backend name → (module, class)
BACKENDS: dict[str, tuple[str, str]] = {
    "daqp": ("services.safety.qp.daqp_backend", "DaqpBackend"),
    "osqp": ("services.safety.qp.osqp_backend", "OsqpBackend"),
}


def make_backend(name: str, **settings: float) -> QPBackend:
    """A fresh backend instance by name (``daqp`` or ``osqp``), with the backend's own ``settings``
    (e.g. DAQP's ``primal_tol``)."""
    try:
        module, cls = BACKENDS[name]
    except KeyError:
        raise SafetyConfigError(f"unknown QP backend {name!r}; known: {', '.join(BACKENDS)}") from None
    return getattr(importlib.import_module(module), cls)(**settings)


__all__ = ["BACKENDS", "QPBackend", "QPProblem", "QPSolution", "QPStatus", "make_backend"]
