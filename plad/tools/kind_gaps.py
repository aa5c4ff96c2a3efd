"""Which parts of a program does the network read from the shape? The loss and the prefix-swap gap
(:func:`plad.learn.diagnostics.prefix_gap`) split by the kind of the target token.

``python -m plad.tools.kind_gaps CHECKPOINT`` prints :func:`kind_gaps` for the synthetic validation programs of
the checkpoint's domain (docs/pretraining-probes.md, section 4); with ``--labels``, for the search labels of
real training shapes (``data/labels/<domain>.npz`` beside their prepared shapes, evenly spaced as the teach
stage's fit sample): which parts of the labels a taught network fails to fit (docs/teaching.md).
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

import torch

from plad.model.network import PLADNet


@torch.no_grad()
def kind_gaps(model: PLADNet, shapes: torch.Tensor, programs: torch.Tensor, lengths: torch.Tensor,
              kinds: Sequence[str]) -> dict[str, dict[str, float]]:
    """Per kind of target token (``kinds[token id]``): its share of the tokens, mean nll, accuracy and
    prefix-swap gap (as :func:`plad.learn.diagnostics.prefix_gap`, the next row's prefix), eval mode (restored after).

    The share-weighted nll is the loss of :meth:`PLADNet.loss`; a kind whose gap is ~0 is predicted from
    the program so far alone, whatever the shape.
    """
    if len(shapes) < 2:
        raise ValueError("kind_gaps needs at least two shapes")
    was_training = model.training
    model.eval()
    try:
        prefix = model.encode(shapes)
        nll, correct, valid = model.token_nll(prefix, programs, lengths)
        other, _, _ = model.token_nll(prefix.roll(1, dims=0), programs, lengths)
    finally:
        model.train(was_training)
    # the valid tokens only, flattened: (T,) each
    nll, correct, gap, tokens = nll[valid], correct[valid].float(), other[valid] - nll[valid], programs[valid]
    names = sorted(set(kinds))
    group = torch.tensor([names.index(k) for k in kinds], device=programs.device)[tokens]   # (T,) kind index
    out = {}
    for i, name in enumerate(names):
        sel = group == i
        if sel.any():
            out[name] = {"share": float(sel.float().mean()), "nll": float(nll[sel].mean()),
                         "accuracy": float(correct[sel].mean()), "gap": float(gap[sel].mean())}
    return out


def labelled_batch(domain, layout, n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(real shapes (n, *s), label programs (n, L), lengths (n,)) of ``n`` evenly spaced labelled training shapes."""
    import numpy as np

    from plad.data.files import evenly_spaced_index, load_prepared
    from plad.domains.base import split_padding
    from plad.learn.labels import load_labels
    from plad.rewrite.pool import pad_programs

    labels = load_labels(layout.labels(domain.name))
    pick = evenly_spaced_index(len(labels), min(n, len(labels)))
    real = load_prepared(layout.prepared(domain.name), "train")[labels.index[pick]]
    programs = pad_programs([labels.programs[i] for i in pick], domain.tokens.max_len)
    tokens, lengths = split_padding(torch.from_numpy(np.asarray(programs, dtype=np.int64)))
    return torch.from_numpy(np.asarray(real)), tokens, lengths


def main(argv: list[str] | None = None) -> int:
    """Print :func:`kind_gaps` of a checkpoint on its domain's synthetic programs."""
    from plad.domains import get_domain
    from plad.errors import run_guarded
    from plad.layout import Layout
    from plad.learn.synthetic import load_programs, make_batch
    from plad.model.checkpoint import load_model

    ap = argparse.ArgumentParser(prog="python -m plad.tools.kind_gaps", description=main.__doc__)
    ap.add_argument("checkpoint")
    ap.add_argument("--split", default="val", choices=("train", "val"))
    ap.add_argument("--programs", type=int, default=256, help="the first N programs of the split")
    ap.add_argument("--root", default=".", help="project root holding data/synthetic (default: .)")
    ap.add_argument("--labels", action="store_true",
                    help="the search labels of N evenly spaced labelled real training shapes (data/labels, "
                         "data/prepared) instead of synthetic programs")
    args = ap.parse_args(argv)

    def run() -> None:
        model, name = load_model(args.checkpoint)
        domain = get_domain(name)
        if args.labels:
            shapes, programs, lengths = labelled_batch(domain, Layout(args.root), args.programs)
        else:
            rows = load_programs(Layout(args.root).synthetic(name))[args.split][: args.programs]
            shapes, programs, lengths = make_batch(domain, rows, torch.device("cpu"))
        table = kind_gaps(model, shapes.float(), programs, lengths, [t.kind for t in domain.tokens.tokens])
        print(f"{'kind':12s} {'share':>6s} {'nll':>6s} {'acc':>6s} {'gap':>6s}")
        for kind, r in sorted(table.items(), key=lambda kv: -kv[1]["share"] * kv[1]["nll"]):
            print(f"{kind:12s} {r['share']:6.3f} {r['nll']:6.3f} {r['accuracy']:6.3f} {r['gap']:6.3f}")

    return run_guarded("python -m plad.tools.kind_gaps", run)


__all__ = ["kind_gaps"]


if __name__ == "__main__":
    sys.exit(main())
