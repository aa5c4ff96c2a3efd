"""A small project with search labels, shared by the tests of the labels, the teach stage and the token-kind
probe: prepared shapes drawn by sampled programs, labelled by a cheap search."""
from __future__ import annotations

import numpy as np

from plad.data.files import write_prepared
from plad.domains import get_domain
from plad.domains.base import pad_programs
from plad.layout import Layout
from plad.learn.labels import LabelConfig, label_shapes

#: a cheap search: few insertions, no refinement
SMALL = {"insertions": 3, "refine": {"rounds": 0}}


def sampled_project(root, domain_name: str = "csg2d", n: int = 9) -> Layout:
    """A layout root whose prepared shapes are executions of sampled programs (n train, 4 val)."""
    domain = get_domain(domain_name)
    rng = np.random.default_rng(11)
    split = {s: domain.execute(pad_programs(domain.sample(k, rng))).numpy() for s, k in (("train", n), ("val", 4))}
    layout = Layout(root)
    write_prepared(domain_name, domain.shape, split, layout.prepared(domain_name),
                   layout.prepared_summary(domain_name))
    return layout


def label_project(layout: Layout, **kw) -> dict:
    """The 2D labels of ``layout``'s training shapes by the cheap search, in chunks of 3 (``kw``: LabelConfig keys)."""
    cfg = LabelConfig(domain="csg2d", **{"chunk": 3, "search": SMALL, **kw})
    return label_shapes(cfg, layout.prepared("csg2d"), layout.labels_dir, log=lambda line: None)
