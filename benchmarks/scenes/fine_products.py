"""The fine products: a food tin, a gift box, a woven basket and a torch, whose appearance lives in the
high spatial-frequency band (small print, a tartan, a basket weave, a diamond knurl at periods of
``FINE_PERIOD_PX`` px in a ``BENCH_SIZE`` render). Their backs differ from their fronts and each has
a thin part (a ring pull, ribbon loops, a cane handle, a lanyard ring). ``FINE_BUILDERS`` maps each
scene name to its builder."""

from __future__ import annotations

import math
from collections.abc import Callable

import cv2
import numpy as np

from benchmarks.scenes.painting import (
    FINE_PERIOD_PX,
    Canvas,
    Colour,
    box_texture,
    darker,
    fine_period,
    hsv,
    luma,
    palette,
    plain_box_texture,
    px_per_unit,
    sector_texture,
    texels_per_px,
    with_luma,
)
from benchmarks.scenes.parts import (
    BOX_FACE_NAMES,
    CONTENT,
    Part,
    arc,
    arc_v,
    box_part,
    on_axis,
    place,
    revolved_part,
    rotation,
    torus_part,
)

_PRODUCTS = ("TOMATO SOUP", "BAKED BEANS", "SWEET CORN", "PEACHES", "CHICKPEAS", "PEAR HALVES", "LENTIL SOUP",
             "APRICOTS")
_BRANDS = ("Harvest", "Oakfield", "Marlow", "Sunvale", "Brookes", "Greystone", "Alder", "Northway")
_NUTRIENTS = ("Energy", "Fat", "- saturates", "Carbohydrate", "- sugars", "Fibre", "Protein", "Salt")
_INK = (0.06, 0.06, 0.07)


