"""The executor: the robot end of the bus (architecture §1).

Library (no Zenoh): :mod:`services.executor.mujoco.sim` (the MuJoCo simulation with the person's
capsules and contact counting, shared with the offline evaluator), :mod:`services.executor.contacts`
(contact reports and tallies), :mod:`services.executor.base` (the :class:`Executor` interface),
:mod:`services.executor.mujoco.executor` (its MuJoCo implementation), :mod:`services.executor.g1`
(the real G1: layout, frames, state, CycloneDDS transport, controller, executor, stand-in robot). Service:
:mod:`services.executor.service` (``safemimic executor``, ``python -m services.executor``).
"""
