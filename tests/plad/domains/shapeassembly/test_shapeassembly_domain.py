"""shapeassembly domain: token grammar, exact voxels, sampler rule, dataset build, CLI."""
import time

import numpy as np
import pytest
import torch

from plad.data.datasets.partnet.voxels import voxelize_batch
from plad.domains import get_domain
from plad.domains.grammar import ProgramError
from plad.domains.shapeassembly import token_cuboids
from plad.serve.cli import main
from tests.conftest import require_shared

DOMAIN = get_domain("shapeassembly")
TABLE = DOMAIN.tokens


def test_references_only_to_declared_cuboids_other_than_the_mover():
    ok = "START 16 Cuboid 8 8 8 Attach bbox bot fpos_5_5 fpos_5_5 Cuboid 8 8 8 Attach cube0 top fpos_5_5 fpos_5_5 END"
    DOMAIN.parse(ok)
    for bad in ["START 16 Cuboid 8 8 8 Attach cube0 bot fpos_5_5 fpos_5_5 END",      # itself
                "START 16 Cuboid 8 8 8 Attach cube1 bot fpos_5_5 fpos_5_5 END",      # not declared yet
                "START 16 Cuboid 8 8 8 Reflect X END",                               # no move
                "START 16 Cuboid 8 8 8 Squeeze bbox bbox top fpos_5_5 Attach bbox top fpos_5_5 fpos_5_5 END",
                "START 16 END"]:                                                    # no part
        with pytest.raises(ProgramError):
            DOMAIN.parse(bad)


def test_at_most_ten_cuboids():
    part = " Cuboid 2 2 2 Squeeze bbox bbox top fpos_5_5"
    DOMAIN.parse("START 16" + part * 10 + " END")
    with pytest.raises(ProgramError):
        DOMAIN.parse("START 16" + part * 11 + " END")


def test_mask_follows_the_cuboid_count():
    ids = TABLE.encode("START 16 Cuboid 8 8 8 Attach bbox bot fpos_5_5 fpos_5_5 Cuboid 4 4 4 Attach".split())
    state = TABLE.initial_state(1)
    for t in ids:
        state = TABLE.advance(state, torch.tensor([t]))
    allowed = {TABLE.tokens[i].name for i in torch.nonzero(TABLE.mask(state)[0]).flatten().tolist()}
    assert allowed == {"bbox", "cube0"}


def test_slab_voxels_exact():
    # bbox 1 x 0.5 x 1; a 31/32 x 1/4 x 31/32 slab standing on the bbox bottom (y = -0.25)
    ids = DOMAIN.parse("START 16 Cuboid 31 8 31 Attach bbox bot fpos_5_5 fpos_5_5 END")
    grid = DOMAIN.execute(torch.tensor([ids]))[0].numpy()
    want = np.zeros((32, 32, 32), bool)
    want[:, 8:16, :] = True      # y in [-0.25, 0]; x, z within +-31/64 holds every voxel center
    assert np.array_equal(grid, want)


def test_reflected_leg_voxels_exact():
    text = ("START 16 Cuboid 31 4 31 Attach bbox top fpos_5_5 fpos_5_5 "
            "Cuboid 4 12 4 Attach cube0 top fpos_5_5 fpos_1_1 Reflect X END")
    cub = token_cuboids(DOMAIN.parse(text))
    assert cub.shape == (3, 15)
    # slab hangs from the bbox top: y in [0.125, 0.25]. The leg's top-center goes to the slab's
    # bottom at (0.1, 0, 0.1): x = z = -31/64 + 0.1 * 31/32 = -0.3875; the copy mirrors x.
    np.testing.assert_allclose(cub[:, 0:3], [[0, 0.1875, 0], [-0.3875, -0.0625, -0.3875],
                                             [0.3875, -0.0625, -0.3875]], atol=1e-6)
    np.testing.assert_allclose(cub[1:, 12:15], [[0.125, 0.375, 0.125]] * 2, atol=1e-6)
    grid = DOMAIN.execute(torch.tensor([DOMAIN.parse(text)]))[0].numpy()
    want = np.zeros((32, 32, 32), bool)
    want[:, 20:24, :] = True
    # leg x in [-0.45, -0.325] holds centers (i + .5)/32 - .5 for i = 2..5; y in [-0.25, 0.125]: 8..19
    want[2:6, 8:20, 2:6] = True
    want[26:30, 8:20, 2:6] = True
    assert np.array_equal(grid, want)


def test_executor_equals_the_full_language_on_the_same_statements():
    from plad.data.datasets.partnet.execute import execute_program
    from plad.data.datasets.partnet.lang import Block, Program
    from plad.data.datasets.partnet.voxels import voxelize
    from plad.domains.shapeassembly.tokens import to_statements

    for ids in DOMAIN.sample(50, np.random.default_rng(5)):
        prog = Program({"P": Block("P", to_statements(ids))}, "P")
        # the discretized variant names copies apart; without copies both namings agree
        if not any(TABLE.tokens[i].name in ("Reflect", "Translate") for i in ids):
            assert np.array_equal(execute_program(prog), token_cuboids(ids))
        grid = DOMAIN.execute(torch.tensor([ids]))[0].numpy()
        assert np.array_equal(grid, voxelize(token_cuboids(ids), normalized=True))


