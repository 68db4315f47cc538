"""Perception service (architecture §1): skeleton source → point filter → pose angles θ + human capsules.

Modules: ``stream`` (source interface, pacing), ``sources`` (replay / scenario / camera by config),
``placement`` (person ↔ robot frame), ``synthetic`` + ``scenarios`` (scripted people with known
angles), ``point_filter``, ``angles``, ``capsules``, ``pipeline`` (one step, no I/O), ``service``
(``safemimic perception``), ``record`` (``safemimic record-scenario``). Light dependencies only:
no MuJoCo, Pinocchio, QP solver or FastAPI anywhere on this package's import path.
"""
