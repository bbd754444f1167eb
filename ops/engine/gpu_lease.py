"""Crash-safe GPU leases: every run that needs a GPU takes a free slot of one device of the host
(one slot per GPU by default, so a GPU is exclusive; ``$MORPHEUS_GPU_SLOTS`` gives each more).

Without leases every run asks for ``cuda`` and lands on GPU 0, so a ``gpu`` pool of 8 on an 8-GPU
host puts eight runs on one device. A lease is an ``fcntl.flock`` on ``gpu-<id>.lock`` in a folder
that every process of the host shares (``$MORPHEUS_LEASE_DIR``, default a host-local temporary
folder: GPU ids mean nothing on another host, so the folder must not be on shared storage). The
kernel drops the lock when its holder dies, however it dies, so a killed run frees its device at
once and nothing needs cleaning up.

Which GPUs: ``$MORPHEUS_GPUS`` (physical ids, comma-separated; ``none`` for none), else
``$CUDA_VISIBLE_DEVICES``, else every device torch sees. Lock files are named by physical id, so
processes with different ``CUDA_VISIBLE_DEVICES`` still never share a device; the torch device
is the id's position among the visible ones.

Slots: ``$MORPHEUS_GPU_SLOTS`` runs may hold one GPU at once (default 1: a GPU is exclusive). The
stages wait for the host at a batch of 8 (profiles in ``benchmarks/results``), so a second and third
process fill the GPU's idle time: three runs of 4 objects made 1.67× the objects per GPU-hour of
one run of 8 on an H200 in one device call (1.73× and 1.86× in two others;
``benchmarks/results/gpu_sharing_h200.md``), each run being slower. The
runs' peaks add up, so slots × the peak of one run must fit the GPU's memory; a GPU in an
exclusive compute mode takes one process only. Slot ``k`` is the lock ``gpu-<id>.slot<k>.lock``
(slot 0 keeps ``gpu-<id>.lock``); runs take slot 0 of every GPU before any slot 1, so they spread
over the GPUs first.
"""

from __future__ import annotations

import logging
import os
import socket
import tempfile
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from assets_store.fsutil import try_lock

log = logging.getLogger(__name__)

GPUS_ENV = "MORPHEUS_GPUS"
SLOTS_ENV = "MORPHEUS_GPU_SLOTS"
LEASE_DIR_ENV = "MORPHEUS_LEASE_DIR"


class GpuLeaseError(RuntimeError):
    """No GPU could be leased: none configured, a bad setting, or none freed up in time."""


@dataclass(frozen=True)
class LeaseSettings:
    folder: Path = field(default_factory=lambda: Path(os.environ.get(
        LEASE_DIR_ENV, Path(tempfile.gettempdir()) / "morpheus3d-gpu-leases")))
    poll_s: float = 0.5  # how often a waiting run tries again
    report_every_s: float = 30.0  # how often a waiting run says that it waits
    timeout_s: float | None = None  # None: wait as long as it takes


@dataclass(frozen=True)
class GpuLease:
    gpu: str  # physical id (what nvidia-smi shows)
    device: str  # the torch device in this process, e.g. "cuda:1"
    lock_path: Path
    waited_s: float
    slot: int = 0  # which of the GPU's ``slots`` this run holds
    slots: int = 1

    def describe(self) -> str:
        shared = f" slot {self.slot + 1} of {self.slots}" if self.slots > 1 else ""
        return f"GPU {self.gpu}{shared} ({self.device}), leased after waiting {self.waited_s:.1f} s"


def _ids(text: str, name: str) -> list[str]:
    items = [t.strip() for t in text.split(",") if t.strip()]
    if not items or items == ["none"]:
        return []
    if len(set(items)) != len(items):
        raise GpuLeaseError(f"{name}={text!r} lists a GPU twice")
    return items


def visible_gpus(env: Mapping[str, str] | None = None) -> list[tuple[str, str]]:
    """(physical id, torch device) of every GPU this process may lease (see the module docstring)."""
    env = os.environ if env is None else env
    cuda_visible = env.get("CUDA_VISIBLE_DEVICES")
    visible = _ids(cuda_visible, "CUDA_VISIBLE_DEVICES") if cuda_visible is not None else None
    if GPUS_ENV in env:
        chosen = _ids(env[GPUS_ENV], GPUS_ENV)
        if visible is not None:
            hidden = [g for g in chosen if g not in visible]
            if hidden:
                raise GpuLeaseError(f"{GPUS_ENV} names GPU(s) {', '.join(hidden)} that CUDA_VISIBLE_DEVICES="
                                    f"{cuda_visible!r} hides; list only visible ones or unset one of them")
            return [(g, f"cuda:{visible.index(g)}") for g in chosen]
        return [(g, f"cuda:{g}") for g in chosen]
    if visible is not None:
        return [(g, f"cuda:{i}") for i, g in enumerate(visible)]
    import torch

    return [(str(i), f"cuda:{i}") for i in range(torch.cuda.device_count())]


def gpu_count(env: Mapping[str, str] | None = None) -> int:
    """How many GPUs the host's runs may use (0 on a CPU host)."""
    return len(visible_gpus(env))


