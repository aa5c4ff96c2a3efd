"""Search labels (plad.learn.labels) and the network taught by them (plad.learn.teach): exact, resumable."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch

from plad.config import ConfigError, build
from plad.data.files import DataError, load_prepared
from plad.domains import get_domain
from plad.domains.base import pad_programs
from plad.learn.labels import load_labels, order
from plad.learn.teach import TeachConfig, teach
from tests.labelled import label_project, sampled_project


def test_labels_are_exactly_what_their_programs_draw_and_a_killed_run_resumes(tmp_path):
    layout = sampled_project(tmp_path)
    domain = get_domain("csg2d")
    summary = label_project(layout, limit=5)                   # rounded up to whole chunks: 6 shapes
    labels = load_labels(layout.labels("csg2d"))
    assert summary["n"] == len(labels) == 6 and summary["chunks"] == 2 and summary["chunks_resumed"] == 0
    assert np.array_equal(labels.index, order(9)[:6])   # the labelling order's prefix
    assert summary["rescored_max_difference"] == 0.0
    targets = load_prepared(layout.prepared("csg2d"), "train")[labels.index]   # by position in the split
    execs = domain.execute(pad_programs(labels.programs))
    assert torch.equal(execs, torch.from_numpy(labels.executions))
    assert np.array_equal(domain.metric(execs, torch.from_numpy(targets)).numpy(), labels.values)
    meta = json.loads((layout.labels_dir / "csg2d.json").read_text())
    assert meta["mean"] == round(float(labels.values.mean()), 6) and meta["split_shapes"] == 9

    # a kill after the first chunk: the run again searches only the other one, with the same labels
    parts = layout.labels_dir / "csg2d.parts"
    (parts / "chunk_00001.npz").unlink()
    again = label_project(layout, limit=5)
    assert again["chunks_resumed"] == 1
    assert load_labels(layout.labels("csg2d")).programs == labels.programs
    # a larger limit reuses both chunks and searches the third
    more = label_project(layout, limit=None)
    assert more["chunks_resumed"] == 2 and more["n"] == 9
    assert load_labels(layout.labels("csg2d")).programs[:6] == labels.programs
    # other search settings are other work: the chunks are not reused
    other = label_project(layout, limit=5, search={"insertions": 2, "refine": {"rounds": 0}})
    assert other["chunks_resumed"] == 0


def test_label_config_errors_name_the_key(tmp_path):
    layout = sampled_project(tmp_path)
    with pytest.raises(ConfigError, match=r"label\.csg2d: workers"):
        label_project(layout, workers=0)
    with pytest.raises(ConfigError, match=r"label\.csg2d\.search"):
        label_project(layout, search={"no_such_key": 1})
    with pytest.raises(DataError, match="no labels"):
        load_labels(tmp_path / "missing.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(DataError, match="not a labels file"):
        load_labels(bad)


def _teach_cfg(init, **kw) -> TeachConfig:
    raw = {"domain": "csg2d", "init": str(init), "device": "cpu", "val_limit": 4, "val_beam": 2, "fit_shapes": 3,
           "fit_beam_wide": 2, "infer_batch": 8, "sources": {"st": 1.0, "lest": 1.0},
           "train": {"batch_size": 4, "steps_per_epoch": 2, "max_epochs": 2, "patience": 5}, **kw}
    return build(TeachConfig, raw, "teach.csg2d")


def test_teaching_records_fit_beside_validation_and_resumes(tmp_path, tiny_checkpoint):
    layout = sampled_project(tmp_path)
    label_project(layout)
    init = tiny_checkpoint(tmp_path / "init.pt")
    summary = teach(_teach_cfg(init), init, layout, log=lambda line: None)
    out = layout.finetune_dir("csg2d", "taught")
    with open(out / "history.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["unit"]) for r in rows] == [0, 1, 2]   # the start, then every epoch
    for r in rows:
        assert {"val", "fit", "fit_wide"} <= set(r) and all(np.isfinite(float(r[k])) for k in ("val", "fit"))
    assert rows[1]["train_loss"] != "" and summary["units"] == 2 and summary["labels"] == 9
    labels = load_labels(layout.labels("csg2d"))
    assert summary["fit_labels_mean"] == round(float(labels.values[[0, 4, 8]].mean()), 6)
    assert (out / "best.pt").exists() and json.loads((out / "summary.json").read_text())["key"] == "taught"
    assert json.loads(layout.finetune_summary("csg2d", "taught").read_text())["units"] == 2
    # run again with more epochs: it continues after epoch 2 (no epoch is trained twice)
    more = teach(_teach_cfg(init, train={"batch_size": 4, "steps_per_epoch": 2, "max_epochs": 3, "patience": 5}),
                 init, layout, log=lambda line: None)
    assert more["units"] == 3
    with open(out / "history.csv", newline="") as fh:
        assert [int(r["unit"]) for r in csv.DictReader(fh)] == [0, 1, 2, 3]


def _mark_start(history) -> None:
    """Put a sentinel in the starting row's validation metric of ``history``."""
    with open(history, newline="") as fh:
        rows = list(csv.DictReader(fh))
    rows[0]["val"] = "123.0"
    with open(history, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def _start_val(history) -> str:
    with open(history, newline="") as fh:
        return next(csv.DictReader(fh))["val"]


def test_a_history_is_continued_only_with_the_run_it_belongs_to(tmp_path, tiny_checkpoint):
    layout = sampled_project(tmp_path)
    label_project(layout)
    init = tiny_checkpoint(tmp_path / "init.pt")
    teach(_teach_cfg(init), init, layout, log=lambda line: None)
    history = layout.finetune_dir("csg2d", "taught") / "history.csv"
    _mark_start(history)
    # the same work with one more epoch resumes: its rows are kept
    more = {"batch_size": 4, "steps_per_epoch": 2, "max_epochs": 3, "patience": 5}
    assert teach(_teach_cfg(init, train=more), init, layout, log=lambda line: None)["units"] == 3
    assert _start_val(history) == "123.0"
    # other work (another seed) starts over: the old rows go, its own start is measured
    assert teach(_teach_cfg(init, seed=1), init, layout, log=lambda line: None)["units"] == 2
    with open(history, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["unit"]) for r in rows] == [0, 1, 2] and float(rows[0]["val"]) != 123.0


