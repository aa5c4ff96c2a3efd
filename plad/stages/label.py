"""Stage ``label``: search labels for every real training shape of a domain (beyond the paper, issue 58).

A thin shell around :func:`plad.learn.labels.label_shapes`: reads ``label.<domain>``, searches the prepared
split's shapes in resumable chunks and writes ``data/labels/<domain>.npz`` and ``<domain>.json``
(:mod:`plad.layout`).
"""
from __future__ import annotations

import sys

from plad.learn.labels import LabelConfig
from plad.stages import StageContext, stage_main


def run_label(cfg: LabelConfig, ctx: StageContext = StageContext()) -> dict:
    from plad.learn.labels import label_shapes

    layout = ctx.layout
    return label_shapes(cfg, layout.prepared(cfg.domain), layout.labels_dir,
                        log=lambda line: print(line, file=sys.stderr, flush=True))


def main(argv: list[str] | None = None) -> int:
    return stage_main("label", LabelConfig, run_label, argv, __doc__.splitlines()[0])


if __name__ == "__main__":
    sys.exit(main())
