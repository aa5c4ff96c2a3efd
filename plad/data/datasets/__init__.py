"""The real datasets, one module each: where their files are, how they are read and verified.

:mod:`plad.data.datasets.cad` is CSGNet's 2D CAD shapes; :mod:`plad.data.datasets.partnet`
the PartNet shapes given as ShapeAssembly programs, executed and voxelized.
Each exposes a :class:`plad.data.files.TargetSource` that domains name as their
real targets; what datasets share lives in :mod:`plad.data.files`.
"""

#: TargetSource.name -> "module:function" returning the lines of ``plad data check`` for that source
#: (raising :class:`plad.data.files.DataError`); neither loads torch. A test checks that every registered
#: domain's target source has one.
CHECKS: dict[str, str] = {
    "cad": "plad.data.datasets.cad:check",
    "partnet": "plad.data.datasets.partnet.source:check",
}

#: TargetSource.name -> "module:function" returning {file: sha256} of the source's data files
#: (the provenance of a shipped model)
FILES: dict[str, str] = {
    "cad": "plad.data.datasets.cad:checksums",
    "partnet": "plad.data.datasets.partnet.source:checksums",
}