def _tin(rng: np.random.Generator) -> list[Part]:
    radius, height = 0.36 * rng.uniform(0.92, 1.08), 1.0 * rng.uniform(0.94, 1.06)
    bead, sink = 0.012, 0.025
    # Double-seamed rims stand proud of the wall; the lid is countersunk below the top rim.
    profile = [(0.0, 0.0), (radius - 0.02, 0.0), (radius + bead, 0.02), (radius + bead, 0.045), (radius, 0.06),
               (radius, height - 0.06), (radius + bead, height - 0.045), (radius + bead, height),
               (radius - 0.02, height), (radius - 0.03, height - sink), (0.0, height - sink)]
    # The base is seldom seen: its texels go to the label (the lid keeps half its share for its rings).
    weights = [0.15, 1, 1, 1, 1, 1, 1, 1, 1, 0.5]
    v = arc_v(profile, weights)
    lo, hi = v[4], v[5]  # the label covers the straight wall
    span = hi - lo
    wall_span = (height - 0.12) / span  # units of wall the tile's height would cover
    per_v = texels_per_px(wall_span, height)  # texels per render px up the label
    aspect = math.pi * radius / wall_span  # two sectors: half a turn per tile
    metal = hsv(rng.uniform(0.1, 0.14), rng.uniform(0.0, 0.35), rng.uniform(0.7, 0.82))  # tinplate or gold lacquer
    brand_c, paper_hue, fruit_c, ink_c = palette(rng, 4, v=(0.55, 0.8))
    paper = with_luma(tuple(0.3 * c + 0.62 for c in paper_hue), 0.84)  # type: ignore[arg-type]
    brand_c = with_luma(brand_c, rng.uniform(0.5, 0.62))
    ink_c = with_luma(ink_c, 0.22)
    product, brand = str(rng.choice(_PRODUCTS)), str(rng.choice(_BRANDS))
    pu, pv = fine_period(math.pi * radius, height), fine_period(wall_span, height)
    band_lo, band_hi = hi - 0.3 * span, hi - 0.06 * span
    small, line = max(4.0, 2.0 * per_v), max(6.0, 3.0 * per_v)  # small print: 2 px capitals, 3 px lines

    def metal_and_label(canvas: Canvas) -> None:
        canvas.rect(0.0, 1.0, lo, hi, paper)  # type: ignore[arg-type]
        # The paper is printed with fine pinstripes, the brand band with a halftone screen.
        canvas.stripes(pu, 0.4, darker(paper, 0.62), "u", (0.0, 1.0, lo, band_lo))  # type: ignore[arg-type]
        canvas.rect(0.0, 1.0, band_lo, band_hi, brand_c)
        dots = ((canvas.u * canvas.w / pu) % 1.0 - 0.5) ** 2 + ((canvas.v * canvas.h / pv) % 1.0 - 0.5) ** 2
        canvas.where((dots < 0.12) & (canvas.v > band_lo) & (canvas.v < band_hi), darker(brand_c, 0.45))
        for edge in (band_lo - 3 / CONTENT, band_hi + 2 / CONTENT, lo + 0.04 * span):  # thin rules
            canvas.rect(0.0, 1.0, edge, edge + 1 / CONTENT, ink_c)
        for k in (1, 2, 7, 8):  # rolled seams: fine grooves around
            canvas.stripes(pv, 0.5, darker(metal, 0.65), "v", (0.0, 1.0, v[k], v[k + 1]))
        canvas.stripes(3, 0.4, darker(metal, 0.7), "v", (0.0, 1.0, v[9], v[10] - 0.01))  # lid rings

    front = Canvas(metal, aspect=aspect)
    metal_and_label(front)
    white = (0.98, 0.97, 0.92)
    front.lettering(product, 0.5, band_lo + 0.07 * span, 6.5 * per_v, white, "centre", cv2.FONT_HERSHEY_DUPLEX, 2)
    front.lettering(brand, 0.5, band_hi - 0.065 * span, 3.0 * per_v, white, "centre", cv2.FONT_HERSHEY_TRIPLEX)
    # The picture: a few fruit on a plate, shaded round with a highlight and a leaf each.
    pic_v, fr = lo + 0.44 * span, 0.065
    front.ellipse(0.5, pic_v - 0.12 * span, 0.21, 0.05 * span, (0.96, 0.96, 0.94))
    front.ellipse(0.5, pic_v - 0.12 * span, 0.18, 0.035 * span, (0.84, 0.85, 0.86))
    for k, du in enumerate(sorted(rng.uniform(-0.11, 0.11, 3))):
        cu, cv = 0.5 + du, pic_v + (0.03 if k == 1 else -0.02) * span
        dist = ((front.u - cu) / fr) ** 2 + ((front.v - cv) / (fr * aspect)) ** 2
        shade = np.clip(1.15 - 0.5 * dist - 3.0 * (front.u - cu), 0.45, 1.25)[..., None]
        front.img = np.where((dist <= 1.0)[..., None], np.asarray(fruit_c, np.float32) * shade,
                             front.img).astype(np.float32)
        front.ellipse(cu - 0.3 * fr, cv + 0.35 * fr * aspect, 0.15 * fr, 0.25 * fr * aspect, (0.97, 0.95, 0.9))
        front.ellipse(cu + 0.25 * fr, cv + 1.1 * fr * aspect, 0.35 * fr, 0.2 * fr * aspect, (0.2, 0.5, 0.15))
    front.lettering(f"in {rng.choice(('rich', 'light', 'natural'))} juice", 0.5, lo + 0.2 * span, 2.6 * per_v,
                    ink_c, "centre", cv2.FONT_HERSHEY_SIMPLEX)
    front.lettering(f"{int(rng.integers(2, 9)) * 50} g", 0.75, lo + 0.075 * span, 2.6 * per_v, ink_c, "centre")
    front.small_print(rng, 0.2, 0.45, lo + 0.06 * span, lo + 0.15 * span, ink_c, small, line)

    back = Canvas(metal, aspect=aspect)
    metal_and_label(back)
    back.lettering(f"{brand} {product.lower()}", 0.5, band_lo + 0.09 * span, 3.2 * per_v, white, "centre")
    # The nutrition table: a title and ruled rows of names and values, on white.
    row = line / CONTENT
    top = band_lo - 0.05 * span
    bottom = top - 1.6 * row - len(_NUTRIENTS) * row
    back.rect(0.3, 0.7, bottom - 0.3 * row, top, (0.98, 0.98, 0.96))
    back.lettering("Nutrition", 0.32, top - 1.2 * row, 1.2 * small, _INK, font=cv2.FONT_HERSHEY_DUPLEX)
    back.lettering("per 100 g", 0.68, top - 1.2 * row, small, _INK, "right", cv2.FONT_HERSHEY_PLAIN)
    back.rect(0.3, 0.7, top - 1.6 * row, top - 1.6 * row + 2 / CONTENT, _INK)
    for k, nutrient in enumerate(_NUTRIENTS):
        base = top - 1.6 * row - (k + 1) * row
        value = f"{rng.uniform(0.1, 40.0):.1f} g" if k else f"{int(rng.integers(150, 1800))} kJ"
        back.lettering(nutrient, 0.32, base + 0.2 * row, small, _INK, font=cv2.FONT_HERSHEY_PLAIN)
        back.lettering(value, 0.68, base + 0.2 * row, small, _INK, "right", cv2.FONT_HERSHEY_PLAIN)
        back.rect(0.3, 0.7, base, base + 1 / CONTENT, (0.35, 0.35, 0.35))
    back.small_print(rng, 0.04, 0.27, lo + 0.08 * span, top, ink_c, small, line)  # ingredients
    back.small_print(rng, 0.73, 0.96, lo + 0.3 * span, top, ink_c, small, line)  # cooking instructions
    back.barcode(rng, 0.74, 0.94, lo + 0.07 * span, lo + 0.26 * span, bars=(1, 4), gaps=(1, 3))
    back.lettering(" ".join(str(int(d)) for d in rng.integers(0, 10, 7)), 0.84, lo + 0.045 * span, small, _INK,
                   "centre", cv2.FONT_HERSHEY_PLAIN)
    for canvas in (front, back):
        canvas.grain(rng, fine=0.03, coarse=0.03)
    body = revolved_part(on_axis(profile), sector_texture([front, back]), sectors=2, weights=weights)

    ring_tex = Canvas((0.9, 0.9, 0.92))  # bright aluminium against the lid
    ring_tex.stripes(3, 0.5, (0.6, 0.6, 0.64), "v")
    ring_tex.grain(rng)
    major = 0.21 * radius * rng.uniform(0.9, 1.1)
    # The ring pull lies on the lid towards the front, sunk a little into it.
    ring = place(torus_part(major, 0.009, ring_tex.tile(), around=32, tube=10), rotate=rotation("x", 90.0),
                  translate=(0.0, height - sink + 0.005, 0.5 * radius))
    return [body, ring]