def test_the_start_is_its_network_not_the_name_init_gives_it(tmp_path, tiny_checkpoint):
    """The same network under another name (a path, or "search_seeded") resumes the run; another network does
    not."""
    import shutil

    layout = sampled_project(tmp_path)
    label_project(layout)
    init = tiny_checkpoint(tmp_path / "init.pt")
    teach(_teach_cfg(init), init, layout, log=lambda line: None)
    history = layout.finetune_dir("csg2d", "taught") / "history.csv"
    _mark_start(history)
    renamed = tmp_path / "elsewhere" / "start.pt"
    renamed.parent.mkdir()
    shutil.copyfile(init, renamed)
    more = {"batch_size": 4, "steps_per_epoch": 2, "max_epochs": 3, "patience": 5}
    assert teach(_teach_cfg(renamed, train=more), renamed, layout, log=lambda line: None)["units"] == 3
    assert _start_val(history) == "123.0"


def test_teach_starts_from_the_kept_search_seeded_network_never_the_shipped_model(tmp_path):
    from plad.shipped import ShipError, kept_checkpoint, search_seeded_checkpoint, sha256_file
    from plad.stages.teach import init_checkpoint

    for domain in ("csg2d", "csg3d", "shapeassembly"):
        path = init_checkpoint(build(TeachConfig, {"domain": domain, "init": "search_seeded"}, "teach"))
        assert path == search_seeded_checkpoint(domain) and path.name == "search_seeded.pt"
        # the kept taught network: a copy of a shipped one, indexed with the commit that shipped it
        kept = init_checkpoint(build(TeachConfig, {"domain": domain, "init": "taught"}, "teach"))
        assert kept == kept_checkpoint(domain, "taught") and kept.name == "taught.pt" and kept.parent.name == domain
        entry = json.loads((kept.parent.parent / "taught.json").read_text())["models"][domain]
        assert entry["sha256"] == sha256_file(kept)
        assert entry["shipped_as"].startswith(f"plad/shipped/{domain}/model.pt at ")
    with pytest.raises(ConfigError, match=r"teach\.csg3d\.init = shipped: the shipped model"):
        init_checkpoint(build(TeachConfig, {"domain": "csg3d", "init": "shipped"}, "teach"))
    # a damaged or missing copy is named, never trained from
    folder = tmp_path / "shipped"
    (folder / "csg3d").mkdir(parents=True)
    with pytest.raises(ShipError, match="search_seeded.json: missing"):
        search_seeded_checkpoint("csg3d", folder)
    index = {"models": {"csg3d": {"file": "csg3d/search_seeded.pt", "sha256": "0" * 64}}}
    (folder / "search_seeded.json").write_text(json.dumps(index))
    with pytest.raises(ShipError, match=r"csg3d/search_seeded\.pt: missing"):
        search_seeded_checkpoint("csg3d", folder)
    (folder / "csg3d" / "search_seeded.pt").write_bytes(b"not the network")
    with pytest.raises(ShipError, match="sha256 .* differs from 000000000000"):
        search_seeded_checkpoint("csg3d", folder)
    with pytest.raises(ShipError, match="no search-seeded network of csg2d"):
        search_seeded_checkpoint("csg2d", folder)
    with pytest.raises(ShipError, match=r"taught\.json: missing \(the index of the taught networks\)"):
        kept_checkpoint("csg3d", "taught", folder)


