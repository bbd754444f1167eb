"""The catalog's true size: ``products.csv`` rows (good and malformed) and the metric, bottom-centred asset."""

from __future__ import annotations

import numpy as np
import pytest

from morpheus_core.export.true_size import fit_true_size
from morpheus_core.geometry.textured_mesh import BakedTexture
from ops.intake.products import ProductsFileError, products_for, read_products


def random_asset(rng: np.random.Generator, n: int = 60) -> BakedTexture:
    """A random point cloud with random triangles, stretched per axis and moved off the origin."""
    v = (rng.normal(size=(n, 3)) * rng.uniform(0.2, 0.9, size=3) + rng.uniform(-0.3, 0.3, size=3)).astype(np.float32)
    normals = rng.normal(size=(n, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return BakedTexture(v, rng.integers(0, n, (n, 3)), rng.random((n, 2)).astype(np.float32), normals,
                        rng.integers(0, 256, (16, 16, 3), dtype=np.uint8), 0.5, n)


def write_folder(tmp_path, rows: str, photos=("mug.jpg", "box.png")):
    for p in photos:
        (tmp_path / p).write_bytes(b"\xff\xd8 not decoded here \xff\xd9")
    path = tmp_path / "products.csv"
    path.write_text(rows, encoding="utf-8")
    return path


@pytest.mark.parametrize("by", ["height", "width", "depth"])
def test_each_dimension_sets_the_size_and_the_origin_is_the_bottom_centre(by):
    rng = np.random.default_rng()
    asset = random_asset(rng)
    metres = float(rng.uniform(0.05, 1.5))
    known = {"height": None, "width": None, "depth": None, by: metres}
    sized, fit = fit_true_size(asset, known)
    lo, hi = sized.vertices.min(axis=0), sized.vertices.max(axis=0)
    axis = {"width": 0, "height": 1, "depth": 2}[by]
    assert fit.scaled_by == by
    assert hi[axis] - lo[axis] == pytest.approx(metres, rel=1e-5)
    assert fit.size_m[by] == pytest.approx(metres, rel=1e-6)
    assert lo[1] == pytest.approx(0.0, abs=1e-6)  # standing on the floor
    assert (lo[0] + hi[0]) / 2 == pytest.approx(0.0, abs=1e-6)
    assert (lo[2] + hi[2]) / 2 == pytest.approx(0.0, abs=1e-6)
    # A uniform scale: shape ratios kept, faces, UVs and texture untouched.
    before = asset.vertices.max(axis=0) - asset.vertices.min(axis=0)
    np.testing.assert_allclose((hi - lo) / (hi - lo)[axis], before / before[axis], rtol=1e-5)
    assert (sized.faces == asset.faces).all() and (sized.uvs == asset.uvs).all()


def test_height_wins_and_the_other_dimensions_are_compared():
    rng = np.random.default_rng()
    asset = random_asset(rng)
    extent = asset.vertices.max(axis=0) - asset.vertices.min(axis=0)
    height = 0.3
    true_width = extent[0] * height / extent[1]
    _, agree = fit_true_size(asset, {"height": height, "width": true_width, "depth": None})
    assert agree.scaled_by == "height" and agree.worst() == pytest.approx(0.0, abs=1e-5)
    _, off = fit_true_size(asset, {"height": height, "width": true_width * 1.5, "depth": None})
    assert off.disagreement["width"] == pytest.approx(1 / 3, rel=1e-4)


def test_no_size_or_a_bad_one_is_refused():
    asset = random_asset(np.random.default_rng())
    with pytest.raises(ValueError, match="at least one"):
        fit_true_size(asset, {"height": None})
    with pytest.raises(ValueError, match="positive"):
        fit_true_size(asset, {"height": -0.2})
    with pytest.raises(ValueError, match="unknown dimension"):
        fit_true_size(asset, {"length": 0.2})


def test_products_csv_rows_good_and_malformed(tmp_path):
    rng = np.random.default_rng()
    h, w = rng.uniform(10, 900, size=2).round(1)
    path = write_folder(tmp_path, f"photo,sku,height_mm,width_mm,depth_mm\n"
                                  f"mug.jpg,MUG-1,{h},{w},\n"
                                  f"box.png,BOX-2,-5,,\n"
                                  f"ghost.jpg,G,100,,\n")
    table = read_products(path)
    mug = table.size_of("mug.jpg")
    assert (mug.sku, mug.height_mm, mug.width_mm, mug.depth_mm) == ("MUG-1", h, w, None)
    assert mug.source == "products.csv:2"
    with pytest.raises(ProductsFileError, match=r"products\.csv:3: height_mm '-5' must be a positive"):
        table.size_of("box.png")
    assert len(table.unknown) == 1 and "products.csv:4" in table.unknown[0] and "ghost.jpg" in table.unknown[0]
    assert table.size_of("other.jpg") is None  # not listed: the default size, not an error


@pytest.mark.parametrize(("row", "message"), [
    ("mug.jpg,M,tall,,", r"products\.csv:2: height_mm 'tall' is not a number"),
    ("mug.jpg,M,nan,,", r"products\.csv:2: height_mm 'nan' must be a positive"),
    ("mug.jpg,M,0,,", r"must be a positive"),
])
def test_a_bad_value_names_the_file_and_line(tmp_path, row, message):
    table = read_products(write_folder(tmp_path, f"photo,sku,height_mm,width_mm,depth_mm\n{row}\n"))
    with pytest.raises(ProductsFileError, match=message):
        table.size_of("mug.jpg")


def test_a_photo_listed_twice_and_a_file_without_a_photo_column(tmp_path):
    table = read_products(write_folder(tmp_path, "photo,height_mm\nmug.jpg,100\nmug.jpg,120\n"))
    with pytest.raises(ProductsFileError, match="listed twice"):
        table.size_of("mug.jpg")
    with pytest.raises(ProductsFileError, match=r"products\.csv:1: the header must name"):
        read_products(write_folder(tmp_path, "sku,height_mm\nA,100\n"))


def test_products_for_rereads_a_changed_file(tmp_path):
    path = write_folder(tmp_path, "photo,height_mm\nmug.jpg,100\n")
    assert products_for(tmp_path / "mug.jpg").size_of("mug.jpg").height_mm == 100
    path.write_text("photo,height_mm\nmug.jpg,123.5\n", encoding="utf-8")
    assert products_for(tmp_path / "mug.jpg").size_of("mug.jpg").height_mm == 123.5
    assert products_for(tmp_path / "elsewhere" / "x.jpg") is None
