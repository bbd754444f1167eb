"""Painting the scenes' textures: palette helpers (``palette``, ``darker``, ``luma``, ...), ``Canvas``
(one tile's content: flat regions, stripes, print, lettering, barcodes, tartans, knurls, weaves,
grain), the layouts of multi-tile textures (a box's six faces, a revolved part's sectors) and the
sizing of fine patterns in render pixels (``fine_period``)."""

from __future__ import annotations

import colorsys
import math
from collections.abc import Callable, Sequence

import cv2
import numpy as np

from benchmarks.scenes.framing import FRAME_FILL
from benchmarks.scenes.parts import BOX_FACE_NAMES, CONTENT, MARGIN, TILE

# The fine scenes (tin, gift, basket, torch) size their patterns for the quality benchmark's renders:
# FINE_PERIOD_PX pixels at BENCH_SIZE puts a pattern's frequency at 2 / FINE_PERIOD_PX ≈ 0.7 of the
# render's DCT band, above the 2-D prior's high-pass bound r = 0.6 (periods under 3.33 px).
BENCH_SIZE = 128
FINE_PERIOD_PX = 2.8

Colour = tuple[float, float, float]


def hsv(h: float, s: float, v: float) -> Colour:
    r, g, b = colorsys.hsv_to_rgb(h % 1.0, min(max(s, 0.0), 1.0), min(max(v, 0.0), 1.0))
    return (r, g, b)


def palette(rng: np.random.Generator, count: int, s: tuple[float, float] = (0.6, 0.95),
             v: tuple[float, float] = (0.45, 0.9)) -> list[Colour]:
    """``count`` saturated colours with hues spread around the wheel from a random start, so a scene's
    regions differ clearly in colour (the benchmark measures colour deviation)."""
    start = rng.uniform()
    return [hsv(start + k / count + rng.uniform(-0.05, 0.05), rng.uniform(*s), rng.uniform(*v))
            for k in range(count)]


def darker(colour: Colour, factor: float) -> Colour:
    r, g, b = colour
    return (r * factor, g * factor, b * factor)


def luma(colour: Colour) -> float:
    """Rec. 709 luma: the brightness the benchmark's grey spectra see."""
    r, g, b = colour
    return 0.2126 * r + 0.7152 * g + 0.0722 * b


def with_luma(colour: Colour, target: float) -> Colour:
    """``colour`` scaled to a ``luma`` of ``target`` (clipped to [0, 1]): the fine scenes set their large
    regions apart by hue more than by brightness, so the fine print, not the layout, holds the contrast."""
    r, g, b = colour
    scale = target / max(luma(colour), 1e-6)
    return (min(r * scale, 1.0), min(g * scale, 1.0), min(b * scale, 1.0))