def _gift(rng: np.random.Generator) -> list[Part]:
    w, h, d = 1.0 * rng.uniform(0.92, 1.08), 0.58 * rng.uniform(0.9, 1.1), 0.75 * rng.uniform(0.9, 1.1)
    lid_h, lip = 0.16 * rng.uniform(0.9, 1.1), 0.015
    ground, dark_hue, ribbon_c, seal_c, lid_hue = palette(rng, 5, v=(0.55, 0.85))
    dark = darker(dark_hue, 0.45)  # the check must differ in brightness, not only in hue
    lid_c = with_luma(lid_hue, luma(ground))  # the lid: another hue, as bright
    accent = tuple(0.4 * c + 0.6 for c in seal_c)
    loop = 0.12 * rng.uniform(0.9, 1.1)
    long_side = max(w + 2 * lip, h + lip + 2 * loop)
    lw, ld = w + 2 * lip, d + 2 * lip  # the lid overhangs the body

    def face(span_u: float, span_v: float, colour: Colour = ground) -> Canvas:
        canvas = Canvas(colour, aspect=span_u / span_v)
        canvas.tartan(fine_period(span_u, long_side), fine_period(span_v, long_side), dark, accent)  # type: ignore[arg-type]
        return canvas

    def ribbon(canvas: Canvas, along: str, span_across: float, span_along: float) -> None:
        """A satin band 0.1 units wide across the face's middle, ``along`` u or v, with grosgrain ribs
        across it ~3 px apart and darker selvedges."""
        half = 0.05 / span_across
        region = (0.5 - half, 0.5 + half, 0.0, 1.0) if along == "v" else (0.0, 1.0, 0.5 - half, 0.5 + half)
        canvas.rect(*region, ribbon_c)
        canvas.stripes(fine_period(span_along, long_side), 0.4, darker(ribbon_c, 0.7), "v" if along == "v" else "u",
                       region)
        edge = 1.5 / CONTENT
        for at in (0.5 - half, 0.5 + half - edge):
            canvas.rect(*((at, at + edge, 0.0, 1.0) if along == "v" else (0.0, 1.0, at, at + edge)),
                        darker(ribbon_c, 0.5))

    body = {name: face(span, h) for name, span in (("front", w), ("right", d), ("back", w), ("left", d))}
    per = texels_per_px(h, long_side)  # texels per px up the side faces
    shown = (h + lip - lid_h) / h  # the lid hides the body's faces above this v
    # Front: a round foil seal with sunburst ridges ~3 px apart, the maker's name and a date.
    front = body["front"]
    radius = 0.36 * shown * h  # units
    cu, cv = 0.5, 0.5 * shown
    front.ellipse(cu, cv, 1.08 * radius / w, 1.08 * radius / h, darker(seal_c, 0.55))
    front.ellipse(cu, cv, radius / w, radius / h, seal_c)
    dx, dy = (front.u - cu) * w, (front.v - cv) * h
    rays = 2 * round(math.pi * radius * px_per_unit(long_side) / FINE_PERIOD_PX)
    ray = (np.arctan2(dy, dx) * rays / (2 * math.pi)) % 1.0 < 0.5
    ring = (dx ** 2 + dy ** 2 < radius ** 2) & (dx ** 2 + dy ** 2 > (0.72 * radius) ** 2)
    front.where(ring & ray, darker(seal_c, 0.65))
    name = str(rng.choice(_BRANDS))
    front.lettering(name, cu, cv - 0.02 * shown, 2.4 * per, _INK, "centre", cv2.FONT_HERSHEY_TRIPLEX)
    front.lettering(f"EST. {int(rng.integers(1890, 2010))}", cu, cv - 0.2 * shown, 1.6 * per, _INK, "centre",
                    cv2.FONT_HERSHEY_PLAIN)
    # Back: a printed label: "To" and "From" lines and a message in small print, a barcode and the
    # maker's address.
    back = body["back"]
    small, line = max(4.0, 2.0 * per), max(6.0, 3.0 * per)
    back.rect(0.14, 0.86, 0.1 * shown, 0.92 * shown, (0.7, 0.68, 0.62))
    back.rect(0.15, 0.85, 0.115 * shown, 0.905 * shown, (0.94, 0.92, 0.85))
    for label, at in (("To:", 0.8 * shown), ("From:", 0.67 * shown)):
        back.lettering(label, 0.18, at, 2.4 * per, _INK, font=cv2.FONT_HERSHEY_SIMPLEX)
        back.rect(0.18 + back.text_length(label, 2.4 * per) / CONTENT + 0.02, 0.56, at, at + 1 / CONTENT, _INK)
    back.small_print(rng, 0.18, 0.56, 0.14 * shown, 0.58 * shown, (0.2, 0.2, 0.25), small, line)
    back.barcode(rng, 0.62, 0.82, 0.5 * shown, 0.84 * shown, (0.94, 0.92, 0.85), bars=(1, 4), gaps=(1, 3))
    back.small_print(rng, 0.62, 0.83, 0.14 * shown, 0.45 * shown, (0.2, 0.2, 0.25), small, line)
    body["top"] = Canvas(darker(ground, 0.9))  # under the lid
    body["bottom"] = Canvas(darker(ground, 0.9))
    for canvas in body.values():
        canvas.grain(rng, fine=0.03, coarse=0.04)
    base = place(box_part((w, h, d), box_texture(body)), translate=(0.0, h / 2, 0.0))

    lid = {}
    for name, span_u, span_v in (("front", lw, lid_h), ("right", ld, lid_h), ("back", lw, lid_h),
                                 ("left", ld, lid_h), ("top", lw, ld), ("bottom", lw, ld)):
        canvas = face(span_u, span_v, lid_c)
        if name != "bottom":
            ribbon(canvas, "v", span_u, span_v)
        if name == "top":
            ribbon(canvas, "u", span_v, span_u)
        canvas.grain(rng, fine=0.03, coarse=0.04)
        lid[name] = canvas
    top = h + lip
    cover = place(box_part((lw, lid_h, ld), box_texture(lid)), translate=(0.0, top - lid_h / 2, 0.0))

    # The bow: two thin satin loops leaning out from a knot, facing the camera.
    bow_tex = Canvas(ribbon_c)
    bow_tex.stripes(3, 0.4, darker(ribbon_c, 0.7), "u")
    bow_tex.grain(rng)
    bow = bow_tex.tile()
    lean = rng.uniform(30.0, 45.0)
    parts = [base, cover]
    for side in (-1, 1):
        tilt = math.radians(lean)
        centre = (side * 0.92 * loop * math.sin(tilt), top + 0.92 * loop * math.cos(tilt), 0.0)
        parts.append(place(torus_part(loop, 0.011, bow, around=40, tube=10), rotate=rotation("z", -side * lean),
                            translate=centre))
    knot = plain_box_texture(rng, darker(ribbon_c, 0.85), lambda c: c.stripes(8, 0.4, darker(ribbon_c, 0.6)))
    parts.append(place(box_part((0.07, 0.05, 0.06), knot), translate=(0.0, top + 0.015, 0.0)))
    return parts


