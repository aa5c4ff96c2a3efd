"""Program rewriting and search, generic over domains.

Rewriters (each batched over many programs, never returning a worse program):
:mod:`.po` (parameter optimization by discrete coordinate descent),
:mod:`.prune` (SIRI's pruning rules), :mod:`.graft` (SIRI's code grafting) and
:mod:`.insert` (insertion of a primitive where the residual says it helps). :mod:`.driver` composes them:
:func:`refine` from given programs, :func:`search` from scratch (greedy, or by
:mod:`.beam` search over partial programs). A domain
takes part by returning a :class:`~plad.domains.space.RewriteSpace` from its
``rewrite`` member.
"""
from plad.rewrite.driver import EFFORTS, RefineConfig, Result, SearchConfig, refine, search, search_config

__all__ = ["EFFORTS", "RefineConfig", "Result", "SearchConfig", "refine", "search", "search_config"]
