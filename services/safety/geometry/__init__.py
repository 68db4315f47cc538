"""Collision geometries of the CBF (paper §IV-B, Table I), one per module behind
:class:`~services.safety.geometry.base.CollisionGeometry`:

* ``capsule`` (default): :class:`services.safety.barrier.CapsuleBarrier`, one row per pair;
* ``spheres``: :class:`~services.safety.geometry.spheres.SphereBarrier`, each capsule decomposed
  into enclosing spheres, k levels of subsampling;
* ``box``: :class:`~services.safety.geometry.boxes.BoxBarrier`, the oriented bounding box of each
  capsule with its edges rounded by r/2 (``EDGE_ROUNDING``), signed distance and witness points
  from coal.

``services.safety.assembly.make_geometry`` builds the configured one (``safety.geometry``).
"""