def test_teach_config_errors_name_the_key(tmp_path, tiny_checkpoint):
    layout = sampled_project(tmp_path)
    init = tiny_checkpoint(tmp_path / "init.pt")
    with pytest.raises(ConfigError, match=r"teach\.csg2d\.sources: unknown source"):
        teach(_teach_cfg(init, sources={"ws": 1.0}), init, layout)
    with pytest.raises(ConfigError, match=r"teach\.csg2d\.sources: weights"):
        teach(_teach_cfg(init, sources={"st": 0.0}), init, layout)
    with pytest.raises(DataError, match="no labels"):
        teach(_teach_cfg(init), init, layout)


def test_a_grown_start_begins_where_the_start_is_and_trains_the_larger_network(tmp_path, tiny_checkpoint):
    """teach.<domain>.grow: the start grown before the first step (the same function: the epoch-0 row equals the
    ungrown run's), the checkpoints carry the larger network, a rerun resumes it, and a size that would shrink
    is a config error naming the key."""
    from plad.model.checkpoint import load_model

    init = tiny_checkpoint(tmp_path / "init.pt")
    small, _ = load_model(init)
    wider = [2 * c for c in small.cfg.enc_channels]
    runs = {}
    for name, kw in (("plain", {}), ("grown", {"grow": {"enc_channels": wider, "n_layers": small.cfg.n_layers + 1}})):
        layout = sampled_project(tmp_path / name)
        label_project(layout)
        summary = teach(_teach_cfg(init, **kw), init, layout, log=lambda line: None)
        with open(layout.finetune_dir("csg2d", "taught") / "history.csv", newline="") as fh:
            runs[name] = (summary, list(csv.DictReader(fh)), layout)
    (plain, plain_rows, _), (grown, grown_rows, layout) = runs["plain"], runs["grown"]
    for key in ("val", "fit", "fit_wide"):
        assert float(grown_rows[0][key]) == pytest.approx(float(plain_rows[0][key]), abs=1e-6)
    assert "grow" not in plain and grown["grow"] == {"enc_channels": wider, "n_layers": small.cfg.n_layers + 1}
    best, _ = load_model(layout.finetune_dir("csg2d", "taught") / "best.pt")
    assert list(best.cfg.enc_channels) == wider and best.cfg.n_layers == small.cfg.n_layers + 1
    more = {"batch_size": 4, "steps_per_epoch": 2, "max_epochs": 3, "patience": 5}
    again = teach(_teach_cfg(init, train=more, grow={"enc_channels": wider, "n_layers": small.cfg.n_layers + 1}),
                  init, layout, log=lambda line: None)
    assert again["units"] == 3
    with pytest.raises(ConfigError, match=rf"teach\.csg2d\.grow: dim_ff {small.cfg.dim_ff - 1}: the network has"):
        teach(_teach_cfg(init, grow={"dim_ff": small.cfg.dim_ff - 1}), init, layout, log=lambda line: None)


def _digest(path) -> str:
    from plad.model.checkpoint import network_digest

    return network_digest(path)


