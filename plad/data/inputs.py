# size: one contract, kept whole: the docstring below (about 65 lines) is the rule every command reads a user's
# shape by, and the readers of images, arrays and meshes share its Item, Frame, InputError and file limits;
# docs/conventions.md and docs/inference.md name this file as the one reader. A split would move those shared
# names to a third module for about 520 lines of code. No function over 100 lines.
"""The user's own shapes: images, arrays and meshes turned into a domain's target shapes. One reader for all.

Every command that takes a user's shape reads it here, by the same rules:
``plad infer`` (:func:`read_inputs`), ``plad score``, ``refine`` and ``search``
(:func:`read_file`), and the MLflow pyfunc model's ``predict`` (:func:`read_array`).
A bad shape never stops the others: each reader returns one :class:`Item` per
shape, with ``error`` set (a one-line reason) instead of raising, and
``notes`` for what was done to a shape that needed help. A file holding a
batch gives one item per shape, so one bad shape of a batch is one error.

2D domains (a canvas of ``domain.shape``, e.g. 64 x 64):

* images (``.png``, ``.jpg``, ``.bmp``, ``.gif``, ``.tif``, ``.webp``), any
  color mode: the gray values (16-bit and float images on their own scale,
  never clipped to 8 bits) are split at Otsu's threshold and the shape is the
  side that covers less of the image border (black on white and white on
  black both work). An image with transparent pixels (alpha below 128) and
  opaque ones is read by one rule (:func:`binarize`), with a note saying
  which way: where the transparent pixels are the background around the
  shape (most of the border), or where the opaque pixels are of one color,
  the alpha channel is the shape (the side of it that covers less of the
  border); otherwise the shape is read from the opaque pixels' colors as
  above and the transparent pixels are background (one stray transparent
  pixel never turns a drawing into a filled square). A file of several frames
  (an animated GIF, a multi-page TIFF) is read from its first frame, with a
  note.
* ``.npy`` arrays (and the pyfunc's arrays): one (H, W) array, or a batch
  (N, *canvas*) of canvas-sized arrays; nonzero is inside. Any other array
  (e.g. a 32^3 voxel grid) is refused.
* size: a shape of exactly the canvas size is used as it is. Any other size
  is cropped to the shape's bounding box, scaled (a canvas pixel is inside
  when at least half of the pixels it averages are: PIL's box filter) so that
  its longer side is :data:`FIT_2D` pixels (the median of the CAD shapes), and
  centered on the canvas. The placement is the item's :class:`Frame`: ``plad score`` puts a
  prediction where its target went (same size required), so that both are
  compared on one grid.

3D domains (a voxel grid of ``domain.shape``, e.g. 32^3 indexed [x, y, z], y up):

* meshes (``.obj``, ``.ply``, ``.off``, ``.stl``, read with open3d, at most
  :data:`plad.data.mesh.MAX_TRIANGLES` triangles, counted from the header
  where the format has one: :func:`plad.data.mesh.read_mesh`), normalized
  as the real training shapes: centered on their bounding box, the longest
  side spanning the grid (a predicted mesh in ``plad score``: in its target
  mesh's frame). A watertight mesh is voxelized by whether each voxel center
  is inside it, plus a layer of voxels along parts too thin for any center to
  fall inside them (as the training data keeps thin parts). A mesh that is
  not watertight is voxelized by its surface (voxel centers within half a
  voxel of it), and the space that surface encloses is filled, with a note.
* ``.npy`` arrays of exactly the grid's shape, or a batch of them.

Limits and values, the same everywhere:

* a file is at most :data:`MAX_FILE_BYTES` (256 MiB); one shape is at most
  :data:`MAX_PIXELS` (25 million pixels, e.g. 5000 x 5000), for an image and
  a ``.npy`` alike, checked from the header before anything is decoded (PIL's
  decompression bombs included);
* an array holds numbers or bools without NaN or infinite values (an image's
  too);
* **empty and full shapes**, in every domain: an empty *target* (nothing
  inside) is refused, since no metric can say how close a program comes to
  nothing, and so is a target that fills its whole image, array or grid.
  A *prediction* (``plad score --pred``) may be empty or full: the metric
  scores it (a single-color prediction image is empty).
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
#: the largest shape read (pixels of one image or one 2D array); PIL refuses larger images as bombs from here on
MAX_PIXELS = 25_000_000
Image.MAX_IMAGE_PIXELS = MAX_PIXELS
#: PIL modes of one gray channel wider than 8 bits: read on their own scale
_WIDE_MODES = ("I;16", "I;16L", "I;16B", "I;16N", "I", "F")


class InputError(BadInput, ValueError):
    """A user's shape cannot be used; the message is one line (without the file name)."""


