"""Semantic class tables: contiguous class ids ``0..C-1``, names and display / semantic colours.

The palette colour of a class is also its *semantic colour* in the Gaussian map (paper §III-A): a Gaussian's class is
the index of the nearest palette colour, so the colours of one table must be distinct.
"""
from __future__ import annotations

import colorsys
import json
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch


@dataclass(frozen=True)
class ClassTable:
    """Classes ``0..len(names)-1`` with names and RGB colours (``colors`` (C, 3) uint8)."""

    names: tuple[str, ...]
    colors: np.ndarray

    def __post_init__(self):
        colors = np.asarray(self.colors)
        if colors.shape != (len(self.names), 3):
            raise ValueError(f"ClassTable: colors shape {colors.shape} does not match {len(self.names)} names")
        if colors.min(initial=0) < 0 or colors.max(initial=0) > 255:
            raise ValueError("ClassTable: colours must lie in 0..255")
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"ClassTable: duplicate class names in {self.names}")
        if len({tuple(c) for c in colors.tolist()}) != len(self.names):
            raise ValueError("ClassTable: class colours must be distinct (they identify classes in the map)")
        colors = colors.astype(np.uint8)
        colors.setflags(write=False)
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "colors", colors)

    def __len__(self) -> int:
        return len(self.names)

    @property
    def ids(self) -> np.ndarray:
        return np.arange(len(self.names), dtype=np.int64)

    @property
    def palette(self) -> torch.Tensor:
        """(C, 3) float32 colours in [0, 1]."""
        return torch.from_numpy(self.colors.astype(np.float32) / 255.0)

    def id_of(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise ValueError(f"unknown class {name!r}; known: {', '.join(self.names)}") from None

    def colorize(self, labels: np.ndarray) -> np.ndarray:
        """Class ids (H, W) -> RGB image (H, W, 3) uint8."""
        labels = np.asarray(labels)
        if labels.size and (labels.min() < 0 or labels.max() >= len(self)):
            raise ValueError(f"labels hold ids in [{labels.min()}, {labels.max()}], "
                             f"outside this table's 0..{len(self) - 1}")
        return self.colors[labels]

    # --- text form: one "id name r g b" line per class -------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        rows = enumerate(zip(self.names, self.colors))
        lines = ["# id name r g b"] + [f"{i} {name} {r} {g} {b}" for i, (name, (r, g, b)) in rows]
        Path(path).write_text("\n".join(lines) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> "ClassTable":
        names, colors = [], []
        for number, line in enumerate(Path(path).read_text().splitlines(), 1):
            if not line.strip() or line.lstrip().startswith("#"):
                continue
            parts = line.split()
            if len(parts) != 5 or not parts[0].isdigit() or int(parts[0]) != len(names):
                raise ValueError(f"{path}:{number}: expected 'id name r g b' with ids 0, 1, 2, ... in order, "
                                 f"got {line!r}")
            names.append(parts[1])
            colors.append([int(v) for v in parts[2:]])
        if not names:
            raise ValueError(f"{path}: no classes")
        return cls(tuple(names), np.array(colors))


# Class table files a dataset folder may hold, in the order they are looked for (see :func:`load_class_table`).
CLASS_TABLE_FILES = ("classes.txt", "classes.json", "palette.txt")


def generic_colors(count: int) -> np.ndarray:
    """``count`` distinct RGB colours (uint8 values as int64), well spread for small counts (golden-ratio hues)."""
    if count > 256**3:
        raise ValueError(f"generic_colors: {count} colours cannot be distinct")
    colors, seen = [], set()
    for i in range(count):
        rgb = colorsys.hsv_to_rgb(i * 0.618033988749895 % 1.0, 0.75, 0.95 - 0.3 * (i // 8 % 2))
        code = int(round(rgb[0] * 255)) << 16 | int(round(rgb[1] * 255)) << 8 | int(round(rgb[2] * 255))
        while code in seen:  # rounding collides for large counts: take the next free colour
            code = (code + 1) % 256**3
        seen.add(code)
        colors.append([code >> 16, code >> 8 & 255, code & 255])
    return np.array(colors, dtype=np.int64).reshape(-1, 3)


def generic_table(count: int) -> ClassTable:
    """``count`` classes named ``class_<id>`` with :func:`generic_colors`."""
    return ClassTable(tuple(f"class_{i}" for i in range(count)), generic_colors(count))


def load_class_table(path: str | Path) -> ClassTable:
    """A class table from ``classes.txt`` (``id name r g b`` lines), a ``.json`` file (a list of names, or of
    ``{"name": ..., "color": [r, g, b]}`` objects with optional ``id`` keys, possibly under ``"classes"``; or an
    object keyed by id, ``{"0": {"name": ..., "color": [...]}, "1": "wall", ...}``; missing colours are generic, ids
    missing below the largest are assumed as ``class_<id>`` with a warning) or a palette (``palette.txt``: one
    ``r g b`` line per class id, names ``class_<id>``)."""
    path = Path(path)
    if path.suffix == ".json":
        return _json_table(path)
    if path.name.startswith("palette"):
        return _palette_table(path)
    return ClassTable.load(path)


def _json_table(path: Path) -> ClassTable:
    doc = json.loads(path.read_text())
    if isinstance(doc, dict) and doc and all(key.isdigit() for key in doc):  # keyed by class id
        doc = [_with_id(entry, int(key)) for key, entry in doc.items()]
    entries = doc.get("classes") if isinstance(doc, dict) else doc
    if not isinstance(entries, list) or not entries:
        raise ValueError(f"{path}: expected a non-empty list of classes (or {{\"classes\": [...]}})")
    entries = [{"name": e} if isinstance(e, str) else e for e in entries]
    if not all(isinstance(e, dict) and "name" in e for e in entries):
        raise ValueError(f"{path}: each class must be a name or an object with a \"name\"")
    if any("id" in e for e in entries):
        ids = [e.get("id") for e in entries]
        if not all(isinstance(i, int) and i >= 0 for i in ids) or len(set(ids)) != len(ids):
            raise ValueError(f"{path}: when classes have ids, each needs its own id >= 0, got {ids}")
        missing = sorted(set(range(max(ids) + 1)) - set(ids))
        if missing:
            warnings.warn(f"{path}: no class has the ids {missing}; they are assumed, named class_<id>", stacklevel=3)
        by_id = {e["id"]: e for e in entries}
        entries = [by_id.get(i, {"name": f"class_{i}"}) for i in range(max(ids) + 1)]
    fallback = generic_colors(len(entries))
    colors = [e.get("color", e.get("colour", fallback[i])) for i, e in enumerate(entries)]
    return ClassTable(tuple(str(e["name"]) for e in entries), np.array(colors, dtype=np.int64).reshape(-1, 3))


def _with_id(entry, class_id: int):
    """An entry of a table keyed by id (a name or an object) as a list entry with its ``id``; others as they are."""
    if isinstance(entry, str):
        return {"name": entry, "id": class_id}
    return {**entry, "id": class_id} if isinstance(entry, dict) else entry


def _palette_table(path: Path) -> ClassTable:
    colors = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 3 or not all(p.isdigit() for p in parts):
            raise ValueError(f"{path}:{number}: expected 'r g b' (0..255), got {line!r}")
        colors.append([int(p) for p in parts])
    if not colors:
        raise ValueError(f"{path}: no colours")
    return ClassTable(tuple(f"class_{i}" for i in range(len(colors))), np.array(colors))


def find_class_table(folder: Path) -> tuple[ClassTable, Path] | None:
    """The first of :data:`CLASS_TABLE_FILES` in ``folder``, loaded, and its path; None when there is none."""
    for name in CLASS_TABLE_FILES:
        if (folder / name).is_file():
            return load_class_table(folder / name), folder / name
    return None


def _table(entries: list[tuple[str, tuple[int, int, int]]]) -> ClassTable:
    return ClassTable(tuple(n for n, _ in entries), np.array([c for _, c in entries]))


SYNTHETIC_CLASSES = _table([
    ("floor", (152, 223, 138)), ("wall", (174, 199, 232)), ("ceiling", (120, 120, 120)), ("table", (255, 152, 150)),
    ("chair", (188, 189, 34)), ("sofa", (140, 86, 75)), ("cabinet", (31, 119, 180)), ("plant", (44, 160, 44)),
    ("picture", (196, 156, 148)), ("lamp", (255, 187, 120)), ("door", (214, 39, 40)), ("box", (148, 103, 189)),
])

# NYU40 ids with the colours of ScanNet's util.create_color_palette (0 = unlabelled).
NYU40_CLASSES = _table([
    ("unlabelled", (0, 0, 0)), ("wall", (174, 199, 232)), ("floor", (152, 223, 138)), ("cabinet", (31, 119, 180)),
    ("bed", (255, 187, 120)), ("chair", (188, 189, 34)), ("sofa", (140, 86, 75)), ("table", (255, 152, 150)),
    ("door", (214, 39, 40)), ("window", (197, 176, 213)), ("bookshelf", (148, 103, 189)), ("picture", (196, 156, 148)),
    ("counter", (23, 190, 207)), ("blinds", (178, 76, 76)), ("desk", (247, 182, 210)), ("shelves", (66, 188, 102)),
    ("curtain", (219, 219, 141)), ("dresser", (140, 57, 197)), ("pillow", (202, 185, 52)), ("mirror", (51, 176, 203)),
    ("floor_mat", (200, 54, 131)), ("clothes", (92, 193, 61)), ("ceiling", (78, 71, 183)), ("books", (172, 114, 82)),
    ("refrigerator", (255, 127, 14)), ("television", (91, 163, 138)), ("paper", (153, 98, 156)),
    ("towel", (140, 153, 101)), ("shower_curtain", (158, 218, 229)), ("box", (100, 125, 154)),
    ("whiteboard", (178, 127, 135)), ("person", (120, 185, 128)), ("night_stand", (146, 111, 194)),
    ("toilet", (44, 160, 44)), ("sink", (112, 128, 144)), ("lamp", (96, 207, 209)), ("bathtub", (227, 119, 194)),
    ("bag", (213, 92, 176)), ("otherstructure", (94, 106, 211)), ("otherfurniture", (82, 84, 163)),
    ("otherprop", (100, 85, 144)),
])

# The 20 classes of the ScanNet benchmark as NYU40 ids: SCANNET20_CLASSES id i + 1 is NYU40 id SCANNET20_NYU40_IDS[i].
SCANNET20_NYU40_IDS = (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14, 16, 24, 28, 33, 34, 36, 39)
SCANNET20_CLASSES = ClassTable(
    ("unlabelled",) + tuple(NYU40_CLASSES.names[i] for i in SCANNET20_NYU40_IDS),
    NYU40_CLASSES.colors[[0, *SCANNET20_NYU40_IDS]],
)


def nyu40_to_scannet20() -> np.ndarray:
    """Lookup array (41,) mapping NYU40 ids to SCANNET20_CLASSES ids (classes outside the 20 map to 0)."""
    lut = np.zeros(len(NYU40_CLASSES), dtype=np.int64)
    lut[list(SCANNET20_NYU40_IDS)] = np.arange(1, len(SCANNET20_NYU40_IDS) + 1)
    return lut
