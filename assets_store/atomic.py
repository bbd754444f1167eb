"""The store's atomic writes. The primitive lives in ``morpheus_core.atomic_io`` (the method writes
checkpoints and exports too, and must not import the store); this is the store's name for it."""

from morpheus_core.atomic_io import atomic_write, atomic_write_bytes, atomic_write_text

__all__ = ["atomic_write", "atomic_write_bytes", "atomic_write_text"]