@dataclass(frozen=True)
class Frame:
    """Where a source shape went on the domain's grid, so that another of the same source size goes there too.

    ``kind``: ``grid`` (the source had the grid's exact size: used as it is), ``fit`` (a 2D shape of
    another size: canvas row ``top + (row - r0) / ky``, column ``left + (col - c0) / kx``, ``k`` source pixels
    per canvas pixel) or ``mesh`` (vertices ``(v - center) / extent`` in the unit cube of the grid).
    """

    kind: str
    #: the source's size: (H, W) of a 2D source, the grid's shape for a grid, () for a mesh
    size: tuple[int, ...]
    #: fit: (r0, c0, top, left, ky, kx); mesh: (cx, cy, cz, extent)
    params: tuple[float, ...] = ()


@dataclass
class Item:
    """One input shape: where it came from and the target shape, or why there is none."""
    name: str                       # output file stem (unique within a run: :func:`read_inputs`)
    source: Path
    shape: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)
    error: str | None = None
    #: position in its file's batch (None: the file holds one shape)
    index: int | None = None
    #: how the shape was put on the grid (None when there is no shape)
    frame: Frame | None = None

    @property
    def where(self) -> str:
        """The source, quoted when it holds a control character, with the batch position: ``a.npy [3]``."""
        return quote(self.source) + ("" if self.index is None else f" [{self.index}]")


def quote(path: object) -> str:
    """``path`` as shown in a message: as it is, or Python-quoted when it holds a newline or another character
    that is not printable (a file name could otherwise forge a line of output)."""
    text = str(path)
    return text if text.isprintable() else repr(text)


def supported_suffixes(shape: tuple[int, ...]) -> tuple[str, ...]:
    return (*IMAGE_SUFFIXES, ".npy") if len(shape) == 2 else (*MESH_SUFFIXES, ".npy")


# ---- files ---------------------------------------------------------------------------------------
def check_file(path: Path) -> None:
    """The rules every input file meets before it is read: it exists, is a file, and is not too large."""
    try:
        size = path.stat().st_size
    except (OSError, ValueError):
        raise InputError("no such file") from None
    if not path.is_file():
        raise InputError("not a file")
    if size > MAX_FILE_BYTES:
        raise InputError(f"the file is {size / 2 ** 20:.0f} MiB, more than the limit of "
                         f"{MAX_FILE_BYTES // 2 ** 20} MiB")


def _check_pixels(size: tuple[int, int], what: str) -> None:
    h, w = size
    if h * w > MAX_PIXELS:
        raise InputError(f"the {what} is {w}x{h} pixels, more than the limit of {MAX_PIXELS:,} pixels")


