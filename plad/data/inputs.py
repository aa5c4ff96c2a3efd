"""The user's own shapes: images, arrays and meshes turned into a domain's target shapes.

A bad file never stops the others: :func:`read_inputs` returns one
:class:`Item` per shape, with ``error`` set (a one-line reason) instead of
raising, and ``notes`` for what was done to a file that needed help.

2D domains (a canvas of ``domain.shape``, e.g. 64 x 64):

* images (``.png``, ``.jpg``, ``.bmp``, ``.gif``, ``.tif``, ``.webp``): with a
  varying alpha channel, the opaque pixels are the shape; otherwise the
  grayscale image is split at Otsu's threshold and the shape is the side that
  covers less of the image border (black on white and white on black both
  work). An image of exactly the canvas size is used as it is. Any other size
  is cropped to the shape's bounding box, scaled (aspect kept) so that its
  longer side is :data:`FIT_2D` pixels (the median of the CAD shapes) and
  centered on the canvas.
* ``.npy`` arrays: one (H, W) array, fitted like an image when it is not the
  canvas's size, or a batch (N, *canvas*) of canvas-sized arrays; nonzero is
  inside. Any other array (e.g. a 32^3 voxel grid) is refused.

3D domains (a voxel grid of ``domain.shape``, e.g. 32^3 indexed [x, y, z], y up):

* meshes (``.obj``, ``.ply``, ``.off``, ``.stl``, read with open3d), normalized
  as the real training shapes: centered on their bounding box, the longest
  side spanning the grid. A watertight mesh is voxelized by whether each voxel
  center is inside it, plus a layer of voxels along parts too thin for any
  center to fall inside them (as the training data keeps thin parts). A mesh
  that is not watertight is voxelized by its surface (voxel centers within
  half a voxel of it), and the space that surface encloses is filled, with a
  note saying so.
* ``.npy`` arrays of exactly the grid's shape, or a batch of them.

The same rules at the edge for every command (``plad score``, ``infer``,
``refine``, ``search``; :func:`read_shapes` and :func:`read_inputs`):

* a file is at most :data:`MAX_FILE_BYTES` (256 MiB), an image at most
  :data:`MAX_PIXELS` (25 million pixels, e.g. 5000 x 5000; larger images, and
  PIL's decompression bombs, are refused before they are decoded);
* a ``.npy`` must hold a numeric or bool array without NaN or infinite values;
* the array's dimensions must be the domain's (one shape or a batch);
* **empty shapes**, in every domain: an empty *target* (nothing inside) is
  refused, since no metric can say how close a program comes to nothing; an
  input that fills the whole grid is refused likewise. An empty *prediction*
  (``plad score --pred``) is allowed and scored by the domain's metric.
"""
from __future__ import annotations

import re
import warnings
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError
from scipy import ndimage
from skimage.filters import threshold_otsu

from plad.errors import BadInput, one_line

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".gif", ".tif", ".tiff", ".webp")
MESH_SUFFIXES = (".obj", ".ply", ".off", ".stl")
#: longer side, in pixels, of a fitted 2D shape: the median over the CAD shapes' bounding boxes
FIT_2D = 44
#: the largest input file read (bytes)
MAX_FILE_BYTES = 256 * 2 ** 20
#: the largest image decoded (pixels); PIL refuses larger ones as decompression bombs from here on
MAX_PIXELS = 25_000_000
Image.MAX_IMAGE_PIXELS = MAX_PIXELS


class InputError(BadInput, ValueError):
    """A user's file cannot be used; the message is one line (without the file name)."""


@dataclass
class Item:
    """One input shape: where it came from and the target shape, or why there is none."""
    name: str                       # output file stem
    source: Path
    shape: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)
    error: str | None = None


def supported_suffixes(shape: tuple[int, ...]) -> tuple[str, ...]:
    return (*IMAGE_SUFFIXES, ".npy") if len(shape) == 2 else (*MESH_SUFFIXES, ".npy")


# ---- 2D -----------------------------------------------------------------------------------------
def check_file(path: Path) -> None:
    """The rules every input file meets before it is read: it exists, is a file, and is not too large."""
    try:
        size = path.stat().st_size
    except OSError:
        raise InputError("no such file") from None
    if not path.is_file():
        raise InputError("not a file")
    if size > MAX_FILE_BYTES:
        raise InputError(f"the file is {size / 2 ** 20:.0f} MiB, more than the limit of "
                         f"{MAX_FILE_BYTES // 2 ** 20} MiB")


