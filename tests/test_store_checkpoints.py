"""Checkpoints round-trip training state, refuse NaN, and survive corruption and SIGKILL."""

from __future__ import annotations

import io
import os
import random
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import pytest
import torch
from torch import nn

from assets_store.checkpoints import MAGIC, Checkpoints, NonFiniteStateError

ROOT = Path(__file__).resolve().parent.parent


def _assert_same(a: Any, b: Any, path: str = "") -> None:
    assert type(a) is type(b) or (isinstance(a, dict) and isinstance(b, dict)), path
    if isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and torch.equal(a, b), path
    elif isinstance(a, dict):
        assert list(a) == list(b), path
        for k in a:
            _assert_same(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same(x, y, f"{path}.{i}")
    else:
        assert a == b, path


def _training_state(seed: int) -> dict[str, Any]:
    torch.manual_seed(seed)
    model = nn.Sequential(nn.Linear(5, 7), nn.ReLU(), nn.Linear(7, 3))
    opt = torch.optim.Adam(model.parameters(), lr=1e-3, betas=(0.9, 0.99))
    model(torch.randn(4, 5)).square().mean().backward()
    opt.step()
    gen = torch.Generator().manual_seed(seed)
    torch.rand(3, generator=gen)
    return {
        "model": model.state_dict(),
        "optimizers": {"nerf": opt.state_dict()},
        "rng": {"torch": gen.get_state(), "cpu": torch.get_rng_state()},
        "losses": [random.random() for _ in range(5)],
        "meta": {"step": seed, "name": "geometry", "done": False, "best": None, "shape": (64, 64), "best_loss": 1e9},
        "ints": torch.randint(0, 100, (6,), dtype=torch.int64),
        "half": torch.randn(3, dtype=torch.float16),
    }


def test_round_trip_of_real_training_state(tmp_path: Path) -> None:
    ck = Checkpoints(tmp_path / "ck")
    step = random.randint(0, 10**6)
    state = _training_state(step)
    path = ck.save(step, state)
    assert path.name == f"step-{step:09d}.ckpt" and path.read_bytes()[:8] == MAGIC
    loaded = ck.load_latest()
    assert loaded is not None and loaded[0] == step
    _assert_same(state, loaded[1])
    # The restored optimizer state is usable, not just equal.
    model = nn.Sequential(nn.Linear(5, 7), nn.ReLU(), nn.Linear(7, 3))
    model.load_state_dict(loaded[1]["model"])
    opt = torch.optim.Adam(model.parameters())
    opt.load_state_dict(loaded[1]["optimizers"]["nerf"])
    assert torch.Generator().set_state(loaded[1]["rng"]["torch"]).get_state().equal(state["rng"]["torch"])


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_non_finite_tensor_is_refused_and_nothing_written(tmp_path: Path, bad: float) -> None:
    ck = Checkpoints(tmp_path / "ck")
    state = _training_state(random.randint(0, 1000))
    exp_avg = state["optimizers"]["nerf"]["state"][2]["exp_avg"]
    exp_avg.view(-1)[random.randrange(exp_avg.numel())] = bad
    with pytest.raises(NonFiniteStateError, match=r"optimizers\.nerf\.state\.2\.exp_avg"):
        ck.save(5, state)
    assert not (tmp_path / "ck").exists() or list((tmp_path / "ck").iterdir()) == []
    assert ck.load_latest() is None


def test_non_finite_in_a_list_is_named(tmp_path: Path) -> None:
    state = {"views": [torch.zeros(2), torch.tensor([1.0, float("nan")])]}
    with pytest.raises(NonFiniteStateError, match=r"views\.1"):
        Checkpoints(tmp_path).save(1, state)
    Checkpoints(tmp_path).save(1, {"ints": torch.tensor([1, 2]), "best": float("inf")})  # python floats may be inf


def _corrupt(path: Path, how: str) -> None:
    data = path.read_bytes()
    if how == "truncate":
        path.write_bytes(data[: random.randint(1, len(data) - 1)])
    elif how == "flip":
        buf = bytearray(data)
        buf[random.randrange(48, len(buf))] ^= 1 << random.randrange(8)
        path.write_bytes(bytes(buf))
    elif how == "empty":
        path.write_bytes(b"")
    elif how == "magic":
        path.write_bytes(b"NOTACKPT" + data[8:])


@pytest.mark.parametrize("how", ["truncate", "flip", "empty", "magic"])
def test_corrupt_newest_is_skipped_and_set_aside(tmp_path: Path, how: str) -> None:
    ck = Checkpoints(tmp_path, keep=3)
    older = _training_state(1)
    ck.save(10, older)
    newest = ck.save(20, _training_state(2))
    _corrupt(newest, how)
    with pytest.warns(RuntimeWarning, match=newest.name):
        loaded = ck.load_latest()
    assert loaded is not None and loaded[0] == 10
    _assert_same(older, loaded[1])
    assert not newest.exists() and newest.with_name(newest.name + ".corrupt").is_file()
    assert ck.steps() == [10]
    assert ck.load_latest() is not None  # no second warning: the bad file is never tried again


def test_pickle_that_is_not_plain_weights_is_refused(tmp_path: Path) -> None:
    import hashlib
    import struct

    buffer = io.BytesIO()
    torch.save({"obj": ValueError("arbitrary object")}, buffer)  # weights_only=True must not unpickle this
    payload = buffer.getvalue()
    data = MAGIC + struct.pack("<Q", len(payload)) + hashlib.sha256(payload).digest() + payload
    ck = Checkpoints(tmp_path)
    ck.save(1, {"x": torch.ones(1)})
    (tmp_path / "step-000000002.ckpt").write_bytes(data)
    with pytest.warns(RuntimeWarning, match="step-000000002"):
        loaded = ck.load_latest()
    assert loaded is not None and loaded[0] == 1


def test_all_corrupt_gives_none(tmp_path: Path) -> None:
    ck = Checkpoints(tmp_path)
    _corrupt(ck.save(3, {"x": torch.ones(3)}), "empty")
    with pytest.warns(RuntimeWarning):
        assert ck.load_latest() is None
    assert Checkpoints(tmp_path / "never").load_latest() is None


@pytest.mark.parametrize("keep", [1, 2, 3])
def test_pruning_keeps_the_newest(tmp_path: Path, keep: int) -> None:
    ck = Checkpoints(tmp_path, keep=keep)
    steps = sorted(random.sample(range(1000), 6))
    for step in steps:
        ck.save(step, {"step": step, "x": torch.full((4,), float(step))})
    assert ck.steps() == steps[-keep:]
    loaded = ck.load_latest()
    assert loaded is not None and loaded[0] == steps[-1] and loaded[1]["step"] == steps[-1]


def test_temporaries_are_ignored_and_cleared(tmp_path: Path) -> None:
    ck = Checkpoints(tmp_path)
    ck.save(1, {"x": torch.ones(2)})
    (tmp_path / ".step-000000002.ckpt.12345.tmp").write_bytes(os.urandom(100))
    assert ck.steps() == [1]
    loaded = ck.load_latest()
    assert loaded is not None and loaded[0] == 1
    ck.clear()
    assert not tmp_path.exists() or list(tmp_path.iterdir()) == []
    assert ck.steps() == [] and ck.load_latest() is None


_WRITER = """
import sys
from pathlib import Path
import torch
from assets_store.checkpoints import Checkpoints

ck = Checkpoints(Path(sys.argv[1]), keep=2)
print("ready", flush=True)
step = 0
while True:
    step += 1
    ck.save(step, {"step": step, "x": torch.full((4_000_000,), float(step)), "tag": "s" * step})
"""


def _listing(folder: Path) -> set[str]:
    try:
        return set(os.listdir(folder))
    except FileNotFoundError:
        return set()


def _wait_for_a_new_file(folder: Path, timeout_s: float = 20.0) -> None:
    seen = _listing(folder)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        now = _listing(folder)
        if now - seen:
            return
        seen = now
    raise AssertionError("the writer stopped saving checkpoints")


@pytest.mark.parametrize("attempt", range(3))
def test_sigkill_during_save_never_leaves_a_loadable_partial_file(tmp_path: Path, attempt: int) -> None:
    folder = tmp_path / "ck"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(folder)], stdout=subprocess.PIPE, env=env, cwd=ROOT)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == b"ready"
        time.sleep(random.uniform(0.1, 1.0))
        _wait_for_a_new_file(folder)  # a save has just started writing: kill it mid-write
        time.sleep(random.uniform(0.0, 0.004))
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    ck = Checkpoints(folder)
    # Atomic writes mean no visible step file is ever partial: loading must not even need to skip one.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loaded = ck.load_latest()
    if loaded is not None:
        step, state = loaded
        assert state["step"] == step and state["tag"] == "s" * step
        assert torch.equal(state["x"], torch.full((4_000_000,), float(step)))
    # The killed writer's temporary (if any) is removed by the next save.
    ck.save(10**6, {"x": torch.zeros(1)})
    assert [p.name for p in folder.iterdir() if p.name.startswith(".")] == []


def test_another_hosts_temporary_is_kept_until_it_is_old(tmp_path: Path) -> None:
    from assets_store.atomic import HOST

    ck = Checkpoints(tmp_path)
    dead = 999_999_999  # no such process here
    here = tmp_path / f".step-000000002.ckpt.{HOST}.{dead}.tmp"
    elsewhere = tmp_path / f".step-000000003.ckpt.other-node-7.{dead}.tmp"
    stale = tmp_path / f".step-000000004.ckpt.other-node-8.{dead}.tmp"
    for path in (here, elsewhere, stale):
        path.write_bytes(os.urandom(100))
    old = time.time() - 2 * 3600
    os.utime(stale, (old, old))
    ck.save(5, {"x": torch.rand(3)})
    assert not here.exists() and not stale.exists()  # a dead writer of this host; another host's, long idle
    assert elsewhere.exists()  # its process id means nothing here: its writer may be alive
    assert ck.steps() == [5]