# ---- images ---------------------------------------------------------------------------------------
def read_image(path: Path, notes: list[str] | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """(gray (H, W) float64 on the image's own scale, alpha (H, W) uint8 or None) of an image file (its first
    frame; a note in ``notes`` when it has more).

    Too large or unreadable images are an :class:`InputError`; the size is checked from the header.
    """
    check_file(path)
    try:
        with warnings.catch_warnings():   # PIL warns about what is refused here anyway
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            image = Image.open(path)      # reads the header only: the size is known before decoding
        with image:
            w, h = image.size
            _check_pixels((h, w), "image")
            frames = int(getattr(image, "n_frames", 1) or 1)
            if frames > 1:
                image.seek(0)
                if notes is not None:
                    notes.append(f"the file holds {frames} frames (an animation or pages): read the first only")
            image.load()
            if image.mode in _WIDE_MODES:
                # 16-bit and float gray: on their own scale (convert("L") would clip them to 0..255)
                wide = image.convert("F") if image.mode != "F" else image
                return np.asarray(wide, dtype=np.float64), None
            has_alpha = "A" in image.mode or "transparency" in image.info
            rgba = np.asarray(image.convert("RGBA" if has_alpha else "RGB"))
    except InputError:
        raise
    except Image.DecompressionBombError as err:   # PIL's own check at open: over twice the limit
        found = re.search(r"\((\d+) pixels\)", str(err))
        size = f"has {int(found.group(1)):,} pixels" if found else "is too large"
        raise InputError(f"the image {size}, more than the limit of {MAX_PIXELS:,} pixels") from None
    except (UnidentifiedImageError, OSError, ValueError, EOFError, SyntaxError) as err:
        raise InputError(f"not a readable image ({err.__class__.__name__})") from None
    gray = rgba[..., :3].astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    return gray, (rgba[..., 3] if rgba.shape[-1] == 4 else None)


def _border(mask: np.ndarray) -> np.ndarray:
    return np.concatenate([mask[0], mask[-1], mask[:, 0], mask[:, -1]])


def binarize(gray: np.ndarray, alpha: np.ndarray | None = None, target: bool = True,
             notes: list[str] | None = None) -> np.ndarray:
    """Foreground mask (H, W) of an image by the module's rule: Otsu's threshold with the border rule, and the
    one rule of transparency (module docstring), which says in ``notes`` what it did. A single-color image is
    refused as a target and empty as a prediction."""
    notes = [] if notes is None else notes
    if not np.isfinite(gray).all():
        raise InputError("the image holds NaN or infinite values")
    opaque = None if alpha is None or not (alpha.min() < 128 <= alpha.max()) else alpha >= 128
    if opaque is not None:
        seen = gray[opaque]
        background_transparent = _border(~opaque).mean() > 0.5
        if background_transparent or seen.max() - seen.min() <= 0:
            # the alpha channel is the shape: the side of it that covers less of the border
            shape = opaque if _border(opaque).mean() <= 0.5 else ~opaque
            notes.append(f"read the shape from the alpha channel: the {'opaque' if shape is opaque else 'transparent'} "
                         f"pixels ({int(shape.sum())} of {shape.size})")
            return shape
        dark = np.zeros(gray.shape, bool)
        dark[opaque] = seen <= threshold_otsu(seen)
        light = opaque & ~dark
        edge = _border(opaque)
        shape = dark if _border(dark)[edge].mean() <= 0.5 else light
        notes.append(f"took {int((~opaque).sum())} transparent pixel(s) as background; read the shape from the "
                     f"opaque pixels' colors")
        return shape
    if gray.max() - gray.min() <= 0:
        if target:
            raise InputError("the image is a single color: there is no shape in it")
        return np.zeros(gray.shape, bool)
    dark = gray <= threshold_otsu(gray)
    return dark if _border(dark).mean() <= 0.5 else ~dark


def binarize_image(path: Path, target: bool = True, notes: list[str] | None = None) -> np.ndarray:
    """Foreground mask (H, W) of an image file by the module's rule; what it did beyond the plain rule (alpha,
    frames) goes into ``notes``."""
    notes = [] if notes is None else notes
    gray, alpha = read_image(path, notes)
    return binarize(gray, alpha, target=target, notes=notes)


# ---- fitting 2D shapes to the canvas ---------------------------------------------------------------------
def _box_weights(n_out: int, n_in: int, first: float, top: float, k: float) -> tuple[np.ndarray, np.ndarray]:
    """(W (n_out, n_in) 0/1, count (n_out,)): the source pixels that output pixel i averages, and how many source
    pixel positions its window holds (positions off the source count as empty pixels).

    Output pixel i of a scaling by ``k`` source pixels per output pixel, whose output row ``top`` starts at
    source position ``first``, averages the source pixels whose centers lie within half a window (at least
    half a pixel) of its center: PIL's box filter (``Image.resize(..., BOX)``), on the whole source rather
    than a crop of it, so that a prediction of the same size as its target goes exactly where the target went.
    """
    half = max(k, 1.0) / 2
    center = (np.arange(n_out) - top + 0.5) * k                        # in source pixels from ``first``
    # every source position a window can hold, on and off the source (off it: empty pixels, counted)
    lo = min(0, int(np.floor(first + center.min() - half)) - 2)
    hi = max(n_in, int(np.ceil(first + center.max() + half)) + 2)
    rel = np.arange(lo, hi) - first                                     # source pixel index from ``first``
    # PIL's filter argument and its window bounds, in PIL's order of operations: a window's edge can fall on a
    # pixel center exactly, and PIL's bounds then decide
    offset = (rel[None, :] - center[:, None] + 0.5) * (1.0 / max(k, 1.0))
    first_in, end = np.floor(center - half + 0.5)[:, None], np.floor(center + half + 0.5)[:, None]
    window = (offset > -0.5) & (offset <= 0.5) & (rel[None, :] >= first_in) & (rel[None, :] < end)
    return window[:, -lo:n_in - lo].astype(np.float64), np.maximum(window.sum(1), 1)


def fit_frame(mask: np.ndarray, canvas: tuple[int, int], longer: int = FIT_2D) -> Frame:
    """The frame that crops ``mask`` to its shape, scales the longer side to ``longer`` pixels and centers it."""
    rows, cols = np.nonzero(mask)
    if len(rows) == 0:
        raise InputError("the shape is empty (nothing inside): an empty target is refused in every domain")
    r0, c0 = int(rows.min()), int(cols.min())
    h, w = int(rows.max()) + 1 - r0, int(cols.max()) + 1 - c0
    scale = longer / max(h, w)
    nh, nw = max(1, round(h * scale)), max(1, round(w * scale))
    top, left = (canvas[0] - nh) // 2, (canvas[1] - nw) // 2
    return Frame("fit", tuple(mask.shape), (r0, c0, top, left, h / nh, w / nw))


def apply_frame(mask: np.ndarray, canvas: tuple[int, int], frame: Frame) -> np.ndarray:
    """``mask`` placed on the canvas by ``frame`` (a ``fit`` frame of a source of the same size): a canvas pixel
    is inside when at least half of the source pixels it averages are (:func:`_box_weights`)."""
    r0, c0, top, left, ky, kx = frame.params
    wr, nr = _box_weights(canvas[0], mask.shape[0], r0, top, ky)      # (H_canvas, H), (H_canvas,)
    wc, nc = _box_weights(canvas[1], mask.shape[1], c0, left, kx)     # (W_canvas, W), (W_canvas,)
    # only the source rows and columns that reach the canvas take part (a large image, a small shape)
    rs, cs = np.nonzero(wr.any(0))[0], np.nonzero(wc.any(0))[0]
    if len(rs) == 0 or len(cs) == 0:
        return np.zeros(canvas, bool)
    part = mask[rs[0]:rs[-1] + 1, cs[0]:cs[-1] + 1].astype(np.float64)
    inside = wr[:, rs[0]:rs[-1] + 1] @ part @ wc[:, cs[0]:cs[-1] + 1].T   # source pixels inside, per canvas pixel
    return 2 * inside >= nr[:, None] * nc[None, :]


def fit_canvas(mask: np.ndarray, canvas: tuple[int, int], longer: int = FIT_2D) -> np.ndarray:
    """Crop ``mask`` to its shape, scale the longer side to ``longer`` pixels, center on ``canvas``."""
    return apply_frame(mask, canvas, fit_frame(mask, canvas, longer))


def _place_2d(mask: np.ndarray, shape: tuple[int, int], item: Item, target: bool, frame: Frame | None) -> None:
    """Put the 2D ``mask`` on the canvas (``item.shape``, ``item.frame``, a note when fitted).

    ``frame``: the target's, for a prediction; a prediction of another size but the same aspect ratio is
    taken to show the same area at another resolution (e.g. a 64x64 execution of a 256x256 drawing).
    """
    size = tuple(mask.shape)
    if target:
        _check_raw(mask)
    if frame is not None and frame.size != size:
        (H, W), (h, w) = frame.size, size
        if h * W != H * w:
            raise InputError(f"its size {w}x{h} has another aspect ratio than its target's {W}x{H}: a prediction is "
                             f"placed where its target went, so both need to show the same area")
        # the same area at another resolution: first to the target's size (PIL's box filter; a 4x larger or
        # smaller image of 4x4 blocks maps back exactly), then where the target went
        mask = np.asarray(Image.fromarray(mask.astype(np.float32)).resize((W, H), Image.Resampling.BOX)) >= 0.5
        size = (H, W)
    elif frame is None and size != shape and not target and not mask.any():
        frame = Frame("fit", size, (0, 0, 0, 0, size[0] / shape[0], size[1] / shape[1]))   # nothing to center
    if size == shape and (frame is None or frame.kind == "grid"):
        item.shape, item.frame = mask, Frame("grid", size)
        return
    frame = frame or fit_frame(mask, shape)
    item.shape, item.frame = apply_frame(mask, shape, frame), frame
    item.notes.append(f"fitted a {size[1]}x{size[0]} shape to the {shape[1]}x{shape[0]} canvas")


def _check_raw(mask: np.ndarray) -> None:
    if not mask.any():
        raise InputError("the shape is empty (nothing inside): an empty target is refused in every domain")
    if mask.all():
        raise InputError("the shape fills the whole grid: a target needs space outside it")


# ---- 3D -----------------------------------------------------------------------------------------
def voxelize_mesh(path: Path, shape: tuple[int, int, int], frame: Frame | None = None
                  ) -> tuple[np.ndarray, list[str]]:
    """(bool grid of ``shape`` indexed [x, y, z], notes) of a mesh file by the module's rule."""
    grid, notes, _ = _voxelize(path, shape, frame)
    return grid, notes


def _voxelize(path: Path, shape: tuple[int, int, int], frame: Frame | None) -> tuple[np.ndarray, list[str], Frame]:
    import open3d as o3d

    from plad.data.mesh import MeshError, read_mesh, watertight

    check_file(path)
    try:   # at most MAX_TRIANGLES, counted from the header first: a cost bounded by the file's size
        verts, faces = read_mesh(path)
    except MeshError as err:
        raise InputError(str(err)) from None
    used = verts[faces].reshape(-1, 3)
    if frame is None:
        lo, hi = used.min(0), used.max(0)
        size = float((hi - lo).max())
        if size <= 0:
            raise InputError("the mesh is a single point")
        frame = Frame("mesh", (), (*((lo + hi) / 2).tolist(), size))
    *center, size = frame.params
    res = np.asarray(shape)
    # the training data's frame: centered on the bounds, longest side = 1; voxel centers (i+.5)/n - .5
    unit = (verts - np.asarray(center)) / size
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(unit.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    axes = [(np.arange(n) + 0.5) / n - 0.5 for n in res]
    centers = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).astype(np.float32)
    near = scene.compute_distance(o3d.core.Tensor(centers)).numpy().reshape(shape) <= 0.5 / res.max()
    notes = []
    closed, note = watertight(verts, faces)   # linear in the triangles (plad.data.mesh)
    if note:
        notes.append(note)
    if closed:
        inside = scene.compute_occupancy(o3d.core.Tensor(centers)).numpy().reshape(shape) > 0.5
        # parts thinner than a voxel hold no center: keep the surface layer where nothing is inside
        grid = inside | (near & ~ndimage.binary_dilation(inside))
    else:
        filled = ndimage.binary_fill_holes(near)
        notes.append("the mesh is not watertight: voxelized its surface"
                     + (" and filled the space it encloses" if filled.sum() > near.sum() else
                        " (it encloses no space to fill)"))
        grid = filled
    return grid, notes, frame


# ---- arrays -------------------------------------------------------------------------------------------
def _npy_header(path: Path) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) from a .npy file's header, read without loading the data."""
    fmt = np.lib.format
    with open(path, "rb") as fh:
        version = fmt.read_magic(fh)
        read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape, _fortran, dtype = read(fh)
    return tuple(int(n) for n in shape), dtype