def _basket(rng: np.random.Generator) -> list[Part]:
    top_r, rim_h = 0.45 * rng.uniform(0.95, 1.05), 0.42 * rng.uniform(0.92, 1.08)
    base_r, bead, dome = 0.72 * top_r, 0.022, 0.04 * rng.uniform(0.8, 1.2)
    inner = top_r - 2 * bead
    cloth = [(inner * math.cos(a), rim_h - 0.03 + dome * math.sin(a) ** 1.5) for a in np.linspace(0.0, math.pi / 2, 9)]
    profile = on_axis([(0.0, 0.0), (base_r - 0.04, 0.0), *arc(base_r - 0.04, 0.04, 0.04, -90.0, 0.0, 3)[1:],
                        (top_r, rim_h), *arc(top_r - bead, rim_h, bead, 0.0, 180.0, 6)[1:],
                        (inner, rim_h - 0.03), *cloth[1:]])
    # The base and the cloth take a smaller share of v: the woven wall gets the texels.
    weights = [0.3] + [1.0] * (len(profile) - 10) + [0.6] * 8
    v = arc_v(profile, weights)
    wall_lo, wall_hi = v[4], v[5]  # profile points 4 and 5 bound the straight flared wall
    rim_hi = v[12]  # the rim bead runs from v[5] to v[12], the cloth from v[13] to the pole
    major = 0.89 * top_r  # the handle
    long_side = max(2 * top_r, 2 * major + 0.03)
    wall_len = math.hypot(top_r - base_r, rim_h - 0.04)
    span_u = 2 * math.pi * (top_r + base_r) / 2 / 4  # four sectors: a quarter turn per tile
    span_v = wall_len / (wall_hi - wall_lo)
    willow = hsv(rng.uniform(0.07, 0.12), rng.uniform(0.4, 0.6), rng.uniform(0.62, 0.82))  # natural cane
    stake = darker(willow, 0.8)
    dyed, cloth_c, tag_c, stain = palette(rng, 4, s=(0.5, 0.85), v=(0.4, 0.75))
    pale = with_luma(tuple(0.5 * x + 0.5 for x in dyed), 0.8)  # type: ignore[arg-type]  # the back's band
    dyed = with_luma(dyed, 0.35)
    stain = with_luma(stain, 0.6 * luma(willow))  # the foot is dipped in a darker stain
    pu, pv = fine_period(span_u, long_side), fine_period(span_v, long_side)
    check = FINE_PERIOD_PX / px_per_unit(long_side)  # ~3 px in world units
    foot = wall_lo + 0.4 * (wall_hi - wall_lo)  # the base and the lowest rows are stained
    band = wall_lo + 0.55 * (wall_hi - wall_lo)  # dyed rows above
    canvases = []
    for k in range(4):
        c = Canvas(willow)
        c.basket_weave(rng, pu, pv, stake, willow, (0.0, 1.0, 0.0, v[5]))
        c.basket_weave(rng, pu, pv, darker(stain, 0.8), stain, (0.0, 1.0, 0.0, foot))
        # The rim: cane wrapped round the bead, diagonal turns ~3 px apart.
        turns = (c.u * c.w + c.v * c.h) / pu
        c.where((c.v >= v[5]) & (c.v < rim_hi) & (turns % 1.0 < 0.4), darker(willow, 0.55))
        # The cloth: a gingham napkin tucked into the rim, checked in world x, z.
        r = np.interp(c.v, v[13:], [p[0] for p in profile[13:]])
        theta = math.pi + 2.0 * math.pi * (0.375 + (k + c.u) / 4)  # ``parts._revolve``'s angle of sector k
        c.rect(0.0, 1.0, rim_hi, 1.0, with_luma(tuple(0.3 * x + 0.7 for x in cloth_c), 0.75))  # type: ignore[arg-type]
        c.tartan(check, check, with_luma(cloth_c, 0.22), region=(0.0, 1.0, rim_hi, 1.0),
                 coords=(r * np.sin(theta), r * np.cos(theta)))
        # A dark band round the front and sides, a wide pale one across the back (k = 2).
        colour, rows = (pale, 6) if k == 2 else (dyed, 3)
        c.basket_weave(rng, pu, pv, darker(colour, 0.85), colour, (0.0, 1.0, band, band + rows * pv / CONTENT))
        c.grain(rng, fine=0.04, coarse=0.05)
        canvases.append(c)
    body = revolved_part(profile, sector_texture(canvases), sectors=4, weights=weights)

    # A thin cane handle: a whole ring whose lower half is buried in the basket under the cloth.
    handle_tex = Canvas(darker(willow, 0.9))
    wrap = (handle_tex.u * handle_tex.w / 3.0 + handle_tex.v * 2.0) % 1.0
    handle_tex.where(wrap < 0.4, darker(willow, 0.55))
    handle_tex.grain(rng)
    handle = place(torus_part(major, 0.015, handle_tex.tile(), around=64, tube=10), translate=(0.0, major, 0.0))

    # A leather tag with the maker's name, flat against the back wall.
    tw, th = 0.2, 0.11
    tag = {name: Canvas(tag_c, aspect=tw / th) for name in BOX_FACE_NAMES}
    outside = tag["back"]  # the face looking away from the basket (towards −z)
    outside.rect(0.06, 0.94, 0.1, 0.9, darker(tag_c, 0.8))
    outside.stripes(8, 0.5, darker(tag_c, 0.45), "u", (0.08, 0.92, 0.14, 0.18))  # stitching
    outside.stripes(8, 0.5, darker(tag_c, 0.45), "u", (0.08, 0.92, 0.82, 0.86))
    outside.lettering(str(rng.choice(_BRANDS)).upper(), 0.5, 0.47, 60, (0.95, 0.9, 0.75), "centre",
                      cv2.FONT_HERSHEY_DUPLEX, 3)
    outside.lettering("HANDWOVEN", 0.5, 0.27, 30, (0.95, 0.9, 0.75), "centre", cv2.FONT_HERSHEY_PLAIN, 2)
    for canvas in tag.values():
        canvas.grain(rng, fine=0.04)
    slope = math.degrees(math.atan2(top_r - base_r, rim_h))
    tag_y = 0.55 * rim_h
    wall_r = base_r + (top_r - base_r) * tag_y / rim_h
    tag_part = place(box_part((tw, th, 0.008), box_texture(tag)), rotate=rotation("x", -slope),
                      translate=(0.0, tag_y, -(wall_r - 0.001)))
    return [body, handle, tag_part]


