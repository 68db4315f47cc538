"""The viewer service: a live 3D view of robot, person and barriers in Rerun (``safemimic viewer``).

It only subscribes. :mod:`services.viewer.robot_mesh` and :mod:`services.viewer.draw` are the
drawing code the offline evaluator's ``--rrd`` recordings use too (one source of entity names,
meshes and colours: :mod:`services.viewer.entities`).
"""