def read_npy(path: Path) -> np.ndarray:
    """The numeric or bool array of a .npy file, its header checked first (dtype, size) (:func:`numeric`)."""
    check_file(path)
    try:
        shape, dtype = _npy_header(path)
        if dtype.kind not in "biuf":
            raise InputError(f"expected a numeric or bool array, got dtype {dtype}")
        _check_size(shape)
        array = np.load(path, allow_pickle=False)
    except InputError:
        raise
    except Exception as err:  # numpy raises several types for bad files
        raise InputError(f"not a readable .npy file ({err.__class__.__name__}: {one_line(err)})") from None
    return numeric(array)


def _check_size(shape: tuple[int, ...]) -> None:
    """One shape of an array is at most :data:`MAX_PIXELS` cells (its last two dimensions for a 2D image)."""
    if len(shape) >= 2 and shape[-1] * shape[-2] > MAX_PIXELS:
        _check_pixels(shape[-2:], "array")   # raises
    if int(np.prod(shape, dtype=np.float64)) > MAX_FILE_BYTES:
        raise InputError(f"the array has {int(np.prod(shape, dtype=np.float64)):,} cells, more than the limit of "
                         f"{MAX_FILE_BYTES:,}")


def numeric(array: np.ndarray) -> np.ndarray:
    """``array`` if it is a numeric or bool array with a shape in it (NaN is checked per shape, later)."""
    if not isinstance(array, np.ndarray) or array.dtype.kind not in "biuf":
        raise InputError(f"expected a numeric or bool array, got dtype {getattr(array, 'dtype', type(array))}")
    _check_size(array.shape)
    if array.ndim == 0 or array.size == 0:
        raise InputError(f"the array has no shape in it (shape {array.shape})")
    return array


