"""Photo keys are safe folder names, stable, and distinct for distinct photos."""

from __future__ import annotations

import random
import secrets
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from assets_store.keys import UnsafeKeyError, assign_keys, check_key, is_safe_key, photo_key
from assets_store.store import Store

NASTY = [
    "..",
    "../../etc/passwd",
    "..\\..\\windows\\system32",
    "/abs/path/mug.jpg",
    "sub/dir/mug.jpg",
    "C:\\photos\\mug.jpg",
    "my mug.jpg",
    "café été.jpg",
    "商品.png",
    "📷🍵.jpg",
    "a,b,c.jpg",
    "tab\there\nnewline\x00nul\x7f.jpg",
    ".hidden.jpg",
    "-dash.jpg",
    "....jpg",
    "mug...jpg",
    "x" * 500 + ".jpg",
    "é" * 300,
    "",
    " ",
    ".",
    "___",
    "ＦＵＬＬ　ＷＩＤＴＨ.jpg",
    "ﬁle.jpg",
]


@pytest.mark.parametrize("name", NASTY)
def test_nasty_names_give_safe_keys_inside_the_root(name: str, tmp_path: Path) -> None:
    key = photo_key(name)
    assert check_key(key) == key
    assert len(key) <= 128
    assert key != name  # none of these is a safe name, so each must carry the hash suffix
    root = tmp_path / "store"
    stage = Store(root).stage_dir(key, "reference")
    assert stage.resolve().is_relative_to(root.resolve())
    assert stage.parent.parent == root


def test_lossless_names_are_unchanged_and_extension_is_kept() -> None:
    for name in ["mug.jpg", "IMG_0001.JPG", "a-b_c.1.png", "photo"]:
        assert photo_key(name) == name
    assert photo_key("mug.jpg") != photo_key("mug.png")


def test_lossy_names_carry_a_hash_of_the_original() -> None:
    stem = secrets.token_hex(4)
    a, b = photo_key(f"{stem} a.jpg"), photo_key(f"{stem}?a.jpg")
    assert a.startswith(f"{stem}_a.jpg-") and b.startswith(f"{stem}_a.jpg-")
    assert a != b
    assert photo_key("café.jpg").startswith("cafe.jpg-")
    assert photo_key("sub/mug.jpg").startswith("sub__mug.jpg-")


def test_no_dot_runs_survive() -> None:
    for name in ["....jpg", "a..b", "a" + "." * random.randint(2, 9) + "b", "../x/../y"]:
        assert ".." not in photo_key(name)


@pytest.mark.parametrize("bad", ["..", "a/b", "a\\b", "a,b", "", ".hidden", "-x", "a..b", "a b", "é", "x" * 129,
                                 "a\x00b"])
def test_check_key_rejects_unsafe(bad: str) -> None:
    assert not is_safe_key(bad)
    with pytest.raises(UnsafeKeyError, match="unsafe photo key"):
        check_key(bad)


@settings(max_examples=300, suppress_health_check=[HealthCheck.function_scoped_fixture], deadline=None)
@given(st.one_of(st.text(), st.lists(st.text(max_size=20), max_size=5).map("/".join)))
def test_any_text_gives_a_safe_key_inside_the_root(tmp_path: Path, name: str) -> None:
    key = photo_key(name)
    check_key(key)
    assert photo_key(name) == key  # deterministic
    assert Store(tmp_path).stage_dir(key, "reference").resolve().is_relative_to(tmp_path.resolve())


@settings(max_examples=200, deadline=None)
@given(st.lists(st.text(max_size=12), unique=True, max_size=40))
def test_distinct_names_give_distinct_keys(names: list[str]) -> None:
    assert len({photo_key(n) for n in names}) == len(names)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.text(alphabet="Mmug.jpgJPG _/é", max_size=8), unique=True, max_size=30), st.randoms())
def test_assign_keys_is_unique_ignoring_case_and_order_independent(names: list[str], rnd: random.Random) -> None:
    keys = assign_keys(names)
    assert set(keys) == set(names)
    assert len({k.lower() for k in keys.values()}) == len(names)
    assert all(is_safe_key(k) for k in keys.values())
    shuffled = list(names)
    rnd.shuffle(shuffled)
    assert assign_keys(shuffled) == keys


def test_assign_keys_case_collision() -> None:
    other = f"{secrets.token_hex(3)}.png"
    keys = assign_keys(["mug.jpg", other, "Mug.jpg"])
    assert keys["Mug.jpg"] == "Mug.jpg"  # sorts first ("M" < "m"), keeps its key
    assert keys["mug.jpg"].startswith("mug.jpg-") and len(keys["mug.jpg"]) == len("mug.jpg-") + 12
    assert keys[other] == other
    assert assign_keys(["Mug.jpg", "mug.jpg", other]) == keys


def test_a_key_without_collision_does_not_depend_on_other_photos() -> None:
    name = f"photo {secrets.token_hex(4)}.jpg"
    others = [f"{secrets.token_hex(5)}.jpg" for _ in range(20)]
    assert assign_keys([name, *others])[name] == photo_key(name) == assign_keys([name])[name]
