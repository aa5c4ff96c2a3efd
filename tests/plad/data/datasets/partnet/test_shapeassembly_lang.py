"""ShapeAssembly full language: fixture reproduction, voxels, parse errors, grow search, mesh/PNG."""
import numpy as np
import pytest

from plad.data.datasets.partnet.execute import BlockState, Cuboid, _nearest_pair, nearest_pair_brute, run_text
from plad.data.datasets.partnet.lang import SAParseError, parse_program
from plad.data.datasets.partnet.voxels import normalization, voxelize
from plad.domains.grammar import ProgramError


@pytest.fixture(scope="module")
def fixture(fixtures_dir):
    return np.load(fixtures_dir / "shapeassembly_reference.npz")


@pytest.fixture(scope="module")
def executed(fixture):
    return [run_text(str(t)) for t in fixture["program_text"]]


def test_fixture_cuboids_reproduced(fixture, executed):
    assert len(executed) == 120
    worst = 0.0
    for i, out in enumerate(executed):
        o, n = fixture["cuboid_offset"][i], fixture["n_cuboids"][i]
        assert out.shape == (n, 15), (i, fixture["program_id"][i])
        worst = max(worst, float(np.abs(out - fixture["cuboids"][o:o + n]).max()))
    assert worst < 1e-4, worst


def test_fixture_voxels_reproduced(fixture, executed):
    flips = plain_flips = 0
    for i, out in enumerate(executed):
        center, scale = normalization(out)
        assert np.abs(center - fixture["norm_center"][i]).max() < 1e-5
        assert abs(scale - fixture["norm_scale"][i]) < 1e-5
        grid = voxelize(out)
        assert grid.shape == (32, 32, 32) and grid.dtype == bool
        flips += int((grid != fixture["voxels"][i]).sum())
        plain_flips += int((voxelize(out, min_half=0) != fixture["voxels_plain"][i]).sum())
    # a handful of boundary flips would be tolerable (float32 knife edges); this implementation has none
    assert flips <= 5 and plain_flips <= 5, (flips, plain_flips)


CHAIR = """Assembly Program_0 {
\tbbox = Cuboid(1.0, 1.0, 1.0, True)
\tcube0 = Cuboid(1.0, 0.25, 1.0, True)
\tcube1 = Cuboid(0.25, 0.5, 0.25, True)
\tattach(cube0, bbox, 0.5, 1.0, 0.5, 0.5, 1.0, 0.5)
\tsqueeze(cube1, bbox, cube0, bot, 0.125, 0.125)
\treflect(cube1, X)
}
"""


def test_hand_program_exact_cuboids_and_voxels():
    out = run_text(CHAIR)
    # top slab hanging from the bbox top; a leg squeezed below it at the (-x, -z) corner; its mirror.
    # The leg is aligned and declared 0.5 high: standing on the bbox bottom it leaves a gap of 0.25
    # (more than 5% of the larger part) below the slab, so the grow step stretches it to 0.75.
    np.testing.assert_allclose(out[:, 0:3], [[0, 0.375, 0], [-0.375, -0.125, -0.375], [0.375, -0.125, -0.375]],
                               atol=1e-6)
    np.testing.assert_allclose(out[:, 12:15], [[1, 0.25, 1], [0.25, 0.75, 0.25], [0.25, 0.75, 0.25]], atol=1e-6)
    np.testing.assert_allclose(out[:, 3:12], np.tile(np.eye(3).reshape(-1), (3, 1)), atol=1e-6)
    grid = voxelize(out)
    # shape spans 1 x 1 x 1: slab = y in [0.25, 0.5] -> layers 24..31; legs 8 x 24 x 8 voxels
    want = np.zeros((32, 32, 32), bool)
    want[:, 24:, :] = True
    want[0:8, 0:24, 0:8] = True
    want[24:32, 0:24, 0:8] = True
    assert np.array_equal(grid, want)