def gpu_slots(env: Mapping[str, str] | None = None) -> int:
    """Runs that may hold one GPU at once (``$MORPHEUS_GPU_SLOTS``, default 1)."""
    env = os.environ if env is None else env
    text = env.get(SLOTS_ENV, "1").strip()
    if not text.isdigit() or int(text) < 1:
        raise GpuLeaseError(f"{SLOTS_ENV}={text!r} must be a whole number ≥ 1 (runs per GPU; 1: exclusive)")
    return int(text)


def _lock_file(folder: Path, gpu: str, slot: int) -> Path:
    return folder / (f"gpu-{gpu}.lock" if slot == 0 else f"gpu-{gpu}.slot{slot}.lock")


def _take(path: Path) -> int | None:
    fd = try_lock(path)
    if fd is not None:  # who holds it, for people looking at the folder; the lock itself is what counts
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()} on {socket.gethostname()} since {time.strftime('%Y-%m-%dT%H:%M:%S')}\n"
                 .encode())
    return fd


@contextmanager
def gpu_lease(settings: LeaseSettings | None = None, want: str | None = None,
              on_wait: Callable[[float, list[str]], None] | None = None) -> Iterator[GpuLease]:
    """Hold one free GPU (``want``: only this physical id) for the ``with`` block.

    Waits while every slot of them is taken, calling ``on_wait(seconds waited, busy ids)`` every
    ``report_every_s`` (default: a log line); raises ``GpuLeaseError`` when none is configured or
    ``timeout_s`` passes.
    """
    s = settings or LeaseSettings()
    gpus = visible_gpus()
    slots = gpu_slots()
    if want is not None:
        gpus = [g for g in gpus if g[0] == want]
    if not gpus:
        raise GpuLeaseError(f"no GPU to lease{f' with id {want}' if want else ''}: set {GPUS_ENV} or "
                            "CUDA_VISIBLE_DEVICES, or run on the CPU (device=cpu)")
    s.folder.mkdir(parents=True, exist_ok=True)
    # Start at a different GPU per process so simultaneous starters do not all race for the first one.
    order = gpus[os.getpid() % len(gpus):] + gpus[:os.getpid() % len(gpus)]
    start = last_report = time.monotonic()
    report = on_wait or (lambda waited, busy: log.info("waiting %.0f s for a GPU: %s busy", waited, ", ".join(busy)))
    while True:
        for slot, (gpu, device) in ((k, g) for k in range(slots) for g in order):
            path = _lock_file(s.folder, gpu, slot)
            fd = _take(path)
            if fd is None:
                continue
            lease = GpuLease(gpu, device, path, round(time.monotonic() - start, 3), slot, slots)
            log.info("leased %s", lease.describe())
            try:
                yield lease
            finally:
                os.close(fd)  # closing the descriptor releases the flock
            return
        waited = time.monotonic() - start
        if s.timeout_s is not None and waited >= s.timeout_s:
            raise GpuLeaseError(f"no GPU of {', '.join(g for g, _ in gpus)} came free in {s.timeout_s:g} s "
                                f"(leases in {s.folder})")
        if time.monotonic() - last_report >= s.report_every_s or last_report == start:
            report(waited, [g for g, _ in gpus])
            last_report = time.monotonic()
        time.sleep(s.poll_s)


def needs_gpu(device: str) -> bool:
    """Whether a configuration's device name asks for a CUDA device (``auto`` only where one exists)."""
    if device == "auto":
        import torch

        return torch.cuda.is_available()
    return device.split(":")[0] == "cuda"


def wanted_gpu(device: str, gpus: list[tuple[str, str]]) -> str | None:
    """The physical id an explicit ``cuda:N`` names among ``gpus`` (N counts the visible GPUs)."""
    if ":" not in device:
        return None
    return next((gpu for gpu, dev in gpus if dev == f"cuda:{int(device.split(':')[1])}"), None)


@contextmanager
def leased_device(device: str, settings: LeaseSettings | None = None,
                  on_wait: Callable[[float, list[str]], None] | None = None) -> Iterator[tuple[str, GpuLease | None]]:
    """(the device to run on, the lease) for a configuration's device name: a leased ``cuda:N``
    when it asks for CUDA, else the name itself and no lease (a CPU host changes nothing). A CUDA
    request that names no visible GPU is passed on unchanged, for the stage to fail with its reason."""
    gpus = visible_gpus() if needs_gpu(device) else []
    want = wanted_gpu(device, gpus)
    if not gpus or (":" in device and want is None):
        yield device, None
        return
    with gpu_lease(settings, want, on_wait) as lease:
        try:
            yield lease.device, lease
        except Exception as exc:
            hint = memory_hint(exc)
            if hint:
                exc.add_note(hint)
            raise


def memory_hint(exc: BaseException) -> str | None:
    """What to change when a run ran out of GPU memory: with slots, the neighbours' peaks count too."""
    if not (isinstance(exc, RuntimeError) and "out of memory" in str(exc).lower() and "cuda" in str(exc).lower()):
        return None
    slots = gpu_slots()
    if slots > 1:
        return (f"{SLOTS_ENV}={slots} runs share each GPU and their memory peaks add up: lower {SLOTS_ENV} "
                "or the objects per batch (--batch, MORPHEUS_BATCH; benchmarks/results/gpu_sharing_h200.md "
                "lists the peaks)")
    return "lower the objects per batch (--batch, MORPHEUS_BATCH) or the preset's sizes"