def test_10000_sampled_programs_satisfy_the_8_voxel_rule():
    start = time.perf_counter()
    programs = DOMAIN.sample(10000, np.random.default_rng(11))
    elapsed = time.perf_counter() - start
    assert len(programs) == 10000
    # independent check of the rule: voxelize each program's cuboids on its own
    fewest = []
    for chunk in range(0, len(programs), 1000):
        rows = programs[chunk:chunk + 1000]
        cubs = [token_cuboids(p) for p in rows]
        owner = torch.cat([torch.full((len(c),), i, dtype=torch.long) for i, c in enumerate(cubs)])
        _, unique = voxelize_batch(torch.from_numpy(np.concatenate(cubs)), owner, len(rows))
        for i in range(len(rows)):
            fewest.append(int(unique[owner == i].min()))
    assert min(fewest) >= 8
    parts = np.bincount([sum(TABLE.tokens[t].name == "Cuboid" for t in p) for p in programs], minlength=9)
    assert parts[:2].sum() == 0 and (parts[2:] > 1000).all()
    assert max(len(p) for p in programs) <= 100
    print(f"sampled 10000 programs in {elapsed:.1f} s")


def test_inside_sampler_keeps_every_part_in_the_bbox():
    sample = DOMAIN.samplers()["inside"]
    programs = sample(300, np.random.default_rng(3))
    assert len(programs) == 300 and max(len(p) for p in programs) <= 100
    heights = []
    for ids in programs:
        cubs = token_cuboids(ids)
        h = int(TABLE.tokens[ids[1]].name)
        heights.append(h)
        # independent of the sampler's check: the 8 corners of every cuboid, copies included
        centre, axes, dims = cubs[:, 0:3], cubs[:, 3:12].reshape(-1, 3, 3), cubs[:, 12:15]
        axes = axes / np.linalg.norm(axes, axis=2, keepdims=True)
        signs = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
        corners = centre[:, None, :] + np.einsum("ka,na,nab->nkb", signs, dims, axes)
        limit = np.array([0.5, h / 64, 0.5]) + 0.5 / 32 + 1e-5
        assert (np.abs(corners) <= limit).all(), DOMAIN.format(ids)
        # and the voxels: no occupied row above or below the bbox's
        grid = DOMAIN.execute(torch.tensor([ids]))[0].numpy()
        rows = np.nonzero(grid.any(axis=(0, 2)))[0]
        assert rows.max() - rows.min() + 1 <= h + 1
    cubs = [token_cuboids(p) for p in programs]
    owner = torch.cat([torch.full((len(c),), i, dtype=torch.long) for i, c in enumerate(cubs)])
    _, unique = voxelize_batch(torch.from_numpy(np.concatenate(cubs)), owner, len(programs))
    assert all(int(unique[owner == i].min()) >= 8 for i in range(len(programs)))
    # most bboxes full height, as most voxelized PartNet shapes are
    assert 0.55 < np.mean(np.array(heights) == 31) < 0.9
    # the paper's sampler leaves the bbox in almost every program
    outside = 0
    for ids in DOMAIN.sample(100, np.random.default_rng(3)):
        grid = DOMAIN.execute(torch.tensor([ids]))[0].numpy()
        rows = np.nonzero(grid.any(axis=(0, 2)))[0]
        outside += rows.max() - rows.min() + 1 > int(TABLE.tokens[ids[1]].name) + 1
    assert outside > 50


def test_dataset_build_end_to_end(tmp_path, fixtures_dir):
    from plad.data.datasets.partnet.dataset import build_partnet_dataset, load_split, unpack

    tar = require_shared("datasets/shapeassembly_partnet/partnet_programs.tar.gz")
    report = build_partnet_dataset(tar, tmp_path / "partnet_voxels.npz", limit=3)
    assert report["failures"] == [] and report["shapes"] == 9
    with np.load(tmp_path / "partnet_voxels.npz") as z:
        assert list(z["split"]) == ["train"] * 3 + ["val"] * 3 + ["test"] * 3
        # train starts with the smallest chair ids; val/test alternate over the sorted val ids
        assert list(z["categories"][:3]) == ["chair"] * 3
        assert z["voxels"].shape == (9, 4096) and z["voxels"].dtype == np.uint8
        grids = unpack(z["voxels"])
        ids = list(z["ids"])
    assert grids.any(axis=(1, 2, 3)).all()
    val = load_split("val", tmp_path)
    assert val.shape == (3, 32, 32, 32) and val.dtype == bool
    # the fixture's first chair program is the smallest chair id of the train split
    fixture = np.load(fixtures_dir / "shapeassembly_reference.npz")
    first = [i for i, c in enumerate(fixture["category"]) if c == "chair"]
    first.sort(key=lambda i: int(fixture["program_id"][i]))
    assert ids[0] == fixture["program_id"][first[0]]
    assert np.array_equal(grids[0], fixture["voxels"][first[0]])