def as_mask(array: np.ndarray) -> np.ndarray:
    """One shape's numbers as bool (nonzero inside); NaN or infinite values are an :class:`InputError`."""
    if array.dtype.kind == "f" and not np.isfinite(array).all():
        raise InputError("the array holds NaN or infinite values")
    return array != 0


def npy_batch(array: np.ndarray, shape: tuple[int, ...]) -> tuple[np.ndarray, bool]:
    """(``array`` as a batch (N, ...), whether it was one) by the module's rule: one shape, or a batch of the
    domain's exact shape. A 2D domain also takes one (H, W) array of another size (fitted later); nothing else.
    """
    if array.ndim == len(shape) and (array.shape == shape or len(shape) == 2):
        return array[None], False
    if array.ndim == len(shape) + 1 and array.shape[1:] == shape:
        return array, True
    want = ", ".join(map(str, shape))
    other = " or one (H, W) array to fit" if len(shape) == 2 else ""
    raise InputError(f"expected an array of shape ({want}) or (N, {want}){other}, got {array.shape}: "
                     f"its dimensions do not match the domain")


def check_target(grid: np.ndarray) -> np.ndarray:
    """The empty-shape rule of every domain: a target shape is neither empty nor the whole grid."""
    _check_raw(grid)
    return grid


