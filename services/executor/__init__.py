"""The executor: the robot end of the bus (architecture §1).

Library (no Zenoh): :mod:`services.executor.sim` (the MuJoCo simulation with the person's
capsules and contact counting, shared with the offline evaluator), :mod:`services.executor.contacts`
(contact reports and tallies), :mod:`services.executor.interface` (the :class:`Executor` interface),
:mod:`services.executor.mujoco_executor` (its MuJoCo implementation). Service:
:mod:`services.executor.service` (``safemimic executor``, ``python -m services.executor``).
"""