def open_image(path: Path, mode: str) -> np.ndarray:
    """The image's pixels converted to PIL ``mode``; too large or unreadable images are an :class:`InputError`."""
    check_file(path)
    try:
        with warnings.catch_warnings():   # PIL warns about what is refused here anyway
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            image = Image.open(path)      # reads the header only: the size is known before decoding
        with image:
            w, h = image.size
            if w * h > MAX_PIXELS:
                raise InputError(f"the image is {w}x{h} pixels, more than the limit of {MAX_PIXELS:,} pixels")
            image.load()
            return np.asarray(image.convert(mode))
    except InputError:
        raise
    except Image.DecompressionBombError as err:   # PIL's own check at open: over twice the limit
        found = re.search(r"\((\d+) pixels\)", str(err))
        size = f"has {int(found.group(1)):,} pixels" if found else "is too large"
        raise InputError(f"the image {size}, more than the limit of {MAX_PIXELS:,} pixels") from None
    except (UnidentifiedImageError, OSError, ValueError, EOFError) as err:
        raise InputError(f"not a readable image ({err.__class__.__name__})") from None


def binarize_image(path: Path) -> np.ndarray:
    """Foreground mask (H, W) of an image file by the module's rule."""
    rgba = open_image(path, "RGBA")
    alpha = rgba[..., 3]
    if alpha.min() < 128 <= alpha.max():
        return alpha >= 128
    gray = rgba[..., :3].astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    if gray.max() - gray.min() < 1e-9:
        raise InputError("the image is a single color: there is no shape in it")
    dark = gray <= threshold_otsu(gray)
    border = np.concatenate([dark[0], dark[-1], dark[:, 0], dark[:, -1]])
    return dark if border.mean() <= 0.5 else ~dark


def fit_canvas(mask: np.ndarray, canvas: tuple[int, int], longer: int = FIT_2D) -> np.ndarray:
    """Crop ``mask`` to its shape, scale the longer side to ``longer`` pixels, center on ``canvas``."""
    rows, cols = np.nonzero(mask)
    if len(rows) == 0:
        raise InputError("the shape is empty")
    crop = mask[rows.min():rows.max() + 1, cols.min():cols.max() + 1]
    h, w = crop.shape
    scale = longer / max(h, w)
    nh, nw = max(1, round(h * scale)), max(1, round(w * scale))
    # box filter on the coverage, then half coverage is inside: area-faithful in both directions
    small = np.asarray(Image.fromarray(crop.astype(np.float32)).resize((nw, nh), Image.Resampling.BOX)) >= 0.5
    out = np.zeros(canvas, dtype=bool)
    top, left = (canvas[0] - nh) // 2, (canvas[1] - nw) // 2
    out[top:top + nh, left:left + nw] = small
    return out


def _canvas(mask: np.ndarray, shape: tuple[int, ...], notes: list[str]) -> np.ndarray:
    if mask.shape != shape:
        notes.append(f"fitted a {mask.shape[1]}x{mask.shape[0]} shape to the {shape[1]}x{shape[0]} canvas")
        mask = fit_canvas(mask, shape)
    return mask


# ---- 3D -----------------------------------------------------------------------------------------
def voxelize_mesh(path: Path, shape: tuple[int, int, int]) -> tuple[np.ndarray, list[str]]:
    """(bool grid of ``shape`` indexed [x, y, z], notes) of a mesh file by the module's rule."""
    import open3d as o3d

    check_file(path)
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    mesh = o3d.io.read_triangle_mesh(str(path))
    if not mesh.has_triangles():
        raise InputError("no triangles: not a readable mesh")
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.triangles, dtype=np.int64)
    if not np.isfinite(verts).all():
        raise InputError("the mesh has non-finite vertex coordinates")
    lo, hi = verts[faces].reshape(-1, 3).min(0), verts[faces].reshape(-1, 3).max(0)
    size = float((hi - lo).max())
    if size <= 0:
        raise InputError("the mesh is a single point")
    res = np.asarray(shape)
    # the training data's frame: centered on the bounds, longest side = 1; voxel centers (i+.5)/n - .5
    unit = (verts - (lo + hi) / 2) / size
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(unit.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    axes = [(np.arange(n) + 0.5) / n - 0.5 for n in res]
    centers = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).astype(np.float32)
    near = scene.compute_distance(o3d.core.Tensor(centers)).numpy().reshape(shape) <= 0.5 / res.max()
    notes = []
    if mesh.is_watertight():
        inside = scene.compute_occupancy(o3d.core.Tensor(centers)).numpy().reshape(shape) > 0.5
        # parts thinner than a voxel hold no center: keep the surface layer where nothing is inside
        grid = inside | (near & ~ndimage.binary_dilation(inside))
    else:
        filled = ndimage.binary_fill_holes(near)
        notes.append("the mesh is not watertight: voxelized its surface"
                     + (" and filled the space it encloses" if filled.sum() > near.sum() else
                        " (it encloses no space to fill)"))
        grid = filled
    return grid, notes


# ---- any domain -----------------------------------------------------------------------------------
def read_npy(path: Path) -> np.ndarray:
    """A numeric or bool .npy array without NaN or infinite values, as bool (nonzero inside)."""
    check_file(path)
    try:
        array = np.load(path, allow_pickle=False)
    except Exception as err:  # numpy raises several types for bad files
        raise InputError(f"not a readable .npy file ({err.__class__.__name__}: {one_line(err)})") from None
    if not isinstance(array, np.ndarray) or array.dtype.kind not in "biuf":
        raise InputError(f"expected a numeric or bool array, got dtype {getattr(array, 'dtype', type(array))}")
    if array.dtype.kind == "f" and not np.isfinite(array).all():
        raise InputError("the array holds NaN or infinite values")
    if array.ndim == 0 or array.size == 0:
        raise InputError(f"the array has no shape in it (shape {array.shape})")
    return array != 0


