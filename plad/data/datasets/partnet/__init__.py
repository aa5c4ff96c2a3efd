"""PartNet shapes given as ShapeAssembly programs (Jones et al. 2020), executed and voxelized at 32^3.

Modules: :mod:`.lang` (the full hierarchical ShapeAssembly language text),
:mod:`.execute` (its executor to oriented cuboids), :mod:`.voxels` (32^3
voxelization of cuboids), :mod:`.dataset` (the programs tarball, its split
rule, the prepared file and the target source :data:`.dataset.TARGETS`).

The interpreter and voxelizer live with the dataset because its shapes are
defined by them; domains whose programs execute to cuboids use them too.
"""
