"""Maintainers' tools: measuring, plotting and building what is committed (effort curves, routes, held-out
scores, search baselines, the grafting library, plots of run histories, token-kind probes).

Each is run from a checkout as ``python -m plad.tools.<name>``; no command, stage or inference of the package
runs one. They read the checkout's data and runs, and three write into the source tree (``plad/shipped/routes.json``,
``plad/domains/<domain>/graft_library.npz``, ``plad/shipped/<domain>/taught.pt`` with ``plad/shipped/taught.json``),
so they are not in the wheel (pyproject.toml).

Layer: the top, above ``plad.serve`` and ``plad.stages``; nothing else in ``plad`` imports it.
"""
