"""Loading every kind of photo a catalog holds, and refusing the broken ones with typed errors."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from ops.intake.errors import ImageTooLargeError, InvalidImageError, PreparationError, SegmentationError
from ops.intake.photo import LoadConfig, load_photo
from ops.intake.prepare import prepare_reference


def _object_photo(seed: int, size: tuple[int, int] = (96, 80)) -> np.ndarray:
    """A dark random-coloured rectangle on white, uint8 RGB."""
    rng = np.random.default_rng(seed)
    w, h = size
    img = np.full((h, w, 3), 245, np.uint8)
    img[h // 4: 3 * h // 4, w // 3: 2 * w // 3] = rng.integers(0, 120, 3)
    return img


def _assert_nothing_written(parent: Path) -> None:
    assert not parent.exists() or list(parent.iterdir()) == [], list(parent.iterdir())


def _fails_cleanly(photo: Path, tmp_path: Path, error: type[PreparationError]) -> PreparationError:
    out = tmp_path / "out"
    with pytest.raises(error) as exc:
        prepare_reference(photo, out / "ref")
    assert str(photo) in str(exc.value) and "Fix:" in str(exc.value)
    _assert_nothing_written(out)
    return exc.value


def test_truncated_jpeg(tmp_path: Path) -> None:
    full = tmp_path / "full.jpg"
    Image.fromarray(_object_photo(1, (400, 300))).save(full, quality=95)
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(full.read_bytes()[: full.stat().st_size // 2])
    err = _fails_cleanly(cut, tmp_path, InvalidImageError)
    assert "truncated" in str(err)


def test_text_file_named_jpg(tmp_path: Path) -> None:
    fake = tmp_path / "notes.jpg"
    fake.write_text("shopping list: mugs, bottles\n")
    assert "not a readable image" in str(_fails_cleanly(fake, tmp_path, InvalidImageError))


def test_empty_file_and_missing_file(tmp_path: Path) -> None:
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    assert "empty" in str(_fails_cleanly(empty, tmp_path, InvalidImageError))
    with pytest.raises(InvalidImageError, match="no such file"):
        load_photo(tmp_path / "absent.png")


@pytest.mark.parametrize("size,reason", [((1, 1), "too small"), ((20000, 20), "too small"), ((600, 40), "aspect")])
def test_degenerate_sizes(tmp_path: Path, size: tuple[int, int], reason: str) -> None:
    path = tmp_path / "odd.png"
    Image.new("L", size, 128).save(path)
    assert reason in str(_fails_cleanly(path, tmp_path, InvalidImageError))


def _png_with_header_size(path: Path, width: int, height: int) -> None:
    """A tiny PNG whose header claims ``width``×``height``: what a decompression bomb looks like to open()."""
    Image.new("L", (8, 8)).save(path)
    data = bytearray(path.read_bytes())
    ihdr = 8 + 8  # signature, then length + b"IHDR"
    data[ihdr: ihdr + 8] = struct.pack(">II", width, height)
    crc = zlib.crc32(bytes(data[ihdr - 4: ihdr + 13]))
    data[ihdr + 13: ihdr + 17] = struct.pack(">I", crc)
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("side", [10_000, 20_000])  # Pillow warns above 89 MP and raises above 179 MP
def test_decompression_bomb_is_a_typed_error_not_a_warning(tmp_path: Path, side: int) -> None:
    bomb = tmp_path / "bomb.png"
    _png_with_header_size(bomb, side, side)
    err = _fails_cleanly(bomb, tmp_path, ImageTooLargeError)
    assert "decompression bomb" in str(err)


def test_configured_pixel_limit(tmp_path: Path) -> None:
    path = tmp_path / "p.png"
    Image.fromarray(_object_photo(2, (200, 150))).save(path)
    with pytest.raises(ImageTooLargeError, match="30,000 pixels exceeds the limit of 10,000"):
        load_photo(path, LoadConfig(max_pixels=10_000))
    with pytest.raises(ValueError, match="decompression-bomb limit"):
        LoadConfig(max_pixels=10**10)


def test_all_white_photo_has_no_object(tmp_path: Path) -> None:
    path = tmp_path / "white.png"
    Image.new("RGB", (200, 160), (250, 250, 250)).save(path)
    assert "mask is empty" in str(_fails_cleanly(path, tmp_path, SegmentationError))


def test_fully_transparent_png(tmp_path: Path) -> None:
    path = tmp_path / "clear.png"
    Image.new("RGBA", (120, 100), (30, 60, 90, 0)).save(path)
    assert "alpha channel" in str(_fails_cleanly(path, tmp_path, SegmentationError))


def test_cmyk_jpeg_colours(tmp_path: Path) -> None:
    path = tmp_path / "cmyk.jpg"
    img = Image.new("CMYK", (160, 120), (0, 0, 0, 0))
    img.paste((0, 255, 255, 0), (50, 30, 110, 90))  # pure red in CMYK
    img.save(path, quality=95)
    photo = load_photo(path)
    assert photo.mode == "CMYK" and photo.alpha is None
    red = photo.rgb[60, 80]
    assert red[0] > 0.9 and red[1] < 0.1 and red[2] < 0.1
    info = prepare_reference(path, tmp_path / "ref")
    assert info.method == "classical" and abs(info.area_fraction - 60 * 60 / (160 * 120)) < 0.02


def test_16bit_png_with_alpha_uses_its_alpha(tmp_path: Path) -> None:
    path = tmp_path / "deep.png"
    bgra = np.zeros((100, 140, 4), np.uint16)
    bgra[..., :3] = 40000
    bgra[20:80, 30:100, 3] = 65535  # opaque object, transparent rest
    assert cv2.imwrite(str(path), bgra)
    photo = load_photo(path)
    assert photo.alpha is not None and photo.alpha[50, 60] == 1.0 and photo.alpha[5, 5] == 0.0
    info = prepare_reference(path, tmp_path / "ref")
    assert info.method == "alpha" and info.bbox == (30, 20, 100, 80)
    assert info.chain[0].step == "alpha" and info.chain[0].outcome == "used"


def test_16bit_and_float_greyscale_are_scaled_not_clipped(tmp_path: Path) -> None:
    ramp = np.linspace(0, 65535, 64 * 48).reshape(48, 64).astype(np.uint16)
    deep = tmp_path / "g16.png"
    cv2.imwrite(str(deep), ramp)
    photo = load_photo(deep)
    assert photo.mode.startswith("I")
    assert np.allclose(photo.rgb[..., 0], ramp / 65535.0, atol=1e-6) and np.ptp(photo.rgb, axis=2).max() == 0
    flt = tmp_path / "f.tif"
    values = np.random.default_rng(3).random((40, 50)).astype(np.float32)
    Image.fromarray(values).save(flt)
    assert np.allclose(load_photo(flt).rgb[..., 1], values, atol=1e-6)
    bad = tmp_path / "nan.tif"
    values[3, 3] = np.nan
    Image.fromarray(values).save(bad)
    with pytest.raises(InvalidImageError, match="NaN"):
        load_photo(bad)


def test_exif_rotated_jpeg(tmp_path: Path) -> None:
    img = np.full((60, 100, 3), 245, np.uint8)
    img[5:20, 5:30] = (200, 20, 20)  # red patch near the stored top-left
    path = tmp_path / "rot.jpg"
    exif = Image.Exif()
    exif[0x0112] = 6  # the camera was turned: display = stored rotated 90° clockwise
    Image.fromarray(img).save(path, exif=exif, quality=95)
    photo = load_photo(path)
    assert photo.exif_transposed and photo.size == (60, 100) and photo.source_size == (60, 100)
    assert photo.rgb[15, 50, 0] > 0.7 and photo.rgb[15, 50, 1] < 0.3  # now near the top-right
    assert any("EXIF" in n for n in photo.notes)


@pytest.mark.parametrize("fmt,ext,palette", [("PNG", "png", True), ("WEBP", "webp", False), ("TIFF", "tif", False),
                                             ("BMP", "bmp", True), ("JPEG", "jpg", False)])
def test_formats_and_modes(tmp_path: Path, fmt: str, ext: str, palette: bool) -> None:
    image = Image.fromarray(_object_photo(4))
    image = image.convert("P") if palette else image
    path = tmp_path / f"p.{ext}"
    image.save(path, format=fmt, **({"lossless": True} if fmt == "WEBP" else {}))
    photo = load_photo(path)
    assert photo.format == fmt and photo.rgb.dtype == np.float32 and photo.rgb.shape == (80, 96, 3)
    expected = np.asarray(image.convert("RGB")) / 255.0
    assert np.abs(photo.rgb - expected).max() < (0.1 if fmt == "JPEG" else 1e-6)


def test_palette_transparency_and_opaque_alpha(tmp_path: Path) -> None:
    pal = Image.new("P", (100, 80), 0)
    pal.putpalette([255, 255, 255, 200, 30, 30] + [0] * 762)
    pal.paste(1, (20, 20, 60, 60))
    path = tmp_path / "pal.png"
    pal.save(path, transparency=0)
    photo = load_photo(path)
    assert photo.alpha is not None and photo.alpha[40, 40] == 1.0 and photo.alpha[5, 5] == 0.0
    opaque = tmp_path / "opaque.png"
    Image.fromarray(_object_photo(5)).convert("RGBA").save(opaque)
    loaded = load_photo(opaque)
    assert loaded.alpha is None and any("alpha channel ignored" in n for n in loaded.notes)


def test_big_photo_is_shrunk_to_max_side(tmp_path: Path) -> None:
    path = tmp_path / "big.png"
    Image.fromarray(_object_photo(6, (900, 600))).save(path)
    photo = load_photo(path, LoadConfig(max_side=300))
    assert photo.size == (300, 200) and photo.source_size == (900, 600)
