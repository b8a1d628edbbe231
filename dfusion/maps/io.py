r"""Map files: ROS map_server YAML + image, and the BLE RSSI dataset's ``.occ`` node grids.

map_server format
-----------------
As documented at http://wiki.ros.org/map_server: keys ``image``, ``resolution``,
``origin``, ``negate``, ``occupied_thresh``, ``free_thresh`` and optional ``mode``
(``trinary`` default, ``scale``, ``raw``). A pixel of grey level ``v`` (0..255) has
occupancy probability ``p = (255 - v) / 255`` (``p = v / 255`` when ``negate: 1``);
``p > occupied_thresh`` -> 100, ``p < free_thresh`` -> 0, otherwise -1 (``trinary``) or
``1 + 98 (p - free) / (occ - free)`` (``scale``); ``raw`` stores ``v``. The image's top
row is the map's last row (the image is flipped). Images (PGM P2/P5 of 8 or 16 bits, PNG,
...) are read with Pillow; 16-bit grey levels are scaled to 8 bits as map_server does.
:func:`write_map_yaml` writes the map_saver convention: free 254, occupied 0, unknown 205.
The YAML file is read with PyYAML (:func:`read_map_meta`): map_server files are flat
``key: value`` lines with flow lists ``[x, y, yaw]``; nested tables and block lists are
rejected with a clear error.

``.occ`` node grids
-------------------
:func:`read_occ` reads the occupancy files of the BLE RSSI dataset (Danis et al.).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike
from PIL import Image, UnidentifiedImageError

from dfusion.errors import ShapeError, ValidationError
from dfusion.maps.grid import FREE, OCCUPIED, UNKNOWN, OccupancyGrid

__all__ = ["read_map_yaml", "write_map_yaml", "read_map_meta", "read_pgm", "write_pgm", "read_occ"]


def _scalar(node: yaml.ScalarNode) -> Any:
    value = yaml.safe_load(yaml.serialize(node))
    if isinstance(value, str) and node.style is None:
        try:   # YAML 1.1 reads 5e-2 (no dot) as a string; map files mean a number
            return float(value)
        except ValueError:
            return value
    return value


def read_map_meta(text: str) -> dict[str, Any]:
    """The ``key: value`` pairs of a map_server YAML file.

    Values are scalars (numbers, booleans, strings, null) or flow lists of scalars
    (``[a, b, c]``); ``#`` starts a comment. A nested table or a block list raises
    :class:`ValidationError` naming the key.
    """
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        raise ValidationError(f"invalid YAML: {exc}") from None
    if root is None:
        return {}
    if not isinstance(root, yaml.MappingNode):
        raise ValidationError("a map file must be a YAML mapping of key: value lines")
    out: dict[str, Any] = {}
    for knode, vnode in root.value:
        key = str(_scalar(knode))
        if isinstance(vnode, yaml.ScalarNode):
            out[key] = _scalar(vnode)
        elif isinstance(vnode, yaml.SequenceNode) and vnode.flow_style and all(
                isinstance(v, yaml.ScalarNode) for v in vnode.value):
            out[key] = [_scalar(v) for v in vnode.value]
        else:
            raise ValidationError(f"unsupported YAML value for {key!r} (line {vnode.start_mark.line + 1}): "
                                  "map files hold scalars and flow lists [a, b]")
    return out


def read_pgm(path: str | Path) -> np.ndarray:
    """Grey levels 0..255 (row 0 = the top row) of a PGM image (P2 or P5, 8 or 16 bits)."""
    path = Path(path)
    try:
        with Image.open(path, formats=["PPM"]) as im:
            if im.mode not in ("L", "I", "I;16", "I;16B"):
                raise ValidationError(f"{path}: not a grey-level PGM image (mode {im.mode})")
            img = np.asarray(im, dtype=np.int64)
            wide = im.mode != "L"
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise ValidationError(f"{path}: not a readable PGM image ({exc})") from None
    if wide:   # Pillow reads every 16-bit PGM on the 0..65535 scale
        img = np.rint(img * (255.0 / 65535.0)).astype(np.int64)
    return img


def write_pgm(path: str | Path, image: ArrayLike) -> None:
    """Write an 8-bit binary PGM (P5); ``image[0]`` is the top row."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise ShapeError(f"PGM image must be 2-D, got shape {img.shape}")
    if img.min(initial=0) < 0 or img.max(initial=0) > 255:
        raise ValidationError("PGM image values must be in 0..255")
    Image.fromarray(np.ascontiguousarray(img, dtype=np.uint8), mode="L").save(Path(path), format="PPM")


def _read_image(path: Path) -> np.ndarray:
    """Grey levels 0..255 (top row first) of a map image; NaN where a pixel is transparent."""
    if path.suffix.lower() in (".pgm", ".pnm"):
        return read_pgm(path)
    try:
        im = Image.open(path)
    except (UnidentifiedImageError, OSError) as exc:
        raise ValidationError(f"{path}: cannot read the map image ({exc})") from None
    with im:
        if im.mode in ("RGBA", "LA"):
            arr = np.asarray(im.convert("RGBA"), dtype=np.float64)
            grey = arr[..., :3].mean(axis=2)
            # map_server: pixels with alpha < 255 become unknown
            grey[arr[..., 3] < 255] = np.nan
            return grey
        if im.mode not in ("L", "I", "I;16"):
            return np.asarray(im.convert("RGB"), dtype=np.float64).mean(axis=2).round()
        return np.asarray(im, dtype=np.float64)