def test_a_second_segment_grows_the_first_ones_best_and_a_finished_run_becomes_its_first(tmp_path, tiny_checkpoint):
    """teach.<domain>.then: the first segment in taught/first/ (a run made before ``then`` was asked for moves
    there untouched and is not trained again), the second from its best network, grown, in taught/ (the
    stage's network); one summary and history of both; the same work from scratch gives the same network."""
    from plad.model.checkpoint import load_model

    init = tiny_checkpoint(tmp_path / "init.pt")
    small, _ = load_model(init)
    then = {"grow": {"n_layers": small.cfg.n_layers + 1}, "max_epochs": 2}
    quiet = lambda line: None   # noqa: E731

    layout = sampled_project(tmp_path / "adopted")
    label_project(layout)
    teach(_teach_cfg(init), init, layout, log=quiet)
    out = layout.finetune_dir("csg2d", "taught")
    first_best = (out / "best.pt").read_bytes()
    first_history = (out / "history.csv").read_text()
    summary = teach(_teach_cfg(init, then=then), init, layout, log=quiet)
    assert (out / "first" / "best.pt").read_bytes() == first_best            # moved, not trained again
    assert (out / "first" / "history.csv").read_text() == first_history
    with open(out / "history.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["unit"]) for r in rows] == [0, 1, 2]
    first = json.loads((out / "first" / "summary.json").read_text())
    assert float(rows[0]["val"]) == pytest.approx(first["val"], abs=1e-9)    # the second starts at the first's best
    best, _ = load_model(out / "best.pt")
    assert best.cfg.n_layers == small.cfg.n_layers + 1
    assert summary["units"] == 4 and summary["first"]["units"] == 2 and summary["best_unit"] > 2
    assert summary["then"]["grow"] == {"n_layers": small.cfg.n_layers + 1} and summary["then"]["max_epochs"] == 2
    assert summary["then"]["start_network_sha256"] == _digest(out / "first" / "best.pt")
    assert summary["init_network_sha256"] == _digest(init) and summary["init"] == str(init)
    committed = json.loads(layout.finetune_summary("csg2d", "taught").read_text())
    seconds = [r["seconds"] for r in committed["history"]]
    assert len(seconds) == 4 and seconds == sorted(seconds) and committed["units"] == 4
    # a rerun finds both segments finished: nothing is trained again
    again = teach(_teach_cfg(init, then=then), init, layout, log=quiet)
    assert again["units"] == 4 and (out / "first" / "best.pt").read_bytes() == first_best

    fresh = sampled_project(tmp_path / "fresh")
    label_project(fresh)
    teach(_teach_cfg(init, then=then), init, fresh, log=quiet)
    fresh_out = fresh.finetune_dir("csg2d", "taught")
    assert _digest(fresh_out / "first" / "best.pt") == _digest(out / "first" / "best.pt")
    assert _digest(fresh_out / "best.pt") == _digest(out / "best.pt")
    # a size the second segment would shrink to is an error before any training
    shrink = sampled_project(tmp_path / "shrink")
    label_project(shrink)
    with pytest.raises(ConfigError, match=rf"teach\.csg2d\.then\.grow: dim_ff {small.cfg.dim_ff - 1}: the network"):
        teach(_teach_cfg(init, then={"grow": {"dim_ff": small.cfg.dim_ff - 1}}), init, shrink, log=quiet)
    assert not (shrink.finetune_dir("csg2d", "taught") / "first").exists()


def test_the_teach_stage_logs_both_segments_as_one_curve(tmp_path, tiny_checkpoint, monkeypatch):
    """The stage's MLflow run: the first segment's epochs 0..n, then the second's after them (its epoch 0, the
    first's best network again, left out)."""
    import mlflow

    from plad.model.checkpoint import load_model
    from plad.stages import StageContext
    from plad.stages.teach import tracked_teach

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.setenv("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    mlflow.set_tracking_uri(uri)
    layout = sampled_project(tmp_path / "project")
    label_project(layout)
    init = tiny_checkpoint(tmp_path / "init.pt")
    small_layers = load_model(init)[0].cfg.n_layers
    cfg = _teach_cfg(init, then={"grow": {"n_layers": small_layers + 1}, "max_epochs": 2})
    params = tmp_path / "project" / "params.yaml"
    params.write_text("profile: tests\n")
    try:
        summary = tracked_teach(cfg, StageContext(layout, params))
    finally:
        while mlflow.active_run() is not None:
            mlflow.end_run()
    run_id = json.loads((layout.finetune_dir("csg2d", "taught") / "mlflow_run.json").read_text())["run_id"]
    history = mlflow.MlflowClient().get_metric_history(run_id, "val")
    assert sorted(m.step for m in history) == [0, 1, 2, 3, 4] and summary["units"] == 4
    steps = {m.step: m.value for m in history}
    with open(layout.finetune_dir("csg2d", "taught") / "history.csv", newline="") as fh:
        second = list(csv.DictReader(fh))
    assert steps[3] == pytest.approx(float(second[1]["val"])) and steps[4] == pytest.approx(float(second[2]["val"]))