class Canvas:
    """A tile's content being painted, addressed in the part's own (u, v) ∈ [0, 1]² (v up; row 0 at
    v = 1). Detail sizes are in texels: a tile spans roughly 100–250 px of a 256 px render, so marks
    of 3+ texels stay visible (not sub-pixel). ``aspect`` is the width / height of the surface the tile
    covers (a box face, half a turn of a can): ``lettering`` keeps letters round on a stretched tile."""

    def __init__(self, colour: Colour, height: int = CONTENT, width: int = CONTENT, aspect: float = 1.0) -> None:
        self.img = np.empty((height, width, 3), dtype=np.float32)
        self.img[:] = colour
        self.h, self.w = height, width
        self.aspect = aspect
        jj, ii = np.meshgrid(np.arange(width), np.arange(height))
        self.u = (jj + 0.5) / width
        self.v = 1.0 - (ii + 0.5) / height

    def _slices(self, u0: float, u1: float, v0: float, v1: float) -> tuple[slice, slice]:
        rows = slice(max(0, round((1.0 - v1) * self.h)), min(self.h, round((1.0 - v0) * self.h)))
        cols = slice(max(0, round(u0 * self.w)), min(self.w, round(u1 * self.w)))
        return rows, cols

    def rect(self, u0: float, u1: float, v0: float, v1: float, colour: Colour) -> None:
        self.img[self._slices(u0, u1, v0, v1)] = colour

    def where(self, mask: np.ndarray, colour: Colour) -> None:
        self.img[mask] = colour

    def ellipse(self, cu: float, cv: float, ru: float, rv: float, colour: Colour) -> None:
        self.where(((self.u - cu) / ru) ** 2 + ((self.v - cv) / rv) ** 2 <= 1.0, colour)

    def stripes(self, period: int, duty: float, colour: Colour, along: str = "u",
                region: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 1.0)) -> None:
        """Stripes ``period`` texels apart across ``along`` ("u": vertical stripes), inside ``region``."""
        coord = self.u * self.w if along == "u" else self.v * self.h
        u0, u1, v0, v1 = region
        inside = (self.u >= u0) & (self.u < u1) & (self.v >= v0) & (self.v < v1)
        self.where(inside & ((coord % period) < duty * period), colour)

    def text(self, rng: np.random.Generator, u0: float, u1: float, v0: float, v1: float, colour: Colour,
             line: int = 12, letter: tuple[int, int] = (3, 6)) -> None:
        """Text-like marks: lines of words, each word a run of letter blocks 1–2 texels apart with a few
        ascenders, so they read as print rather than as flat bars."""
        rows, cols = self._slices(u0, u1, v0, v1)
        y = rows.start
        while y + line <= rows.stop:
            x = cols.start + int(rng.integers(0, 6))
            end = cols.stop - int(rng.integers(0, max(1, (cols.stop - cols.start) // 3)))
            while x < end:
                for _ in range(int(rng.integers(2, 8))):
                    lw = int(rng.integers(*letter))
                    if x + lw > end:
                        break
                    top = y + (1 if rng.uniform() < 0.25 else 3)
                    self.img[top:y + line - 3, x:x + lw] = colour
                    x += lw + int(rng.integers(1, 3))
                x += int(rng.integers(5, 9))
            y += line

    def barcode(self, rng: np.random.Generator, u0: float, u1: float, v0: float, v1: float,
                paper: Colour = (0.97, 0.95, 0.88), bars: tuple[int, int] = (2, 6),
                gaps: tuple[int, int] = (2, 5)) -> None:
        """A white patch with black bars ``bars`` texels wide (upper bound excluded), ``gaps`` apart:
        by default 2–5 texels, a few pixels in the render; 1–2 where a tile has texels to spare."""
        rows, cols = self._slices(u0, u1, v0, v1)
        self.img[rows, cols] = paper
        x = cols.start + 3
        while x < cols.stop - 6:
            bar = int(rng.integers(*bars))
            self.img[rows.start + 3:rows.stop - 3, x:x + bar] = (0.05, 0.05, 0.06)
            x += bar + int(rng.integers(*gaps))

    def _glyph_grid(self, sideways: bool) -> tuple[float, float, int, int]:
        """Cells per texel across and along a line of text, and the grid's (width, height) in cells:
        physically square cells, as fine as the tile's coarser axis (``aspect``)."""
        ku, kv = (1.0, 1.0 / self.aspect) if self.aspect >= 1.0 else (self.aspect, 1.0)
        gw, gh = max(1, round(self.w * ku)), max(1, round(self.h * kv))
        return ((ku, kv) if sideways else (kv, ku)) + (gw, gh)

    def text_length(self, text: str, height: float, font: int = cv2.FONT_HERSHEY_SIMPLEX, thickness: int = 1,
                    sideways: bool = False) -> float:
        """The length in texels ``lettering`` gives ``text``."""
        k_across, k_along, _, _ = self._glyph_grid(sideways)
        scale = height * k_across / cv2.getTextSize("H", font, 1.0, thickness)[0][1]
        return cv2.getTextSize(text, font, scale, thickness)[0][0] / k_along

    def lettering(self, text: str, u: float, v: float, height: float, colour: Colour, align: str = "left",
                  font: int = cv2.FONT_HERSHEY_SIMPLEX, thickness: int = 1, sideways: bool = False) -> None:
        """Real letters in a Hershey font, capitals ``height`` texels tall, baseline through (u, v) with
        the text's left end, centre or right end there (``align``). Drawn without anti-aliasing, so
        1-texel strokes stay crisp: at 4–6 texels the glyphs are the finest print a tile can carry.
        ``sideways`` runs the text along +v, upright on a revolved part laid along +x
        (``rotation("z", -90.0)``); ``height`` then counts texels along u. On a stretched tile
        (``aspect`` ≠ 1) the text is drawn on a grid of physically square cells and widened onto the
        tile, so letters keep their shape."""
        k_across, _, gw, gh = self._glyph_grid(sideways)
        scale = height * k_across / cv2.getTextSize("H", font, 1.0, thickness)[0][1]
        shift = {"left": 0.0, "centre": 0.5, "right": 1.0}[align] * cv2.getTextSize(text, font, scale, thickness)[0][0]
        if sideways:  # drawn on the transposed grid: text x along v, text down along u
            mask = np.zeros((gw, gh), np.uint8)
            origin = (round(v * gh - shift), round(u * gw))
        else:
            mask = np.zeros((gh, gw), np.uint8)
            origin = (round(u * gw - shift), round((1.0 - v) * gh))
        cv2.putText(mask, text, origin, font, scale, 255, thickness, cv2.LINE_8)
        if sideways:
            mask = np.ascontiguousarray(np.rot90(mask))
        if mask.shape != (self.h, self.w):
            mask = cv2.resize(mask, (self.w, self.h), interpolation=cv2.INTER_NEAREST)
        self.where(mask > 0, colour)

    def small_print(self, rng: np.random.Generator, u0: float, u1: float, v0: float, v1: float, colour: Colour,
                    height: float = 5.0, line: float = 7.0, sideways: bool = False) -> None:
        """A block of small print (ingredients, instructions): ragged lines ``line`` texels apart of
        random lower-case words in real letters ``height`` texels tall (Hershey plain), finer than
        ``text``'s blocks can go. ``sideways`` as in ``lettering``."""
        across, down = ((v0, v1), (u0, u1)) if sideways else ((u0, u1), (v0, v1))
        size = self.h if sideways else self.w
        step = line / (self.w if sideways else self.h)
        # Down the block: decreasing v for upright text, increasing u for sideways text.
        pos = down[0] + step if sideways else down[1] - step
        while (pos <= down[1]) if sideways else (pos >= down[0]):
            end = across[1] - rng.uniform(0.0, 0.3) * (across[1] - across[0])
            words: list[str] = []
            while True:
                word = "".join(chr(97 + int(c)) for c in rng.integers(0, 26, int(rng.integers(2, 9))))
                width = self.text_length(" ".join([*words, word]), height, cv2.FONT_HERSHEY_PLAIN, sideways=sideways)
                if across[0] + width / size > end:
                    break
                words.append(word)
            if words:
                at = (pos, across[0]) if sideways else (across[0], pos)
                self.lettering(" ".join(words), *at, height, colour, font=cv2.FONT_HERSHEY_PLAIN, sideways=sideways)
            pos += step if sideways else -step

    def tartan(self, period_u: float, period_v: float, dark: Colour, accent: Colour | None = None,
               region: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 1.0), every: int = 3,
               coords: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """A woven check over what is painted: bands of ``dark`` warp (across u) and weft (across v)
        half a period wide, ``period_u`` × ``period_v`` texels (floats: ``fine_period`` sizes them to a
        few render pixels). One set alone shows half mixed with the ground (the weave lets it through),
        both together in full; every ``every``-th period a thin ``accent`` line each way makes it a
        tartan, ``accent=None`` leaves a gingham. ``coords`` (two arrays shaped like the tile, in the
        periods' units) lay the check on other coordinates than the texel grid: a cloth over a pole
        checked in world x, z instead of converging u lines."""
        x, y = coords if coords is not None else (self.u * self.w, self.v * self.h)
        cu, cv = x / period_u, y / period_v
        warp, weft = (cu % 1.0) < 0.5, (cv % 1.0) < 0.5
        u0, u1, v0, v1 = region
        inside = (self.u >= u0) & (self.u < u1) & (self.v >= v0) & (self.v < v1)
        dark_arr = np.asarray(dark, dtype=np.float32)
        mixed = np.where((warp & weft)[..., None], dark_arr, 0.5 * self.img + 0.5 * dark_arr)
        self.img = np.where((inside & (warp | weft))[..., None], mixed, self.img).astype(np.float32)
        if accent is not None:  # a line a sixth of a period wide, in the middle of every few light bands
            line = (((np.floor(cu) % every == 0) & (np.abs(cu % 1.0 - 0.75) < 1 / 12))
                    | ((np.floor(cv) % every == 0) & (np.abs(cv % 1.0 - 0.75) < 1 / 12)))
            self.where(inside & line, accent)

    def knurl(self, period_u: float, period_v: float, region: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 1.0),
              depth: float = 0.45) -> None:
        """Diamond knurling over what is painted: grooves at ±45° (in render pixels, given periods
        that are equal there) cut the surface into diamonds, each a four-facet pyramid lit from the
        upper left. The facets' brightness and the dark grooves make the diamonds read at ~3 px,
        where a flat colour pattern of that size would blur into one tone."""
        a = self.u * self.w / period_u + self.v * self.h / period_v
        b = self.u * self.w / period_u - self.v * self.h / period_v
        da, db = a % 1.0 - 0.5, b % 1.0 - 0.5
        facet = np.where(np.abs(da) > np.abs(db), np.where(da > 0, 1.0 + 0.5 * depth, 1.0 - 0.3 * depth),
                         np.where(db > 0, 1.0 + 0.15 * depth, 1.0 - 0.7 * depth))
        groove = np.maximum(np.abs(da), np.abs(db)) > 0.4
        shade = np.where(groove, 1.0 - depth, facet).astype(np.float32)
        u0, u1, v0, v1 = region
        inside = (self.u >= u0) & (self.u < u1) & (self.v >= v0) & (self.v < v1)
        self.img = np.where(inside[..., None], self.img * shade[..., None], self.img).astype(np.float32)

    def basket_weave(self, rng: np.random.Generator, period_u: float, period_v: float, stake: Colour,
                     weaver: Colour, region: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 1.0)) -> None:
        """Plain basket weave: weavers running around (``period_v`` texels pitch) pass over and under
        upright stakes (``period_u``), one step out of phase on each row. Each strand is shaded round
        (bright middle, dark edges), a weaver darkens where it dives under a stake and each strand
        gets its own slight tint, so the over/under reads at ~3 render px, not as a flat check."""
        cu, cv = self.u * self.w / period_u, self.v * self.h / period_v
        i, j = np.floor(cv).astype(np.int64), np.floor(cu).astype(np.int64)
        fu, fv = cu % 1.0, cv % 1.0
        over = (i + j) % 2 == 0  # the weaver lies on top of the stake here
        rows_tint = 1.0 + 0.08 * rng.standard_normal(int(i.max() - i.min()) + 1)
        cols_tint = 1.0 + 0.06 * rng.standard_normal(int(j.max() - j.min()) + 1)
        weaver_shade = (0.45 + 0.55 * np.sin(math.pi * fv)) * (0.7 + 0.3 * np.sin(math.pi * fu)) \
            * rows_tint[i - i.min()]
        stake_shade = (0.45 + 0.55 * np.sin(math.pi * fu)) * (0.75 + 0.25 * np.sin(math.pi * fv)) \
            * cols_tint[j - j.min()]
        woven = np.where(over[..., None], np.asarray(weaver, np.float32) * weaver_shade[..., None],
                         np.asarray(stake, np.float32) * stake_shade[..., None])
        u0, u1, v0, v1 = region
        inside = (self.u >= u0) & (self.u < u1) & (self.v >= v0) & (self.v < v1)
        self.img = np.where(inside[..., None], woven, self.img).astype(np.float32)

    def grain(self, rng: np.random.Generator, fine: float = 0.06, coarse: float = 0.08, cells: int = 6) -> None:
        """Multiplicative noise: smooth blotches (``cells`` across) plus per-2-texel speckle."""
        blotch = cv2.resize(rng.standard_normal((cells, cells)).astype(np.float32), (self.w, self.h),
                            interpolation=cv2.INTER_CUBIC)
        speck = rng.standard_normal(((self.h + 1) // 2, (self.w + 1) // 2)).astype(np.float32)
        speck = np.repeat(np.repeat(speck, 2, axis=0), 2, axis=1)[:self.h, :self.w]
        self.img *= (1.0 + coarse * blotch + fine * speck)[..., None]

    def tile(self) -> np.ndarray:
        """The content edge-padded by ``MARGIN`` texels: one clean atlas tile."""
        img = np.clip(self.img, 0.0, 1.0)
        return np.pad(img, ((MARGIN, MARGIN), (MARGIN, MARGIN), (0, 0)), mode="edge")


def box_texture(canvases: dict[str, Canvas]) -> np.ndarray:
    """Six face canvases laid out as ``box_part`` expects (3×2 tiles, ``BOX_FACE_NAMES`` order)."""
    out = np.zeros((2 * TILE, 3 * TILE, 3), dtype=np.float32)
    for k, name in enumerate(BOX_FACE_NAMES):
        col, row = k % 3, k // 3
        out[row * TILE:(row + 1) * TILE, col * TILE:(col + 1) * TILE] = canvases[name].tile()
    return out


def sector_texture(canvases: Sequence[Canvas]) -> np.ndarray:
    """One tile per sector of a revolved part, side by side (``revolved_part(..., sectors=k)``):
    canvas 0 faces the camera, canvas k / 2 the back."""
    return np.concatenate([canvas.tile() for canvas in canvases], axis=1)


def px_per_unit(long_side: float) -> float:
    """Pixels of a ``BENCH_SIZE`` render per unit, seen face-on, of an object whose longer side is
    ``long_side`` units before normalisation (which puts that side on ``FRAME_FILL`` of the frame)."""
    return FRAME_FILL * BENCH_SIZE / long_side


def texels_per_px(span: float, long_side: float) -> float:
    """Texels per pixel of a ``BENCH_SIZE`` render where a tile's ``CONTENT`` texels cover ``span`` units
    of surface seen face-on (``px_per_unit``)."""
    return CONTENT / (span * px_per_unit(long_side))


def fine_period(span: float, long_side: float, px: float = FINE_PERIOD_PX) -> float:
    """A period in texels that is about ``px`` pixels of a ``BENCH_SIZE`` render (``texels_per_px``),
    rounded so a whole number of periods fills the tile: the pattern runs on unbroken across a
    revolved part's seam and from one sector's tile to the next."""
    return CONTENT / max(1, round(CONTENT / (px * texels_per_px(span, long_side))))


def plain_box_texture(rng: np.random.Generator, colour: Colour, detail: Callable[[Canvas], None]) -> np.ndarray:
    canvases = {}
    for name in BOX_FACE_NAMES:
        canvas = Canvas(colour)
        detail(canvas)
        canvas.grain(rng)
        canvases[name] = canvas
    return box_texture(canvases)
