"""The results table lays out what each domain declares: display name, scale, digits and the paper's numbers."""
from plad.domains import domain_names, get_domain
from plad.eval.report import MethodResult, table_markdown


def test_table_shows_each_domain_as_it_declares_itself():
    results = {name: [MethodResult("sp", 0.5), MethodResult("lest_st", 0.25),
                      MethodResult("lest_st_per_round", None)] for name in domain_names()}
    text = table_markdown(results, ["sp", "lest_st"], {"lest_st": "lest_st_per_round"}, profile="cpu")
    lines = text.splitlines()
    header = next(line for line in lines if line.startswith("| method |"))
    row = next(line for line in lines if line.startswith("| SP |")).split("|")[2:-1]
    for i, name in enumerate(domain_names()):
        d = get_domain(name)
        assert f"{d.display_name}: {d.metric.name}" in header
        ours, paper = row[2 * i].strip(), row[2 * i + 1].strip()
        assert ours == f"{0.5 * d.display_scale:.{d.display_digits}f}"
        want = d.paper_table.get("sp")
        assert paper == ("—" if want is None else f"{want:.{d.display_digits}f}")
        # the supplement's per-round numbers, where the domain declares them
        block = lines[lines.index(f"{d.display_name}:") + 4].split("|")[1:-1]
        assert block[0].strip() == "LEST+ST" and block[1].strip() == f"{0.25 * d.display_scale:.{d.display_digits}f}"
        want = d.paper_per_round.get("lest_st")
        assert block[4].strip() == ("—" if want is None else f"{want:.{d.display_digits}f}")


def _write(path, data):
    import json

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))


def _prov(commit, wall, dirty=False):
    return {"commit": commit, "dirty": dirty, "params_hash": "0" * 16, "torch_threads": 1, "wall_seconds": wall,
            "machine": {"cpu": "x", "cores": 2, "gpu": None}}


def test_each_column_names_its_commit_and_marks_numbers_from_another_or_stopped_by_time(tmp_path):
    import json

    from plad.eval.report import column, columns_json, columns_markdown, from_files
    from plad.layout import Layout

    layout = Layout(tmp_path)
    a, b = "a" * 40, "b" * 40
    # 2D CSG: SP and LEST+ST at commit a; RL's evaluation at a, its fine-tuning at b and stopped by its budget
    _write(layout.pretrain_dir("csg2d") / "summary.json",
           {"stopped": "max_epochs", "stopped_by_time": False, "train_seconds": 600.0, "provenance": _prov(a, 30.0)})
    for key, commit, timed in [("lest_st", a, False), ("rl", b, True)]:
        _write(layout.finetune_summary("csg2d", key), {"units": 3, "stopped": "budget" if timed else "max_rounds",
                                                        **({"train_shapes": 3000} if timed else {}),
                                                        "stopped_by_time": timed, "train_seconds": 300.0,
                                                        "provenance": _prov(commit, 310.0)})
    for key in ["sp", "lest_st", "rl"]:
        _write(layout.eval_dir(key, "csg2d") / "metrics.json",
               {"test": {"mean": 1.5, "n": 3, "seconds": 1.0}, "stopped_by_time": False, "provenance": _prov(a, 20.0)})
    # the floor: written before provenance existed
    _write(layout.eval_dir("floor", "csg2d") / "metrics.json", {"test": {"mean": 3.0, "n": 3}})
    col = column("csg2d", ["sp", "rl", "lest_st"], layout)
    assert col.commit == a and not col.dirty
    assert col.others == {"rl": [b], "floor": ["not recorded"]}
    assert col.stopped_by_time == ["rl"] and col.stop_unknown == ["floor"]
    # pretraining 600 s (its loop's time, over the call's 30), two fine-tunings 310 s each, three evaluations
    # 20 s each: 1280 s from 6 of the 7 files (the floor's recorded none)
    assert col.wall_seconds == 1280.0 and (col.timed_files, col.files) == (6, 7)
    # the table marks RL's number (another commit, stopped by time), says so under it, and names the columns
    results = {"csg2d": from_files("csg2d", ["sp", "rl", "lest_st"], layout)}
    table = table_markdown(results, ["sp", "rl", "lest_st"], {}, columns={"csg2d": col})
    rows = {line.split("|")[1].strip(): line.split("|")[2].strip()
            for line in table.split("## Fine-tuning")[0].splitlines() if line.startswith("| ")}
    assert rows["SP"] == "1.500" and rows["LEST+ST"] == "1.500" and rows["RL"] == "1.500*†"
    assert "*: a number from another commit than its column's; †: stopped by time" in table
    # the training shapes of each run, where its summary records them (written before: none)
    assert "| RL | 5.0 min, 3, 3,000, † stopped by time |" in table
    assert "| LEST+ST | 5.0 min, 3, —, max_rounds |" in table
    section = columns_markdown({"csg2d": col}, ["sp", "rl", "lest_st"])
    cells = {line.split("|")[1].strip(): line.split("|")[2].strip() for line in section.splitlines()
             if line.startswith("| ")}
    assert cells["commit"] == "aaaaaaa"
    assert cells["* from another commit"] == "RL (bbbbbbb), floor (not recorded)"
    assert cells["stages' wall time"] == "21.3 min (6 of 7 files)"
    assert cells["stop"] == "† by time: RL; not recorded: floor"
    got = json.loads(json.dumps(columns_json({"csg2d": col})))["csg2d"]
    assert got["commit"] == a and got["other_commits"] == {"rl": [b], "floor": ["not recorded"]}
    assert got["numbers"]["rl"]["commits"] == {str(layout.eval_dir("rl", "csg2d") / "metrics.json"): a,
                                               str(layout.finetune_summary("csg2d", "rl")): b}


