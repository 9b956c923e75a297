"""Longitudinal analysis of torso surfaces: visit-to-visit comparison, repeatability, clinical indices, pictures.

Plain Python over numpy arrays (no Django). Stages, one module each:

- :mod:`analysis.torso`: torso point clouds, outward normals, local planes
- :mod:`analysis.rigid`: robust rigid registration (no scale)
- :mod:`analysis.frame`: the patient frame (vertical, facing, mid-sagittal plane)
- :mod:`analysis.backsurface`: the back's depth map, profiles, line of symmetry
- :mod:`analysis.landmarks`: vertebra prominens and sacral point
- :mod:`analysis.indices`: clinical surface indices (``torso-indices/1``)
- :mod:`analysis.compare`: visit to visit (``torso-comparison/1``)
- :mod:`analysis.repeatability`: SEM, minimal detectable change, flags
- :mod:`analysis.pictures`: off-screen pictures (shaded surfaces rasterised in numpy by
  :mod:`analysis.render`, matplotlib)
- :mod:`analysis.synthetic`: scan-like samples of known surfaces (tests, validation)

Parameters: :mod:`analysis.config`. Documentation: ``docs/analysis.md``.
"""