def test_dataset_build_reports_failures(tmp_path):
    import io
    import tarfile

    from plad.data.datasets.partnet.dataset import build_partnet_dataset

    good = "Assembly Program_0 {\n\tbbox = Cuboid(1, 1, 1, True)\n\tcube0 = Cuboid(1, 1, 1, True)\n}\n"
    files = {"programs/chair/1.txt": good, "programs/chair/2.txt": good.replace("cube0 = Cuboid(1, 1, 1",
                                                                               "cube0 = Cuboid(1, -1, 1"),
             "splits/chair/train.txt": "1\n2\n3\n", "splits/chair/val.txt": "1\n"}
    files.update({f"splits/{c}/{s}.txt": "" for c in ("table", "storage") for s in ("train", "val")})
    tar_path = tmp_path / "p.tar.gz"
    with tarfile.open(tar_path, "w:gz") as tar:
        for name, text in files.items():
            data = text.encode()
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    report = build_partnet_dataset(tar_path, tmp_path / "out.npz")
    reasons = {f["program"]: f["reason"] for f in report["failures"]}
    assert set(reasons) == {"chair/2", "chair/3"}
    assert reasons["chair/2"].startswith("line 3: dimensions of cube0 must be positive")
    assert "no program file" in reasons["chair/3"]
    assert report["listed"] == {"train": 3, "val": 1, "test": 0} and report["shapes"] == 2


def test_target_data_missing_is_a_clear_data_error(tmp_path):
    from plad.data.files import DataError

    with pytest.raises(DataError, match="built by the prepare stage"):
        DOMAIN.target_data("val", tmp_path)


def test_cli_outputs_for_both_forms(tmp_path, capsys, fixtures_dir):
    fixture = np.load(fixtures_dir / "shapeassembly_reference.npz")
    program = tmp_path / "chair.txt"
    program.write_text(str(fixture["program_text"][0]))
    assert main(["execute", "shapeassembly", str(program), "-o", str(tmp_path / "v.npy")]) == 0
    grid = np.load(tmp_path / "v.npy")
    assert grid.dtype == bool and np.array_equal(grid, fixture["voxels"][0])
    for name in ("m.ply", "m.obj", "m.png"):
        assert main(["execute", "shapeassembly", str(program), "-o", str(tmp_path / name)]) == 0
        assert (tmp_path / name).stat().st_size > 0
    text = "START 16 Cuboid 31 8 31 Attach bbox bot fpos_5_5 fpos_5_5 END"
    assert main(["execute", "shapeassembly", text, "-o", str(tmp_path / "t.npy")]) == 0
    want = np.zeros((32, 32, 32), bool)
    want[:, 8:16, :] = True
    assert np.array_equal(np.load(tmp_path / "t.npy"), want)
    capsys.readouterr()
    bad = tmp_path / "bad.txt"
    bad.write_text("Assembly Program_0 {\n\tbbox = Cuboid(1, 1, 1, True)\n\treflect(cube3, X)\n}\n")
    assert main(["execute", "shapeassembly", str(bad), "-o", str(tmp_path / "x.npy")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "plad: error: invalid shapeassembly program: line 3: 'cube3' is not a cuboid of block " \
                  "Program_0 at this point"
    assert main(["execute", "shapeassembly", "START 16 Cuboid 8 8 8 Attach cube4", "-o", str(tmp_path / "x.npy")]) == 2
    assert main(["execute", "shapeassembly", str(program), "-o", str(tmp_path / "x.stl")]) == 2


def test_insertion_placements_equal_the_frozen_reference():
    """The insertion's attachment placements (distance and Attach tokens of every cuboid face, best first) equal
    those of the code before they were made fast (tests/reference/shapeassembly_placements_v0.py), float for
    float, for axis-aligned and rotated cuboids of every size."""
    from tests.reference.shapeassembly_placements_v0 import placements

    space = get_domain("shapeassembly").rewrite
    rng = np.random.default_rng(0)
    for _ in range(150):
        cuboids = []
        for k in range(int(rng.integers(1, 6))):
            axes = np.eye(3) if rng.random() < 0.6 else np.linalg.qr(rng.normal(size=(3, 3)))[0]
            cuboids.append(("bbox" if k == 0 else f"cube{k - 1}", rng.uniform(-1, 1, 3), axes,
                            rng.uniform(0.05, 1.2, 3)))
        dims, center = rng.uniform(0.05, 1.0, 3), rng.uniform(-1, 1, 3)
        assert space._placements(cuboids, dims, center) == placements(cuboids, dims, center)
