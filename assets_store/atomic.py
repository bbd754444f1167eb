"""The store's atomic writes. The primitive lives in ``morpheus_core.runtime.atomic_io`` (the method writes
checkpoints and exports too, and must not import the store); this is the store's name for it."""

from morpheus_core.runtime.atomic_io import HOST, atomic_write, atomic_write_bytes, atomic_write_text

__all__ = ["HOST", "atomic_write", "atomic_write_bytes", "atomic_write_text"]
