"""Collision geometries of the CBF (paper §IV-B, Table I), one per module behind
:class:`~services.safety.barriers.pairs.CollisionGeometry`:

* ``capsule`` (default): :class:`services.safety.barriers.capsules.CapsuleBarrier`, one row per pair;
* ``spheres``: :class:`~services.safety.barriers.spheres.SphereBarrier`, each capsule decomposed
  into enclosing spheres, k levels of subsampling;
* ``box``: :class:`~services.safety.barriers.boxes.BoxBarrier`, the oriented bounding box of each
  capsule with its edges rounded by r/2 (``EDGE_ROUNDING``), signed distance and witness points
  from coal.

``services.safety.assembly.make_geometry`` builds the configured one (``safety.geometry``).
"""
