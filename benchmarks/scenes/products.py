"""The original eight products: a mug, a bottle, a carton (scene "box"), a vase, a sneaker, a lamp, a
chair and a toy figure. Each builder draws its shape changes and colours from ``rng`` and returns its
painted parts; ``BUILDERS`` maps each scene name to its builder."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from benchmarks.scenes.painting import Canvas, box_texture, darker, hsv, palette, plain_box_texture
from benchmarks.scenes.parts import (
    Part,
    arc,
    arc_v,
    box_part,
    capsule_profile,
    frustum_profile,
    on_axis,
    place,
    revolved_part,
    rotation,
    rounded_slab_profile,
    torus_part,
)


def _mug(rng: np.random.Generator) -> list[Part]:
    height = 1.0 * rng.uniform(0.95, 1.05)
    r_bottom, r_top = 0.36 * rng.uniform(0.95, 1.05), 0.42 * rng.uniform(0.95, 1.05)
    wall = 0.035
    # Up the outside, over the rim, down the inside to the coffee surface.
    profile = on_axis([(0.0, 0.0), *arc(r_bottom - 0.04, 0.04, 0.04, -90.0, 0.0, 5), (r_top, height),
                        (r_top - wall, height), (r_top - wall, height - 0.06), (0.0, height - 0.06)])
    v = arc_v(profile)
    body, band, logo, ink = palette(rng, 4)
    coffee = (0.28, 0.14, 0.06)
    canvas = Canvas(body)
    canvas.rect(0.0, 1.0, 0.35 * v[-4], 0.62 * v[-4], band)  # a wide band in the middle of the wall
    canvas.stripes(6, 0.5, darker(band, 0.55), "u", (0.0, 1.0, 0.35 * v[-4], 0.42 * v[-4]))
    canvas.ellipse(0.5, 0.72 * v[-4], 0.07, 0.12, logo)
    canvas.ellipse(0.5, 0.72 * v[-4], 0.035, 0.06, ink)
    canvas.text(rng, 0.4, 0.6, 0.12 * v[-4], 0.3 * v[-4], ink)
    canvas.stripes(5, 0.4, darker(body, 0.6), "v", (0.0, 1.0, 0.02, 0.1))
    canvas.rect(0.0, 1.0, v[-3], 1.0, coffee)  # the coffee surface (and the inside rim above it)
    canvas.rect(0.0, 1.0, v[-4], v[-3], darker(body, 1.1))  # the rim top
    canvas.grain(rng)
    handle = Canvas(body)
    handle.stripes(6, 0.5, band, "u")
    handle.grain(rng)
    cup = revolved_part(profile, canvas.tile())
    ring = place(torus_part(0.26 * height, 0.055 * height, handle.tile()),
                  translate=(r_top * 0.92 + 0.13 * height, 0.5 * height, 0.0))
    return [cup, ring]


def _bottle(rng: np.random.Generator) -> list[Part]:
    radius, body_h = 0.3 * rng.uniform(0.93, 1.07), 1.0 * rng.uniform(0.93, 1.07)
    neck, neck_top, cap_r, cap_h = 0.1, body_h + 0.5, 0.125, 0.16
    shoulder = [(neck + (radius - neck) * (0.5 + 0.5 * math.cos(math.pi * t)), body_h + 0.35 * t)
                for t in np.linspace(0.0, 1.0, 17)]
    profile = on_axis([(0.0, 0.0), *arc(radius - 0.05, 0.05, 0.05, -90.0, 0.0, 5), *shoulder[:-1],
                        (neck, body_h + 0.35), (neck, neck_top), (cap_r, neck_top), (cap_r, neck_top + cap_h),
                        (0.0, neck_top + cap_h)])
    v = arc_v(profile)
    glass, paper_hue, block, cap = palette(rng, 4)
    paper = tuple(0.55 * c + 0.4 for c in paper_hue)  # a pale tint (kept clearly off white)
    # Profile points 6 and 7 bound the straight wall; the label covers most of it.
    label_lo, label_hi = v[6] + 0.12 * (v[7] - v[6]), v[6] + 0.9 * (v[7] - v[6])
    canvas = Canvas(glass)
    canvas.stripes(4, 0.5, darker(glass, 0.8), "u", (0.0, 1.0, 0.0, label_lo))  # moulded ribs below the label
    canvas.rect(0.0, 1.0, label_lo, label_hi, paper)  # type: ignore[arg-type]
    span = label_hi - label_lo
    canvas.rect(0.0, 1.0, label_hi - 0.3 * span, label_hi, block)
    canvas.stripes(8, 0.35, darker(block, 0.5), "u", (0.0, 1.0, label_hi - 0.3 * span, label_hi - 0.22 * span))
    canvas.ellipse(0.5, label_hi - 0.55 * span, 0.07, 0.13 * span, darker(block, 0.7))
    canvas.text(rng, 0.36, 0.64, label_lo + 0.08 * span, label_hi - 0.72 * span, (0.1, 0.1, 0.12))
    canvas.text(rng, 0.05, 0.3, label_lo + 0.1 * span, label_hi - 0.35 * span, darker(block, 0.6), line=10)
    canvas.barcode(rng, 0.57, 0.69, label_lo + 0.1 * span, label_lo + 0.45 * span)
    canvas.rect(0.0, 1.0, v[-5], 1.0, cap)
    canvas.stripes(4, 0.5, darker(cap, 0.6), "u", (0.0, 1.0, v[-4], v[-3]))  # cap knurling
    canvas.grain(rng, fine=0.04)
    return [revolved_part(profile, canvas.tile())]


def _carton(rng: np.random.Generator) -> list[Part]:
    size = (1.0 * rng.uniform(0.9, 1.1), 1.35 * rng.uniform(0.92, 1.08), 0.55 * rng.uniform(0.9, 1.1))
    main, accent, side, ink, second = palette(rng, 5)
    kraft = (0.72, 0.55, 0.34)
    front = Canvas(main)
    front.rect(0.0, 1.0, 0.62, 0.86, accent)  # the brand band
    front.stripes(6, 0.5, darker(accent, 0.6), "v", (0.0, 1.0, 0.62, 0.66))
    front.ellipse(0.3, 0.4, 0.18, 0.14, second)
    front.ellipse(0.3, 0.4, 0.09, 0.07, darker(second, 0.5))
    front.text(rng, 0.1, 0.9, 0.88, 0.98, ink, line=11)
    front.text(rng, 0.55, 0.92, 0.3, 0.56, ink)
    front.text(rng, 0.12, 0.9, 0.68, 0.82, (0.97, 0.96, 0.9), line=16, letter=(5, 10))
    front.barcode(rng, 0.08, 0.36, 0.04, 0.18)
    front.stripes(5, 0.4, darker(main, 0.7), "u", (0.5, 0.95, 0.04, 0.18))
    canvases = {"front": front}
    for name in ("right", "left", "back"):
        c = Canvas(side if name != "back" else second)
        c.rect(0.0, 1.0, 0.75, 0.9, accent)
        c.text(rng, 0.08, 0.92, 0.2, 0.7, ink)
        canvases[name] = c
    for name in ("top", "bottom"):
        c = Canvas(kraft)
        c.rect(0.0, 1.0, 0.42, 0.58, darker(kraft, 0.8))  # packing tape
        c.stripes(3, 0.34, darker(kraft, 0.9), "u")
        canvases[name] = c
    for c in canvases.values():
        c.grain(rng, fine=0.04, coarse=0.05)
    return [box_part(size, box_texture(canvases))]


def _vase(rng: np.random.Generator) -> list[Part]:
    height = 1.6 * rng.uniform(0.95, 1.05)
    belly, waist, lip = rng.uniform(0.42, 0.5), rng.uniform(0.15, 0.2), rng.uniform(0.22, 0.28)
    ts = np.linspace(0.0, 1.0, 61)
    # Belly low down, a narrow waist, flaring lip: a smooth bump sum, bounded away from the axis.
    radii = 0.18 + belly * np.exp(-((ts - 0.3) / 0.2) ** 2) + lip * np.exp(-((ts - 1.0) / 0.12) ** 2)
    radii = np.maximum(radii - (0.2 - waist) * np.exp(-((ts - 0.72) / 0.1) ** 2), 0.1)
    wall = [(float(r), float(t * height)) for r, t in zip(radii, ts, strict=True)]
    mouth = float(radii[-1]) - 0.04
    profile = on_axis([(0.0, 0.0), *wall, (mouth, height), (mouth, height - 0.1), (0.0, height - 0.1)])
    colours = palette(rng, 5)
    canvas = Canvas(colours[0])
    edges = np.sort(rng.uniform(0.08, 0.9, 6))
    for k in range(0, 6, 2):
        canvas.rect(0.0, 1.0, edges[k], edges[k + 1], colours[1 + k // 2])
    canvas.stripes(7, 0.45, colours[4], "u", (0.0, 1.0, edges[0] + 0.02, edges[0] + 0.07))
    canvas.stripes(5, 0.4, darker(colours[0], 0.6), "v", (0.0, 1.0, edges[3] + 0.01, edges[4] - 0.01))
    waves = canvas.v - (edges[1] + 0.03) - 0.02 * np.sin(canvas.u * 2 * math.pi * 16)
    canvas.where((waves > 0) & (waves < 0.015), colours[4])
    canvas.rect(0.0, 1.0, 0.95, 1.0, darker(colours[0], 0.4))  # the dark inside of the mouth
    canvas.grain(rng, fine=0.08, coarse=0.1)
    return [revolved_part(profile, canvas.tile())]


def _sneaker(rng: np.random.Generator) -> list[Part]:
    length = rng.uniform(1.0, 1.1)  # half length along x
    upper_c, block_c, sole_c, lace_c = palette(rng, 4)
    sole_c = tuple(0.5 * c + 0.45 for c in sole_c)  # a light rubber tint, still off white
    sole_tex = Canvas(sole_c)  # type: ignore[arg-type]
    sole_tex.stripes(5, 0.4, darker(sole_c, 0.65), "u", (0.0, 1.0, 0.3, 0.7))  # type: ignore[arg-type]
    sole_tex.rect(0.0, 1.0, 0.0, 0.28, darker(block_c, 0.5))  # tread
    sole_tex.grain(rng)
    sole = place(revolved_part(rounded_slab_profile(1.0, 0.16, 0.05), sole_tex.tile()),
                  scale=(length, 1.0, 0.38))
    dome = on_axis([(0.0, 0.1)] + [(0.92 * math.cos(a), 0.1 + 0.8 * math.sin(a))
                                    for a in np.linspace(0.0, math.pi / 2, 25)])
    upper = Canvas(upper_c)
    # The dome's flat bottom (v < rim) hides inside the sole; paint the wall by its own height 0..1.
    rim = arc_v(dome)[1]
    wall = (upper.v - rim) / (1.0 - rim)
    # The side facing the camera is u ≈ 0.5; the toe (+x) is u = 0.75, the heel u = 0.25.
    upper.where((wall < 0.5) & (np.abs(upper.u - 0.5) < 0.16), block_c)  # side panel
    upper.where((np.abs(upper.u - 0.25) < 0.06) & (wall < 0.85), darker(block_c, 0.6))  # heel tab
    upper.where((np.abs(upper.u - 0.75) < 0.1) & (wall < 0.45), darker(upper_c, 0.55))  # toe cap
    swoosh = wall - 0.25 - 1.2 * (upper.u - 0.35) + 6.0 * (upper.u - 0.5) ** 2
    upper.where((np.abs(swoosh) < 0.06) & (np.abs(upper.u - 0.5) < 0.22), lace_c)
    for k in range(6):  # laces across the instep, towards the toe
        s0 = 0.62 + 0.055 * k
        upper.where((np.abs(upper.u - 0.72) < 0.08) & (wall > s0) & (wall < s0 + 0.025), lace_c)
    upper.stripes(4, 0.5, darker(upper_c, 0.75), "v", (0.0, 1.0, rim, rim + 0.06 * (1.0 - rim)))  # welt
    upper.grain(rng, fine=0.12, coarse=0.06)  # knit mesh
    top = place(revolved_part(dome, upper.tile()), scale=(0.85 * length, 1.0, 0.36),
                 translate=(-0.12 * length, 0.0, 0.0))
    # A shoe rises towards the heel: scale heights above the sole by a factor falling from heel to toe
    # (positive everywhere, so the map keeps the winding and the surface closed).
    x = top.vertices[:, 0] / length
    factor = 1.05 - 0.55 * np.clip((x + 1.0) / 2.0, 0.0, 1.0)
    lifted = top.vertices.copy()
    lifted[:, 1] = 0.1 + (lifted[:, 1] - 0.1) * factor
    return [sole, Part(lifted[top.canon], top.faces, top.uvs, top.canon, top.texture)]


def _lamp(rng: np.random.Generator) -> list[Part]:
    metal, shade_c, weave_c, base_c = palette(rng, 4)
    base_tex = Canvas(base_c)
    base_tex.stripes(6, 0.5, darker(base_c, 0.6), "u")
    base_tex.grain(rng)
    base = revolved_part(rounded_slab_profile(0.38, 0.1, 0.03), base_tex.tile())
    pole_tex = Canvas(metal)
    pole_tex.stripes(8, 0.3, darker(metal, 0.6), "v")
    pole_tex.grain(rng)
    pole_top = 1.0 * rng.uniform(0.95, 1.05)
    pole = revolved_part(frustum_profile(0.035, 0.035, 0.05, pole_top + 0.05), pole_tex.tile(), around=24)
    shade_tex = Canvas(shade_c)
    weave = (np.sin(shade_tex.u * shade_tex.w * math.pi / 3) * np.sin(shade_tex.v * shade_tex.h * math.pi / 3))
    shade_tex.img += 0.12 * weave[..., None]
    shade_tex.rect(0.0, 1.0, 0.2, 0.28, weave_c)
    shade_tex.rect(0.0, 1.0, 0.72, 0.8, weave_c)
    shade_tex.stripes(6, 0.5, darker(weave_c, 0.6), "u", (0.0, 1.0, 0.22, 0.26))
    shade_tex.grain(rng, fine=0.05)
    shade_h, r_bottom, r_top = 0.55, 0.5 * rng.uniform(0.9, 1.1), 0.3 * rng.uniform(0.9, 1.1)
    shade = revolved_part(frustum_profile(r_bottom, r_top, pole_top - 0.15, pole_top - 0.15 + shade_h),
                           shade_tex.tile())
    return [base, pole, shade]


def _chair(rng: np.random.Generator) -> list[Part]:
    wood, pad_c, pattern_c = palette(rng, 3, s=(0.55, 0.9), v=(0.4, 0.8))
    wood = darker(wood, 1.0)

    def grain(canvas: Canvas) -> None:
        lines = np.sin(canvas.u * canvas.w * 2 * math.pi / 7 + 3 * np.sin(canvas.v * 9))
        canvas.where(lines > 0.55, darker(wood, 0.7))

    wood_tex = plain_box_texture(rng, wood, grain)
    width, depth, seat_y = 1.0, 0.9 * rng.uniform(0.95, 1.05), 0.85 * rng.uniform(0.95, 1.05)
    parts = [place(box_part((width, 0.08, depth), wood_tex), translate=(0.0, seat_y, 0.0))]
    # The back legs and backrest are inset: seen from the front, perspective would otherwise leave a
    # sliver of background between front and back legs that segmentation closes.
    back_w = 0.62 * width
    leg = box_part((0.1, seat_y + 0.02, 0.1), wood_tex)
    for sx in (-1, 1):
        for sz, x in ((1, width / 2 - 0.06), (-1, back_w / 2 - 0.06)):
            parts.append(place(leg, translate=(sx * x, (seat_y + 0.02) / 2 - 0.01, sz * (depth / 2 - 0.06))))
    back_h = 0.85 * rng.uniform(0.95, 1.05)
    back = box_part((back_w, back_h, 0.07), wood_tex)
    parts.append(place(back, rotate=rotation("x", -8.0),
                        translate=(0.0, seat_y + back_h / 2 - 0.02, -depth / 2 + 0.02)))

    def fabric(canvas: Canvas) -> None:
        canvas.stripes(6, 0.34, pattern_c, "u")
        canvas.stripes(6, 0.34, darker(pattern_c, 0.7), "v")
        canvas.rect(0.0, 1.0, 0.05, 0.15, darker(pad_c, 0.5))

    pad_tex = plain_box_texture(rng, pad_c, fabric)
    pad = box_part((width - 0.1, 0.07, depth - 0.12), pad_tex)
    parts.append(place(pad, translate=(0.0, seat_y + 0.07, 0.03)))
    # A back cushion: the face the reference camera sees.
    cushion = box_part((back_w - 0.12, 0.45, 0.06), pad_tex)
    parts.append(place(cushion, rotate=rotation("x", -8.0),
                        translate=(0.0, seat_y + 0.5 * back_h, -depth / 2 + 0.06)))
    return parts


def _figure(rng: np.random.Generator) -> list[Part]:
    skin = hsv(rng.uniform(0.04, 0.1), rng.uniform(0.35, 0.6), rng.uniform(0.75, 0.95))
    shirt, print_c, trousers, hair, shoes = palette(rng, 5, v=(0.45, 0.85))
    head_r = 0.28 * rng.uniform(0.95, 1.05)
    head_tex = Canvas(skin)
    head_tex.rect(0.0, 1.0, 0.72, 1.0, hair)
    head_tex.stripes(4, 0.5, darker(hair, 0.6), "u", (0.0, 1.0, 0.72, 1.0))
    for du in (-0.045, 0.045):  # eyes on the front (u = 0.5), a little above the equator
        head_tex.ellipse(0.5 + du, 0.56, 0.022, 0.045, (0.98, 0.98, 0.98))
        head_tex.ellipse(0.5 + du, 0.56, 0.012, 0.025, (0.05, 0.05, 0.1))
    mouth = (np.abs(head_tex.u - 0.5) < 0.05) & (np.abs(head_tex.v - 0.4 - 8 * (head_tex.u - 0.5) ** 2) < 0.012)
    head_tex.where(mouth, (0.6, 0.05, 0.1))
    head_tex.ellipse(0.42, 0.45, 0.02, 0.03, darker(skin, 0.85))
    head_tex.grain(rng, fine=0.03, coarse=0.04)
    sphere = on_axis(arc(0.0, 0.0, head_r, -90.0, 90.0, 32))
    head = place(revolved_part(sphere, head_tex.tile()), translate=(0.0, 1.3, 0.0))

    body_tex = Canvas(shirt)
    body_tex.ellipse(0.5, 0.55, 0.09, 0.16, print_c)
    body_tex.stripes(5, 0.4, darker(print_c, 0.5), "v", (0.42, 0.58, 0.45, 0.65))
    body_tex.text(rng, 0.4, 0.6, 0.25, 0.38, darker(shirt, 0.4), line=10)
    body_tex.stripes(6, 0.5, darker(shirt, 0.75), "v", (0.0, 1.0, 0.0, 0.15))
    body_tex.grain(rng)
    body = place(revolved_part(capsule_profile(0.26, 0.35), body_tex.tile()), translate=(0.0, 0.82, 0.0))

    limb_tex = Canvas(shirt)
    limb_tex.rect(0.0, 1.0, 0.0, 0.3, skin)  # hands at the low end
    limb_tex.stripes(5, 0.4, darker(shirt, 0.6), "v", (0.0, 1.0, 0.45, 0.6))
    limb_tex.grain(rng)
    leg_tex = Canvas(trousers)
    # Coloured shoes: near-black, neutral ones pass for the contact shadow in classical segmentation.
    leg_tex.rect(0.0, 1.0, 0.0, 0.2, darker(shoes, 0.7))
    leg_tex.stripes(6, 0.5, darker(trousers, 0.7), "u", (0.0, 1.0, 0.2, 1.0))
    leg_tex.grain(rng)
    spread = rng.uniform(18.0, 30.0)
    parts = [head, body]
    for side in (-1, 1):
        arm = revolved_part(capsule_profile(0.085, 0.5), limb_tex.tile(), around=32)
        parts.append(place(arm, rotate=rotation("z", side * spread),
                            translate=(side * (0.3 + 0.25 * math.sin(math.radians(spread))), 0.82, 0.0)))
        leg = revolved_part(capsule_profile(0.1, 0.45), leg_tex.tile(), around=32)
        # Legs well apart: a gap of a few pixels would be closed by the reference stage's segmentation.
        parts.append(place(leg, translate=(side * 0.145, 0.32, 0.0)))
    return parts


BUILDERS: dict[str, Callable[[np.random.Generator], list[Part]]] = {
    "mug": _mug, "bottle": _bottle, "box": _carton, "vase": _vase, "sneaker": _sneaker, "lamp": _lamp,
    "chair": _chair, "figure": _figure,
}