def _torch(rng: np.random.Generator) -> list[Part]:
    body_r, head_r = 0.15 * rng.uniform(0.94, 1.06), 0.22 * rng.uniform(0.94, 1.06)
    tail_len, body_len, head_len = 0.16, 0.8 * rng.uniform(0.92, 1.08), 0.34 * rng.uniform(0.92, 1.08)
    ring_major = 0.07
    long_side = tail_len + body_len + head_len + ring_major
    anodised, accent = palette(rng, 2, s=(0.5, 0.9), v=(0.35, 0.65))
    # Bright enough for the knurl's facets to show (it shades multiplicatively); a light accent.
    anodised, accent = with_luma(anodised, rng.uniform(0.3, 0.45)), with_luma(accent, 0.65)
    white = (0.95, 0.95, 0.92)

    tail_profile = on_axis([(0.0, 0.0), *arc(body_r + 0.005 - 0.02, 0.02, 0.02, -90.0, 0.0, 3),
                             (body_r + 0.005, tail_len), (0.0, tail_len)])
    tv = arc_v(tail_profile)
    tail_tex = Canvas(darker(anodised, 0.85))
    # Grip rings round the tail cap, ~3 px apart, and the rubber switch boot at its end.
    grip = fine_period((tail_len - 0.02) / (tv[-2] - tv[-3]), long_side)
    tail_tex.stripes(grip, 0.45, darker(anodised, 0.45), "v", (0.0, 1.0, tv[-3] + 0.03, tv[-2] - 0.03))
    tail_tex.rect(0.0, 1.0, 0.0, 0.7 * tv[1], (0.16, 0.16, 0.17))  # ridged like a rubber boot
    tail_tex.stripes(fine_period(tail_len / (tv[-3] - tv[0]), long_side), 0.45, (0.07, 0.07, 0.08), "v",
                     (0.0, 1.0, 0.0, 0.7 * tv[1]))
    tail_tex.grain(rng, fine=0.04)
    tail = revolved_part(tail_profile, tail_tex.tile(), around=32)

    y0 = tail_len - 0.01
    body_profile = [(0.0, y0), (body_r, y0), (body_r, y0 + body_len), (0.0, y0 + body_len)]
    weights = [0.2, 1.0, 0.2]  # the ends hide inside the tail cap and the head
    bv = arc_v(body_profile, weights)
    span_v = body_len / (bv[2] - bv[1])
    knurl_hi = bv[1] + 0.68 * (bv[2] - bv[1])  # knurled from the tail; the smooth rest carries the print
    per_u = texels_per_px(math.pi * body_r, long_side)
    pu, pv = fine_period(math.pi * body_r, long_side), fine_period(span_v, long_side)
    sides = []
    for k in range(2):
        c = Canvas(anodised, aspect=math.pi * body_r / span_v)
        c.knurl(pu, pv, (0.0, 1.0, bv[1] + 0.02, knurl_hi), depth=0.65)
        c.stripes(pv, 0.5, darker(anodised, 0.86), "v", (0.0, 1.0, knurl_hi, bv[2]))  # lathe-turned rings
        c.rect(0.0, 1.0, knurl_hi, knurl_hi + 2 / CONTENT, accent)  # an accent ring
        if k == 0:  # the front: the maker's name and the rating, along the smooth part
            mid, room = 0.5 * (knurl_hi + bv[2]), 0.8 * (bv[2] - knurl_hi) * CONTENT  # texels along v
            name = str(rng.choice(_BRANDS)).upper()
            cap = 3.2 * per_u  # ~3 px capitals, smaller where the name would not fit the smooth part
            cap *= min(1.0, room / c.text_length(name, cap, cv2.FONT_HERSHEY_DUPLEX, 2, sideways=True))
            c.lettering(name, 0.55, mid, cap, white, "centre", cv2.FONT_HERSHEY_DUPLEX, 2, sideways=True)
            rating = f"{int(rng.integers(4, 30)) * 50} LM  IPX{int(rng.integers(4, 9))}"
            cap = 1.8 * per_u
            cap *= min(1.0, room / c.text_length(rating, cap, cv2.FONT_HERSHEY_PLAIN, sideways=True))
            c.lettering(rating, 0.66, mid, cap, accent, "centre", cv2.FONT_HERSHEY_PLAIN, sideways=True)
            c.rect(0.38, 0.38 + 1.5 / CONTENT, knurl_hi + 0.05, bv[2] - 0.05, accent)  # a thin rule above
        c.grain(rng, fine=0.03, coarse=0.03)
        sides.append(c)
    body = revolved_part(body_profile, sector_texture(sides), sectors=2, weights=weights)

    h0 = y0 + body_len - 0.02
    head_profile = on_axis([(0.0, h0), (body_r + 0.004, h0), (body_r + 0.004, h0 + 0.04),
                             (head_r, h0 + 0.45 * head_len), (head_r, h0 + 0.85 * head_len),
                             (head_r + 0.012, h0 + 0.88 * head_len), (head_r + 0.012, h0 + head_len),
                             (head_r - 0.02, h0 + head_len), (head_r - 0.03, h0 + head_len - 0.015),
                             (0.0, h0 + head_len - 0.015)])
    head_weights = [0.2, 1, 1, 1, 1, 1, 1, 1, 1.5]
    hv = arc_v(head_profile, head_weights)
    head_arc = float(np.dot(np.linalg.norm(np.diff(np.asarray(head_profile), axis=0), axis=1), head_weights))
    ring_period = fine_period(head_arc, long_side)  # rings ~3 px apart along the profile
    head_tex = Canvas(anodised)
    # Cooling fins round the flare; the cylinder stays smooth; crenellations round the bezel.
    head_tex.stripes(ring_period, 0.45, darker(anodised, 0.5), "v", (0.0, 1.0, hv[2], hv[3]))
    head_tex.stripes(ring_period, 0.5, darker(anodised, 0.86), "v", (0.0, 1.0, hv[3], hv[5]))  # lathe-turned
    head_tex.stripes(fine_period(2 * math.pi * head_r, long_side), 0.5, darker(anodised, 0.5), "u",
                     (0.0, 1.0, hv[5], hv[7]))
    # The lens: reflector rings and the LED in the middle.
    head_tex.rect(0.0, 1.0, hv[8], 1.0, (0.85, 0.87, 0.89))
    head_tex.stripes(ring_period, 0.45, (0.5, 0.52, 0.56), "v", (0.0, 1.0, hv[8], 1.0 - 0.12 * (1.0 - hv[8])))
    head_tex.rect(0.0, 1.0, 1.0 - 0.1 * (1.0 - hv[8]), 1.0, (1.0, 0.93, 0.55))
    head_tex.grain(rng, fine=0.03, coarse=0.03)
    head = revolved_part(head_profile, head_tex.tile(), weights=head_weights)

    # A pocket clip on the back: a thin steel strip, its far end pressed onto the body.
    clip_len = 0.3 * rng.uniform(0.9, 1.1)
    clip = place(box_part((0.035, clip_len, 0.012), plain_box_texture(rng, (0.78, 0.79, 0.8), lambda c: None)),
                  rotate=rotation("x", 2.0), translate=(0.0, y0 + body_len - 0.06 - clip_len / 2, -(body_r + 0.004)))

    ring_tex = Canvas((0.75, 0.76, 0.78))
    ring_tex.stripes(3, 0.5, (0.45, 0.46, 0.5), "u")
    ring_tex.grain(rng)
    # A thin split ring through the tail cap's lanyard hole, hanging below the axis.
    ring = place(torus_part(ring_major, 0.009, ring_tex.tile(), around=32, tube=10),
                  translate=(0.4 * body_r, 0.05 - ring_major, 0.0))
    lying = rotation("z", -90.0)  # the torch lies along +x, head to the right
    return [place(part, rotate=lying) for part in (tail, body, head, clip, ring)]


FINE_BUILDERS: dict[str, Callable[[np.random.Generator], list[Part]]] = {
    "tin": _tin, "gift": _gift, "basket": _basket, "torch": _torch,
}
