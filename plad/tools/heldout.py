"""The shipped network on real shapes it never saw: the training shapes the labels left out (issue 58).

The taught networks learn from the search labels of the first ``n`` shapes of the training split's labelling
order (:func:`plad.learn.labels.order`; ``n`` is in ``data/labels/<domain>.json``), are selected on validation
shapes and shipped on the test set. The rest of the training split is neither trained nor selected on by a
network taught from the SP (``teach.<domain>.init: pretrained``, synthetic programs only; a start fine-tuned on
real training shapes, as ``search_seeded``, may have seen some of them, and the summary names the start): this
module takes ``--shapes`` of them, evenly spaced in the labelling order, and scores the shipped network alone
(beam 10) against the domain's floor (one primitive / one box per shape) on the same shapes.

Usage: ``python -m plad.tools.heldout DOMAIN [--shapes 300] [--out results/heldout/DOMAIN.json]``
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def held_out_index(n_split: int, labelled: int, shapes: int) -> np.ndarray:
    """Positions in the training split of ``shapes`` shapes the first ``labelled`` of the labelling order leave
    out, evenly spaced over the rest of that order (all of them if fewer)."""
    from plad.data.files import evenly_spaced_index
    from plad.learn.labels import order

    rest = order(n_split)[labelled:]
    return rest[evenly_spaced_index(len(rest), shapes)]


def measure(domain_name: str, shapes: int, layout_root: Path = Path("."), beam: int = 10) -> dict:
    """The shipped network (beam ``beam``) and the floor on ``shapes`` held-out training shapes -> a summary."""
    import torch

    from plad.data.files import load_prepared
    from plad.domains import get_domain
    from plad.eval.floor import evaluate_floor
    from plad.layout import Layout
    from plad.model.checkpoint import load_model
    from plad.model.decode import infer_batched
    from plad.provenance import stamp
    from plad.shipped import shipped_model

    started = time.monotonic()
    domain = get_domain(domain_name)
    layout = Layout(layout_root)
    labels = json.loads((layout.labels_dir / f"{domain_name}.json").read_text())
    train = load_prepared(layout.prepared(domain_name), "train")
    index = held_out_index(len(train), int(labels["n"]), shapes)
    targets = train[index]
    shipped = shipped_model(domain_name)
    if shipped is None:
        raise SystemExit(f"no shipped {domain_name} model")
    shipped.verify()
    model, _ = load_model(shipped.checkpoint, expect_domain=domain_name)
    model.eval()
    torch.set_num_threads(1)
    start = time.perf_counter()
    values, _, _ = infer_batched(model, domain, targets, beam, batch_size=50, desc="held out")
    seconds = time.perf_counter() - start
    floor, _ = evaluate_floor(domain, targets)
    net, box = float(np.mean(values)), float(np.mean(floor))
    summary_file = layout.finetune_summary(domain_name, "taught")
    start = json.loads(summary_file.read_text()).get("init") if summary_file.is_file() else None
    return {"domain": domain_name, "metric": domain.metric.name, "shapes": len(index),
            "split": "train, outside the labelled shapes", "labelled": int(labels["n"]),
            "model": shipped.info.get("method"), "teach_init": start,
            "model_sha256": shipped.info["checkpoint"]["sha256"],
            "network": {"beam": beam, "mean": round(net, 6), "s_per_shape": round(seconds / len(index), 5)},
            "floor": {"mean": round(box, 6)}, "network_minus_floor": round(net - box, 6),
            "better_per_shape": round(float(np.mean(domain.metric.better(torch.as_tensor(values),
                                                                        torch.as_tensor(floor)).numpy())), 4),
            "provenance": stamp({"domain": domain_name, "shapes": shapes, "beam": beam}, started)}


def main(argv: list[str] | None = None) -> None:
    from plad.fsutil import atomic_write_text

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("domain")
    parser.add_argument("--shapes", type=int, default=300)
    parser.add_argument("--out", default=None, help="also write the summary here (JSON)")
    args = parser.parse_args(argv)
    summary = measure(args.domain, args.shapes)
    text = json.dumps(summary, indent=1) + "\n"
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out, text)
    print(text, end="")


if __name__ == "__main__":
    main()
