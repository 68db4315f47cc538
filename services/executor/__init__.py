"""The executor: the robot end of the bus (architecture §1).

Library (no Zenoh): :mod:`services.executor.base` (the :class:`Executor` interface),
:mod:`services.executor.contacts` (the contact reports and tallies it returns),
:mod:`services.executor.errors` (the executor's error base); one package per backend:
:mod:`services.executor.mujoco` (the MuJoCo simulation with the person's capsules: model, contacts,
sim, executor; shared with the offline evaluator) and :mod:`services.executor.g1` (the real G1:
layout, frames, state, CycloneDDS transport, controller, executor, stand-in robot, errors). Service:
:mod:`services.executor.service` (``safemimic executor``, ``python -m services.executor``).
"""