@pytest.mark.parametrize("text, line, words", [
    ("Assembly Program_0 {\n\tcube0 = Cuboid(1, 1, 1, True)\n}\n", 2, "must declare bbox"),
    ("Assembly Program_0 {\n\tbbox = Cuboid(1, 1, 1, True)\n\tattach(cube0, bbox, 0, 0, 0, 0, 0, 0)\n}\n",
     3, "'cube0' is not a cuboid"),
    ("Assembly Program_0 {\n\tbbox = Cuboid(1, 1, 1, True)\n\tcube0 = Cuboid(1, x, 1, True)\n}\n", 3,
     "must be a number"),
    ("Assembly Program_0 {\n\tbbox = Cuboid(1, 1, 1, True)\n\tcube0 = Cuboid(1, 1, 1, True)\n"
     "\tattach(cube0, bbox, 0, 0, 0, 0, 0)\n}\n", 4, "attach expects 8 arguments, got 7"),
    ("Assembly Program_0 {\n\tbbox = Cuboid(1, 1, 1, True)\n\tcube0 = Cuboid(1, 1, 1, True)\n"
     "\tsqueeze(cube0, bbox, bbox, up, 0.5, 0.5)\n}\n", 4, "squeeze face must be one of"),
    ("Assembly Program_0 {\n\tbbox = Cuboid(1, 1, 1, True)\n\tcube0 = Cuboid(1, 1, 1, True)\n"
     "\treflect(cube0, W)\n}\n", 4, "axis must be X, Y or Z"),
    ("Assembly Program_0 {\n\tbbox = Cuboid(1, 1, 1, True)\n\tcube0 = Cuboid(1, 1, 1, True)\n"
     "\ttranslate(cube0, X, 0, 0.5)\n}\n", 4, "count must be from 1 to 100"),
    # values outside the language's range (issue 30: numpy warnings and an empty grid before)
    ("Assembly Program_0 {\n\tbbox = Cuboid(1e300, 1, 1, True)\n}\n", 2,
     "l of bbox must be in [0.001, 1000] (the language's range), got 1e300"),
    ("Assembly Program_0 {\n\tbbox = Cuboid(1, 1, 1, True)\n\tcube0 = Cuboid(1, 1e-300, 1, True)\n}\n", 3,
     "h of cube0 must be in [0.001, 1000]"),
    ("Assembly Program_0 {\n\tbbox = Cuboid(1, 1, 1, True)\n\tcube0 = Cuboid(1, 1, 1, True)\n"
     "\tattach(cube0, bbox, 0, 0, 0, 0, 1e9, 0)\n}\n", 4, "attach coordinate 5 must be in [0, 1]"),
    ("Assembly Program_0 {\n\tbbox = Cuboid(1, 1, 1, True)\n\tcube0 = Cuboid(1, 1, 1, True)\n"
     "\ttranslate(cube0, X, 1000000000, 0.5)\n}\n", 4, "count must be from 1 to 100, got 1000000000"),
    ("Assembly Program_0 {\n\tbbox = Cuboid(1, 1, 1, True)\n\tcube0 = Cuboid(1, 1, 1, True)\n"
     "\ttranslate(cube0, X, 2, 5)\n}\n", 4, "translate distance must be in [-1, 1]"),
    ("Assembly Program_0 {\n\tbbox = Cuboid(1, 1, 1, True)\n\tProgram_1 = Cuboid(1, 1, 1, True)\n}\n", 3,
     "has no 'Assembly Program_1 {' block"),
    ("Assembly Program_0 {\n\tbbox = Cuboid(1, 1, 1, True)\n\tcube0 = Cuboid(1, 1, 1, True)\n", 3,
     "is not closed"),
    ("Assembly Program_0 {\n\tbbox = Cuboid(1, 1, 1, True)\n\tfoo bar\n}\n", 3, "cannot read"),
    ("Assembly Program_0 {\n\tbbox = Cuboid(1, 1, 1, Maybe)\n}\n", 2, "must be True or False"),
    ("Assembly Program_0 {\n\tbbox = Cuboid(1, 1, 1, True)\n\tProgram_1 = Cuboid(1, 1, 1, True)\n}\n"
     "Assembly Program_1 {\n\tbbox = Cuboid(1, 1, 1, True)\n\tProgram_1 = Cuboid(1, 1, 1, True)\n}\n", 7,
     "contains itself"),
])
def test_parse_errors_name_the_line(text, line, words):
    with pytest.raises(SAParseError) as info:
        parse_program(text)
    message = str(info.value)
    assert isinstance(info.value, ProgramError)
    assert message.startswith(f"line {line}: ") and words in message and "\n" not in message


def test_copies_can_be_referenced_by_their_computed_names():
    text = CHAIR.replace("}\n", "\tattach(cube2, bbox, 0.5, 0.0, 0.5, 0.9, 0.0, 0.1)\n}\n")
    assert run_text(text).shape == (3, 15)  # cube2 is the reflect copy: legal reference


def _random_cuboid(rng, name, aligned):
    c = Cuboid(name, rng.uniform(0.05, 1.0, 3), aligned)
    c.pos = rng.uniform(-1, 1, 3).astype(np.float32)
    if not aligned:
        q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
        c.axes = (q * np.sign(np.linalg.det(q))).astype(np.float32)
    return c


def test_bracketing_nearest_search_equals_exhaustive_search():
    rng = np.random.default_rng(0)
    for trial in range(200):
        a = _random_cuboid(rng, "a", True)
        b = _random_cuboid(rng, "b", trial % 2 == 0)
        if trial % 4 == 1:   # exact ties: same dims, aligned, shifted along one axis
            b = Cuboid("b", a.dims, True)
            b.pos = a.pos + np.float32([0, a.dims[1] * 1.5, 0])
        got, want = _nearest_pair(a, b), nearest_pair_brute(a, b)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])


def test_execution_state_is_float32():
    state = BlockState((1, 1, 1))
    state.run(parse_program(CHAIR).blocks["Program_0"].stmts)
    assert all(c.pos.dtype == np.float32 and c.dims.dtype == np.float32 for c in state.cuboids.values())


def test_mesh_and_views_files(tmp_path):
    import open3d as o3d
    from PIL import Image

    from plad.domains.shapeassembly.export import mesh_arrays, save_mesh, save_views

    out = run_text(CHAIR)
    verts, faces = mesh_arrays(out)
    tri = verts[faces]
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6
    assert volume == pytest.approx(0.25 + 2 * 0.25 * 0.75 * 0.25)  # outward-facing triangles
    for suffix in (".ply", ".obj"):
        save_mesh(out, tmp_path / f"m{suffix}")
        mesh = o3d.io.read_triangle_mesh(str(tmp_path / f"m{suffix}"))
        assert len(mesh.vertices) == 24 and len(mesh.triangles) == 36
    save_views(out, tmp_path / "v.png")
    with Image.open(tmp_path / "v.png") as image:
        assert image.size[0] > image.size[1] > 100