def read_map_yaml(yaml_path: str | Path) -> OccupancyGrid:
    """Load a ROS map_server map (YAML + image; see the module docstring)."""
    yaml_path = Path(yaml_path)
    meta = read_map_meta(yaml_path.read_text())
    for key in ("image", "resolution", "origin"):
        if key not in meta:
            raise ValidationError(f"{yaml_path}: missing key {key!r}")
    image_path = Path(str(meta["image"]))
    if not image_path.is_absolute():
        image_path = yaml_path.parent / image_path
    negate = bool(int(meta.get("negate", 0)))
    occ_th = float(meta.get("occupied_thresh", 0.65))
    free_th = float(meta.get("free_thresh", 0.196))
    mode = str(meta.get("mode", "trinary")).lower()
    if mode not in ("trinary", "scale", "raw"):
        raise ValidationError(f"{yaml_path}: unknown mode {mode!r}")
    grey = _read_image(image_path)
    data = _grey_to_occupancy(grey, negate, occ_th, free_th, mode)
    origin = meta["origin"]
    if not isinstance(origin, list) or len(origin) not in (2, 3):
        raise ValidationError(f"{yaml_path}: origin must be a list [x, y, yaw]")
    return OccupancyGrid(data[::-1], float(meta["resolution"]), [float(v) for v in origin], occ_th, free_th)


def _grey_to_occupancy(grey: np.ndarray, negate: bool, occ_th: float, free_th: float, mode: str) -> np.ndarray:
    g = np.asarray(grey, dtype=np.float64)
    nan = np.isnan(g)
    g = np.where(nan, 0.0, g)
    if negate:
        g = 255.0 - g
    if mode == "raw":
        out = np.clip(g, -1, 100).astype(np.int16)
        out[g > 100] = UNKNOWN
        out[nan] = UNKNOWN
        return out
    p = (255.0 - g) / 255.0
    out = np.full(g.shape, UNKNOWN, dtype=np.int16)
    if mode == "scale":
        ratio = (p - free_th) / (occ_th - free_th)
        out = np.rint(1.0 + 98.0 * ratio).astype(np.int16)
    out[p > occ_th] = OCCUPIED
    out[p < free_th] = FREE
    out[nan] = UNKNOWN
    return out


def write_map_yaml(grid: OccupancyGrid, yaml_path: str | Path, image_name: str | None = None) -> Path:
    """Write the map as map_saver does (trinary PGM + YAML); returns the image path.

    Free cells are written as 254, occupied as 0 and everything else as 205, so that
    ``load`` gives back the same free/occupied/unknown classification.
    """
    yaml_path = Path(yaml_path)
    image_name = image_name or yaml_path.with_suffix(".pgm").name
    img = np.full(grid.shape, 205, dtype=np.uint8)
    img[grid.free] = 254
    img[grid.occupied] = 0
    image_path = yaml_path.parent / image_name
    write_pgm(image_path, img[::-1])
    x, y, yaw = (float(v) for v in grid.origin)
    yaml_path.write_text(
        f"image: {image_name}\n"
        f"resolution: {grid.resolution!r}\n"
        f"origin: [{x!r}, {y!r}, {yaw!r}]\n"
        f"negate: 0\n"
        f"occupied_thresh: {grid.occupied_thresh!r}\n"
        f"free_thresh: {grid.free_thresh!r}\n"
    )
    return image_path


def read_occ(path: str | Path, occupied_value: int = 1) -> OccupancyGrid:
    """Read a ``.occ`` node grid of the BLE RSSI dataset (Danis et al.).

    Format: line 1 ``[[x_min, y_min], [x_max, y_max]]::cell``; every other line
    ``[x, y]::v``, one per node, in any order; node ``(x, y)`` is the centre of a
    ``cell`` x ``cell`` square (see :meth:`dfusion.maps.OccupancyGrid.from_nodes`). ``occupied_value`` is the
    value that marks an obstacle: the dataset's own README says 1 = traversable, but
    the data show the reverse (tracks run on 0-nodes, tables and the border are 1), so
    1 = occupied is the default. Raises :class:`ValidationError` on a malformed file,
    a missing or duplicated node, or a node off the lattice.
    """

    path = Path(path)
    lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    if not lines:
        raise ValidationError(f"{path}: empty occupancy file")
    try:
        head, cell_s = lines[0].rsplit("::", 1)
        (x0, y0), (x1, y1) = json.loads(head)
        cell = float(cell_s)
        pts = np.array([json.loads(ln.split("::", 1)[0]) for ln in lines[1:]], dtype=float)
        vals = np.array([int(ln.rsplit("::", 1)[1]) for ln in lines[1:]])
    except (ValueError, TypeError) as exc:
        raise ValidationError(f"{path}: malformed occupancy file ({exc})") from None
    if pts.ndim != 2 or pts.shape[1] != 2 or not np.all(np.isin(vals, (0, 1))):
        raise ValidationError(f"{path}: node lines must be '[x, y]::0' or '[x, y]::1'")
    ij = np.rint((pts - np.array([x0, y0])) / cell).astype(int)
    if np.max(np.abs(ij * cell + np.array([x0, y0]) - pts)) > 1e-6 * max(1.0, cell) or np.any(ij < 0):
        raise ValidationError(f"{path}: node positions are not on the {cell} m lattice from ({x0}, {y0})")
    nx, ny = ij.max(axis=0) + 1
    if nx * ny != len(ij):
        raise ValidationError(f"{path}: expected {nx} x {ny} = {nx * ny} nodes, found {len(ij)}")
    occ = np.zeros((nx, ny), dtype=bool)
    seen = np.zeros((nx, ny), dtype=bool)
    seen[ij[:, 0], ij[:, 1]] = True
    if not seen.all():
        raise ValidationError(f"{path}: duplicated or missing nodes")
    occ[ij[:, 0], ij[:, 1]] = vals == occupied_value
    return OccupancyGrid.from_nodes(occ, cell, (x0, y0))