def test_a_column_of_one_commit_marks_nothing(tmp_path):
    from plad.eval.report import column, columns_markdown
    from plad.layout import Layout

    layout = Layout(tmp_path)
    _write(layout.pretrain_dir("csg3d") / "summary.json",
           {"stopped": "patience", "stopped_by_time": False, "provenance": _prov("c" * 40, 5.0, dirty=True)})
    _write(layout.eval_dir("sp", "csg3d") / "metrics.json",
           {"test": {"mean": 0.5, "n": 3}, "stopped_by_time": False, "provenance": _prov("c" * 40, 5.0)})
    col = column("csg3d", ["sp"], layout)
    assert col.others == {} and col.stopped_by_time == [] and col.dirty
    results = {"csg3d": [MethodResult("sp", 0.5)]}
    assert "*" not in table_markdown(results, ["sp"], {}, columns={"csg3d": col}).split("## Fine-tuning")[0]
    section = columns_markdown({"csg3d": col})
    assert "| commit | ccccccc (dirty) |" in section
    assert "| stop | work (every run ended on its epochs, rounds or patience) |" in section


def test_a_column_counts_each_file_once_and_a_continued_pretraining_its_own_call(tmp_path):
    """The search-seeded training's summary stands behind its evaluation, its refined evaluation and its beam
    sweep: counted once. A pretraining that continued a shipped checkpoint (4 segments) has train_seconds of
    all of them (5.7 h here): the column counts the call's own wall seconds."""
    from plad.eval.report import column
    from plad.layout import Layout

    layout = Layout(tmp_path)
    c = "c" * 40
    _write(layout.pretrain_dir("csg3d") / "summary.json",
           {"stopped": "max_epochs", "stopped_by_time": False, "train_seconds": 20650.9,
            "totals": {"segments": 4, "train_seconds": 20650.9}, "provenance": _prov(c, 12.0)})
    _write(layout.finetune_summary("csg3d", "lest_st_ws_search"),
           {"units": 38, "stopped": "max_rounds", "stopped_by_time": False, "train_seconds": 4200.0,
            "provenance": _prov(c, 4250.0)})
    keys = ["sp", "lest_st_ws_search", "lest_st_ws_search_refined", "lest_st_ws_search_beam1"]
    for key in keys:
        _write(layout.eval_dir(key, "csg3d") / "metrics.json",
               {"test": {"mean": 0.5, "n": 3}, "stopped_by_time": False, "provenance": _prov(c, 10.0)})
    col = column("csg3d", keys, layout)
    # 12 + 4250 + 4 evaluations of 10 s; 6 files, each once
    assert col.wall_seconds == 4302.0 and (col.timed_files, col.files) == (6, 6)
    assert col.records["lest_st_ws_search_beam1"].wall_seconds == 4260.0   # a number's own files, as before
