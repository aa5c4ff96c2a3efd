"""The real datasets, one module each: where their files are, how they are read and verified.

:mod:`plad.datasets.cad` is CSGNet's 2D CAD shapes; :mod:`plad.datasets.partnet`
the PartNet shapes given as ShapeAssembly programs, executed and voxelized.
Each exposes a :class:`plad.data.TargetSource` that domains name as their
real targets; what datasets share lives in :mod:`plad.data`.
"""

#: TargetSource.name -> "module:function" returning the lines of ``plad data check`` for that source
#: (raising :class:`plad.data.DataError`); neither loads torch. A test checks that every registered
#: domain's target source has one.
CHECKS: dict[str, str] = {
    "cad": "plad.datasets.cad:check",
    "partnet": "plad.datasets.partnet.source:check",
}

#: TargetSource.name -> "module:function" returning {file: sha256} of the source's data files
#: (the provenance of a shipped model)
FILES: dict[str, str] = {
    "cad": "plad.datasets.cad:checksums",
    "partnet": "plad.datasets.partnet.source:checksums",
}
