"""Point clouds and RGB-D captures -> surfaces -> :class:`~perception.geometry.ObjectModel`, one concern a module.

- :mod:`~perception.reconstruct.pointfiles`: point-cloud files (PCD, XYZ/XYZN/XYZRGB/PTS, PLY, NPY/NPZ):
  :func:`~perception.reconstruct.pointfiles.read_points`, :func:`~perception.reconstruct.pointfiles.write_points`.
- :mod:`~perception.reconstruct.points`: clouds checked (:func:`~perception.reconstruct.points.validate_points`),
  outliers removed, normals estimated and oriented.
- :mod:`~perception.reconstruct.surface`: oriented points -> surface (screened Poisson trimmed by density; ball
  pivoting or alpha shapes) -> ``ObjectModel``: :func:`~perception.reconstruct.surface.load_points` (also
  ``perception.load_points``), :func:`~perception.reconstruct.surface.points_to_model`, and
  :func:`~perception.reconstruct.surface.surface_error` against a true mesh.
- :mod:`~perception.reconstruct.tabletop`: RGB-D points -> table plane (RANSAC) -> objects on it, each
  alone (:func:`~perception.reconstruct.tabletop.segment_table`), and the one to touch
  (:func:`~perception.reconstruct.tabletop.pick_cluster`).
- :mod:`~perception.reconstruct.carving`: the space the frames left for an object (what no camera saw).
- :mod:`~perception.reconstruct.multiview`: the chosen object's views fused (known poses, ICP refinement) and
  closed where no camera saw it: :func:`~perception.reconstruct.multiview.reconstruct_frames`.

Units are millimetres. Every random choice (RANSAC) is seeded and Poisson runs on one thread, so the same
input and seed give the same bytes.
"""
