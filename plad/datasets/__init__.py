"""The real datasets, one module each: where their files are, how they are read and verified.

:mod:`plad.datasets.cad` is CSGNet's 2D CAD shapes; :mod:`plad.datasets.partnet`
the PartNet shapes given as ShapeAssembly programs, executed and voxelized.
Each exposes a :class:`plad.data.TargetSource` that domains name as their
real targets; what datasets share lives in :mod:`plad.data`.
"""
