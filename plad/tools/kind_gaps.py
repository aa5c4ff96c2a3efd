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

from plad.domains.grammar import near_matrix
from plad.model.network import PLADNet

__all__ = ["kind_gaps", "labelled_batch", "main", "near_matrix"]


@torch.no_grad()
def kind_gaps(model: PLADNet, shapes: torch.Tensor, programs: torch.Tensor, lengths: torch.Tensor,
              kinds: Sequence[str], near: torch.Tensor | None = None) -> dict[str, dict[str, float]]:
    """Per kind of target token (``kinds[token id]``): its share of the tokens, mean nll, accuracy and
    prefix-swap gap (as :func:`plad.learn.diagnostics.prefix_gap`, the next row's prefix), eval mode (restored after);
    with ``near`` (:func:`near_matrix`), also the accuracy that counts a prediction one grid step off as right.

    The share-weighted nll is the loss of :meth:`PLADNet.loss`; a kind whose gap is ~0 is predicted from
    the program so far alone, whatever the shape.
    """
    if len(shapes) < 2:
        raise ValueError("kind_gaps needs at least two shapes")
    was_training = model.training
    model.eval()
    try:
        prefix = model.encode(shapes)
        logits, target, valid = model.teacher_forced(prefix, programs, lengths)
        nll = torch.nn.functional.cross_entropy(logits.flatten(0, 1), target.flatten(), reduction="none")
        nll, predicted = nll.view(target.shape), logits.argmax(-1)
        other, _, _ = model.token_nll(prefix.roll(1, dims=0), programs, lengths)
    finally:
        model.train(was_training)
    # the valid tokens only, flattened: (T,) each
    tokens, predicted = programs[valid], predicted[valid]
    nll, correct, gap = nll[valid], (predicted == tokens).float(), other[valid] - nll[valid]
    close = near.to(tokens.device)[tokens, predicted].float() if near is not None else None
    names = sorted(set(kinds))
    group = torch.tensor([names.index(k) for k in kinds], device=programs.device)[tokens]   # (T,) kind index
    out = {}
    for i, name in enumerate(names):
        sel = group == i
        if sel.any():
            out[name] = {"share": float(sel.float().mean()), "nll": float(nll[sel].mean()),
                         "accuracy": float(correct[sel].mean()), "gap": float(gap[sel].mean())}
            if close is not None:
                out[name]["near"] = float(close[sel].mean())
    return out


def labelled_batch(domain, layout, n: int, first: int = 0,
                   last: int | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(real shapes (n, *s), label programs (n, L), lengths (n,)) of ``n`` evenly spaced labelled training shapes,
    among the labels ``first:last`` of the labelling order (e.g. those a network was taught on, or the others)."""
    import numpy as np

    from plad.data.files import evenly_spaced_index, load_prepared
    from plad.domains.base import split_padding
    from plad.learn.labels import load_labels
    from plad.rewrite.pool import pad_programs

    labels = load_labels(layout.labels(domain.name))
    span = np.arange(len(labels))[first:last]
    if not len(span):
        from plad.data.files import DataError

        raise DataError(layout.labels(domain.name),
                        f"no labels in {first}:{'' if last is None else last} of its {len(labels)}")
    pick = span[evenly_spaced_index(len(span), min(n, len(span)))]
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
    ap.add_argument("--range", default=":", metavar="FIRST:LAST",
                    help="with --labels, only the labels FIRST:LAST of the labelling order (default: all)")
    args = ap.parse_args(argv)
    try:
        first, last = (int(v) if v else None for v in args.range.split(":"))
    except ValueError:
        ap.error(f"--range {args.range!r}: expected FIRST:LAST, e.g. 0:3072 or 3072:")

    def run() -> None:
        model, name = load_model(args.checkpoint)
        domain = get_domain(name)
        if args.labels:
            shapes, programs, lengths = labelled_batch(domain, Layout(args.root), args.programs, first or 0, last)
        else:
            rows = load_programs(Layout(args.root).synthetic(name))[args.split][: args.programs]
            shapes, programs, lengths = make_batch(domain, rows, torch.device("cpu"))
        tokens = domain.tokens.tokens
        table = kind_gaps(model, shapes.float(), programs, lengths, [t.kind for t in tokens], near_matrix(tokens))
        # near: the accuracy that counts a prediction one grid step off as right (numeric parameters)
        print(f"{'kind':12s} {'share':>6s} {'nll':>6s} {'acc':>6s} {'near':>6s} {'gap':>6s}")
        for kind, r in sorted(table.items(), key=lambda kv: -kv[1]["share"] * kv[1]["nll"]):
            print(f"{kind:12s} {r['share']:6.3f} {r['nll']:6.3f} {r['accuracy']:6.3f} {r['near']:6.3f} {r['gap']:6.3f}")

    return run_guarded("python -m plad.tools.kind_gaps", run)


__all__ = ["kind_gaps"]


if __name__ == "__main__":
    sys.exit(main())
