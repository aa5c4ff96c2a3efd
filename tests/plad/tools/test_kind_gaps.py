"""The loss and the prefix-swap gap by token kind (plad.tools.kind_gaps): they add up to the batch's, and a
network that ignores its input has no gap in any kind."""
from __future__ import annotations

import numpy as np
import torch

from plad.domains import get_domain
from plad.domains.base import pad_programs
from plad.learn.diagnostics import prefix_gap
from plad.tools.kind_gaps import kind_gaps, main, near_matrix
from tests.tiny import tiny_model

CSG2D = get_domain("csg2d")


def few_shapes_batch(n_programs=6, seed=0, batch_size=64, draw=100):
    """A batch drawn from a few distinct 1-primitive 2D programs: the program is decided by the shape alone."""
    from plad.domains.csg2d.sampler import sample_programs

    programs = pad_programs(sample_programs(CSG2D.executor, n_programs, np.random.default_rng(seed),
                                            max_primitives=1), pad=-1).clamp(min=0)
    lengths = torch.full((n_programs,), programs.shape[1])
    i = torch.randint(0, n_programs, (batch_size,), generator=torch.Generator().manual_seed(draw))
    return CSG2D.execute(programs)[i], programs[i], lengths[i]


def test_kind_gaps_split_the_loss_and_the_gap_by_token_kind():
    shapes, programs, lengths = few_shapes_batch()
    model = tiny_model("csg2d", 0, enc_init="kaiming", prefix_bos=True, dropout=0.0).eval()
    kinds = [t.kind for t in CSG2D.tokens.tokens]
    table = kind_gaps(model, shapes, programs, lengths, kinds)
    assert set(table) <= set(kinds) and len(table) >= 2
    assert abs(sum(r["share"] for r in table.values()) - 1) < 1e-9
    # weighted by share, the kinds give back the loss, the accuracy and the gap of the whole batch
    with torch.no_grad():
        loss, acc = model.loss(shapes, programs, lengths)
    assert abs(sum(r["share"] * r["nll"] for r in table.values()) - float(loss)) < 1e-4
    assert abs(sum(r["share"] * r["accuracy"] for r in table.values()) - float(acc)) < 1e-4
    gap = prefix_gap(model, shapes, programs, lengths)
    assert abs(sum(r["share"] * r["gap"] for r in table.values()) - gap) < 1e-4 and abs(gap) > 1e-4
    # an input-ignoring network: no kind depends on the shape
    with torch.no_grad():
        model.encoder.mlp[-1].weight.zero_()
    assert all(abs(r["gap"]) < 1e-5 for r in kind_gaps(model, shapes, programs, lengths, kinds).values())


def test_the_command_prints_a_row_per_kind_of_a_checkpoint(tmp_path, capsys, tiny_checkpoint):
    from plad.layout import Layout
    from plad.stages.synthesize import SynthesizeConfig, synthesize

    synthesize(SynthesizeConfig(domain="csg2d", train_programs=8, val_programs=8), Layout(tmp_path))
    checkpoint = tiny_checkpoint(tmp_path / "tiny.pt")
    assert main([str(checkpoint), "--programs", "8", "--root", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == ["kind", "share", "nll", "acc", "near", "gap"] and len(lines) >= 3
    assert abs(sum(float(line.split()[1]) for line in lines[1:]) - 1) < 0.01


def test_the_labels_batch_pairs_each_real_shape_with_its_label_and_the_command_reads_it(tmp_path, capsys,
                                                                                         tiny_checkpoint):
    from plad.data.files import load_prepared
    from plad.learn.labels import load_labels
    from plad.tools.kind_gaps import labelled_batch
    from tests.labelled import label_project, sampled_project

    layout = sampled_project(tmp_path)      # 9 training shapes drawn by sampled programs, all labelled
    label_project(layout)
    labels = load_labels(layout.labels("csg2d"))
    shapes, programs, lengths = labelled_batch(CSG2D, layout, 3)
    # evenly spaced over the 9 labels: 0, 4, 8 (the teach stage's fit sample), each with its own real shape
    pick = [0, 4, 8]
    real = load_prepared(layout.prepared("csg2d"), "train")
    assert torch.equal(shapes, torch.from_numpy(real[labels.index[pick]]))
    assert [programs[i, :lengths[i]].tolist() for i in range(3)] == [labels.programs[i] for i in pick]
    # a range of the labelling order: evenly spaced among labels 3..8
    shapes, programs, lengths = labelled_batch(CSG2D, layout, 2, first=3)
    assert torch.equal(shapes, torch.from_numpy(real[labels.index[[3, 8]]]))
    checkpoint = tiny_checkpoint(tmp_path / "tiny.pt")
    assert main([str(checkpoint), "--labels", "--range", "20:", "--root", str(tmp_path)]) == 1
    capsys.readouterr()
    assert main([str(checkpoint), "--labels", "--programs", "3", "--root", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == ["kind", "share", "nll", "acc", "near", "gap"]
    assert abs(sum(float(line.split()[1]) for line in lines[1:]) - 1) < 0.01


def test_near_counts_one_grid_step_in_every_numeric_parameter_and_nothing_else():
    csg3d, shapeassembly = get_domain("csg3d").tokens, get_domain("shapeassembly").tokens
    near = near_matrix(csg3d.tokens)
    i = csg3d.index
    assert near[i("4"), i("3")] and near[i("4"), i("5")] and near[i("4"), i("4")] and not near[i("4"), i("6")]
    assert not near[i("cuboid"), i("ellipsoid")] and not near[i("union"), i("diff")]
    assert torch.equal(near, near.T)
    near = near_matrix(shapeassembly.tokens)
    j = shapeassembly.index
    assert near[j("fpos_5_5"), j("fpos_4_6")] and not near[j("fpos_5_5"), j("fpos_5_7")]
    assert not near[j("fpos_5_5"), j("5")]                          # another kind
    # 2D: the primitive's type must match, position and size within one step each
    tokens = CSG2D.tokens.tokens
    near = near_matrix(tokens)
    by = {t.params: n for n, t in enumerate(tokens)}
    c = [p for p in by if p[:1] == ("c",)][0]
    step = sorted({p[1] for p in by if p[:1] == ("c",)})
    nxt = ("c", step[step.index(c[1]) + 1], c[2], c[3])
    assert near[by[c], by[nxt]] and not near[by[c], by[("s", *c[1:])]]


def test_near_accuracy_is_at_least_the_accuracy_and_equal_for_kinds_without_numbers():
    shapes, programs, lengths = few_shapes_batch()
    model = tiny_model("csg2d", 0, enc_init="kaiming", prefix_bos=True, dropout=0.0).eval()
    tokens = CSG2D.tokens.tokens
    table = kind_gaps(model, shapes, programs, lengths, [t.kind for t in tokens], near_matrix(tokens))
    assert all(r["near"] >= r["accuracy"] for r in table.values())
    for kind, r in table.items():
        if not any(t.params and t.kind == kind and isinstance(t.params[-1], int) for t in tokens):
            assert r["near"] == r["accuracy"]