def _array_items(array: np.ndarray, shape: tuple[int, ...], name: str, source: Path, target: bool,
                 frames: list[Frame | None] | None) -> list[Item]:
    """One item per shape of a numeric array (one shape or a batch); a bad shape is an error item."""
    batch, is_batch = npy_batch(array, shape)
    if frames is not None and len(frames) != len(batch):
        raise InputError(f"holds {len(batch)} shapes but its target file holds {len(frames)}")
    out = []
    for i, values in enumerate(batch):
        item = Item(f"{name}_{i}" if is_batch else name, source, index=i if is_batch else None)
        try:
            mask = as_mask(values)
            frame = frames[i] if frames is not None else None
            if len(shape) == 2:
                _place_2d(mask, shape, item, target, frame)
            else:
                if frame is not None and frame.kind == "mesh":
                    raise InputError("a voxel grid cannot be placed in its target mesh's frame: give the "
                                     "prediction as a mesh too, or both as grids")
                item.shape, item.frame = (check_target(mask) if target else mask), Frame("grid", shape)
        except InputError as err:
            item.shape, item.frame, item.error = None, None, str(err)
        out.append(item)
    return out


def read_array(array, shape: tuple[int, ...], name: str = "input", target: bool = True,
               source: str | Path = "<array>") -> list[Item]:
    """Items of an in-memory array (the pyfunc model's input): one shape or a batch, by the rules of ``.npy``."""
    source = Path(str(source))
    try:
        return _array_items(numeric(np.asarray(array)), tuple(shape), name, source, target, None)
    except InputError as err:
        return [Item(name, source, error=str(err))]
    except (TypeError, ValueError) as err:   # np.asarray of ragged or non-numeric input
        return [Item(name, source, error=f"not an array of numbers ({one_line(err)})")]


