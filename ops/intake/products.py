"""``products.csv``: the catalog's true size of each product, read from beside the photos.

Columns ``photo, sku, height_mm, width_mm, depth_mm`` (a header row; other columns are ignored). ``photo`` is
the photo's file name in the folder (``mug.jpg``); any of the three dimensions may be empty, and the export
scales by the first one given in that order (``ops.stages.export``). A bad row — an empty or unknown photo, a
dimension that is not a positive number, a photo listed twice — is an error of that row only, naming the file
and line: the photo it names fails its export with that message, the other photos go on.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

from ops.intake.photo_folder import list_photos

PRODUCTS_FILE = "products.csv"
DIMENSIONS = ("height_mm", "width_mm", "depth_mm")
COLUMNS = ("photo", "sku", *DIMENSIONS)


class ProductsFileError(ValueError):
    """``products.csv`` (or one of its rows) cannot be used; the message names the file, the line and the fix."""


@dataclass(frozen=True)
class ProductSize:
    """One product's catalog entry: its SKU and true dimensions in millimetres (None: not given)."""

    photo: str
    sku: str = ""
    height_mm: float | None = None
    width_mm: float | None = None
    depth_mm: float | None = None
    source: str = ""
    """Where it came from, ``products.csv:<line>`` or ``config``."""

    def __post_init__(self) -> None:
        for name in DIMENSIONS:
            positive_mm(name, getattr(self, name))

    @property
    def given(self) -> bool:
        return any(getattr(self, d) is not None for d in DIMENSIONS)


@dataclass(frozen=True)
class ProductTable:
    """What a ``products.csv`` says, by photo file name: sizes of good rows, errors of bad ones.

    ``unknown``: errors of rows naming no photo in the folder (nobody's export fails for them; the run
    reports them)."""

    path: Path
    sizes: dict[str, ProductSize] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)
    unknown: list[str] = field(default_factory=list)

    def size_of(self, photo: str) -> ProductSize | None:
        """The photo's size, None when the file does not list it; ``ProductsFileError`` when its row is bad."""
        if photo in self.errors:
            raise ProductsFileError(self.errors[photo])
        return self.sizes.get(photo)


def positive_mm(name: str, value: float | None) -> float | None:
    """``value`` if it is None or a positive, finite number of millimetres; else ``ValueError`` naming ``name``
    (the one rule for a size, wherever it is given: ``products.csv``, the export stage's config)."""
    if value is not None and not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive number of millimetres, got {value}")
    return value


def _dimension(text: str, where: str, name: str) -> float | None:
    text = text.strip()
    if not text:
        return None
    try:
        value = float(text)
    except ValueError:
        raise ProductsFileError(f"{where}: {name} {text!r} is not a number; write millimetres, e.g. 250") from None
    try:
        return positive_mm(name, value)
    except ValueError:
        raise ProductsFileError(f"{where}: {name} {text!r} must be a positive number of millimetres") from None


def read_products(path: Path, photos: set[str] | None = None) -> ProductTable:
    """Read ``path``. ``photos``: the file names in the folder (a row naming another is ``unknown``); None:
    the photos beside the file. A file that cannot be read as a table raises ``ProductsFileError``."""
    path = Path(path)
    if photos is None:
        photos = {p.name for p in list_photos(path.parent)}
    try:
        text = path.read_text(encoding="utf-8-sig")  # spreadsheets save UTF-8 with a byte-order mark
    except UnicodeDecodeError as exc:
        raise ProductsFileError(f"{path}: not UTF-8 text ({exc.reason}); save it as CSV UTF-8") from None
    except OSError as exc:
        raise ProductsFileError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    reader = csv.DictReader(text.splitlines())
    header = [h.strip() for h in reader.fieldnames or []]
    if "photo" not in header:
        raise ProductsFileError(f"{path}:1: the header must name the columns {', '.join(COLUMNS)} "
                                f"(found {', '.join(header) or 'nothing'})")
    reader.fieldnames = header
    table = ProductTable(path)
    seen: dict[str, int] = {}
    for row in reader:
        line = reader.line_num
        where = f"{path}:{line}"
        photo = (row.get("photo") or "").strip()
        if not photo:
            if any((v or "").strip() for v in row.values() if isinstance(v, str)):
                table.unknown.append(f"{where}: the photo column is empty; name the photo's file, e.g. mug.jpg")
            continue
        if photo not in photos:
            table.unknown.append(f"{where}: no photo {photo!r} in {path.parent}; fix the name or remove the row")
            continue
        if photo in seen:
            table.errors[photo] = f"{where}: {photo} is listed twice (also on line {seen[photo]}); keep one row"
            table.sizes.pop(photo, None)
            continue
        seen[photo] = line
        try:
            dims = {d: _dimension(row.get(d) or "", where, d) for d in DIMENSIONS}
        except ProductsFileError as exc:
            table.errors[photo] = str(exc)
            continue
        sku = (row.get("sku") or "").strip()
        table.sizes[photo] = ProductSize(photo, sku, **dims, source=f"{PRODUCTS_FILE}:{line}")
    return table


_CACHE: dict[Path, tuple[int, int, ProductTable]] = {}


def products_for(photo: Path) -> ProductTable | None:
    """The ``products.csv`` beside ``photo`` (None when there is none), read once per change of the file."""
    path = Path(photo).parent / PRODUCTS_FILE
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    key = path.resolve()
    cached = _CACHE.get(key)
    if cached is not None and cached[:2] == (st.st_mtime_ns, st.st_size):
        return cached[2]
    table = read_products(path)
    _CACHE[key] = (st.st_mtime_ns, st.st_size, table)
    return table