def npy_batch(array: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``array`` as a batch (N, ...) by the module's rule: one shape, or a batch of the domain's exact shape.

    A 2D domain also takes one (H, W) array of another size (fitted later); nothing else.
    """
    if array.ndim == len(shape) and (array.shape == shape or len(shape) == 2):
        return array[None]
    if array.ndim == len(shape) + 1 and array.shape[1:] == shape:
        return array
    want = ", ".join(map(str, shape))
    other = " or one (H, W) array to fit" if len(shape) == 2 else ""
    raise InputError(f"expected an array of shape ({want}) or (N, {want}){other}, got {array.shape}: "
                     f"its dimensions do not match the domain")


def check_target(grid: np.ndarray) -> np.ndarray:
    """The empty-shape rule of every domain: a target shape is neither empty nor the whole grid."""
    if not grid.any():
        raise InputError("the shape is empty (nothing inside): an empty target is refused in every domain")
    if grid.all():
        raise InputError("the shape fills the whole grid")
    return grid


def read_shapes(path: Path, shape: tuple[int, ...], targets: bool = True) -> np.ndarray:
    """Shapes of exactly the domain's ``shape`` for scoring or search: bool (N, *shape).

    A ``.npy`` (one shape or a batch), or for a 2D domain an image of exactly the
    canvas size (255 inside, 0 outside, as ``plad execute`` writes). ``targets``:
    the empty-shape rule applies (:func:`check_target`); a prediction may be empty.
    """
    suffix = path.suffix.lower()
    if suffix == ".npy":
        array = read_npy(path)
    elif suffix in IMAGE_SUFFIXES and len(shape) == 2:
        array = open_image(path, "L") > 127
    else:
        allowed = ".npy" + (" or an image (.png, ...)" if len(shape) == 2 else "")
        raise InputError(f"unsupported file type {suffix or '(none)'!r}; use {allowed}")
    batch = array[None] if array.shape == shape else array
    if batch.shape[1:] != shape:   # exactly the domain's grid: nothing is fitted for scoring
        want = ", ".join(map(str, shape))
        raise InputError(f"expected shape ({want}) or (N, {want}), got {array.shape}: its dimensions do not "
                         f"match the domain")
    if targets:
        for i, grid in enumerate(batch):
            try:
                check_target(grid)
            except InputError as err:
                raise InputError(f"shape {i}: {err}" if len(batch) > 1 else str(err)) from None
    return batch


def _items_of(path: Path, shape: tuple[int, ...], name: str) -> list[Item]:
    """The shapes of one file (several for a batch .npy); errors are recorded, not raised."""
    suffix = path.suffix.lower()
    notes: list[str] = []
    try:
        if suffix not in supported_suffixes(shape):
            raise InputError(f"unsupported file type {suffix or '(none)'!r}; use "
                             f"{', '.join(supported_suffixes(shape))}")
        if suffix == ".npy":
            array = read_npy(path)
            batch = npy_batch(array, shape)
            names = [name] if batch.shape[0] == 1 and array.ndim == len(shape) else \
                [f"{name}_{i}" for i in range(len(batch))]
            out = []
            for n, mask in zip(names, batch):
                item = Item(n, path)
                try:
                    item.shape = _check(_canvas(mask, shape, item.notes) if len(shape) == 2 else mask)
                except InputError as err:
                    item.error = str(err)
                out.append(item)
            return out
        if suffix in IMAGE_SUFFIXES:
            grid = _canvas(binarize_image(path), shape, notes)
        else:
            grid, notes = voxelize_mesh(path, shape)  # type: ignore[arg-type]
        return [Item(name, path, _check(grid), notes)]
    except InputError as err:
        return [Item(name, path, None, notes, str(err))]


_check = check_target


def read_inputs(paths: Iterable[str | Path], shape: tuple[int, ...]) -> list[Item]:
    """Items of the given files and folders (a folder: its supported files, sorted by name).

    Output stems are the file stems, made unique with ``-2``, ``-3``, ... .
    """
    files: list[Path] = []
    missing: list[Item] = []
    for p in map(Path, paths):
        if p.is_dir():
            files += sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in supported_suffixes(shape))
        elif p.exists():
            files.append(p)
        else:
            missing.append(Item(p.stem or p.name, p, error="no such file or folder"))
    items: list[Item] = []
    used: set[str] = set()
    for f in files:
        stem, k = f.stem, 2
        while stem in used:
            stem, k = f"{f.stem}-{k}", k + 1
        used.add(stem)
        items += _items_of(f, shape, stem)
    return missing + items