def read_file(path: str | Path, shape: tuple[int, ...], name: str | None = None, target: bool = True,
              frames: list[Frame | None] | None = None) -> list[Item]:
    """The shapes of one file (several for a batch .npy): one :class:`Item` each; errors are recorded, not raised.

    ``target``: the empty/full rule applies (a prediction may be empty). ``frames``: a prediction's targets'
    frames, one per shape (``plad score``): the prediction is placed where its target went.
    """
    path = Path(path)
    shape = tuple(shape)
    name = name if name is not None else safe_name(path.stem)
    suffix = path.suffix.lower()
    item = Item(name, path)
    try:
        if suffix not in supported_suffixes(shape):
            raise InputError(f"unsupported file type {suffix or '(none)'!r}; use "
                             f"{', '.join(supported_suffixes(shape))}")
        if suffix == ".npy":
            return _array_items(read_npy(path), shape, name, path, target, frames)
        frame = frames[0] if frames else None
        if suffix in IMAGE_SUFFIXES:
            mask = binarize_image(path, target, item.notes)   # a file's own problem first, then its pairing
            _check_count(frames)
            _place_2d(mask, shape, item, target, frame)
        else:
            _check_count(frames)
            if frame is not None and frame.kind != "mesh":
                raise InputError("a mesh prediction is placed in its target's frame: give the target as a mesh "
                                 "too, or the prediction as a voxel grid (.npy)")
            grid, item.notes, item.frame = _voxelize(path, shape, frame)   # type: ignore[arg-type]
            item.shape = check_target(grid) if target else grid
    except InputError as err:
        item.shape, item.frame, item.error = None, None, str(err)
    return [item]


def _check_count(frames: list[Frame | None] | None) -> None:
    if frames is not None and len(frames) != 1:
        raise InputError(f"holds one shape but its target file holds {len(frames)}")


def safe_name(stem: str) -> str:
    """A file stem as an output name: letters, digits, ``.``, ``_`` and ``-`` only, not starting with a dot
    (``..png`` or ``../x.png`` never name a file outside the run folder)."""
    name = re.sub(r"[^A-Za-z0-9._-]", "_", stem).lstrip(".")
    return name or "shape"


def unique_names(items: list[Item]) -> list[Item]:
    """Give every item a distinct output name (case-insensitively): the first of equal names keeps it, the
    others get ``-2``, ``-3``, ... never taking a name that a later item has by itself."""
    reserved = {it.name.lower() for it in items}
    used: set[str] = set()
    for it in items:
        name = it.name
        if name.lower() in used:
            k = 2
            while f"{name}-{k}".lower() in used or f"{name}-{k}".lower() in reserved:
                k += 1
            name = f"{name}-{k}"
        used.add(name.lower())
        it.name = name
    return items


def read_inputs(paths: Iterable[str | Path], shape: tuple[int, ...]) -> list[Item]:
    """Items of the given files and folders (a folder: its supported files, sorted by name), all as targets.

    Output names are the files' safe stems (:func:`safe_name`; a batch's shapes ``<stem>_<i>``), made unique
    over the whole run (:func:`unique_names`).
    """
    files: list[Path] = []
    missing: list[Item] = []
    for p in map(Path, paths):
        if p.is_dir():
            files += sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in supported_suffixes(shape))
        elif p.exists():
            files.append(p)
        else:
            missing.append(Item(safe_name(p.stem or p.name), p, error="no such file or folder"))
    items = list(missing)
    for f in files:
        items += read_file(f, shape)
    return unique_names(items)
