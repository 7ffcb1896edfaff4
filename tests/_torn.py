"""A helper of the resume tests: interrupt the real atomic writer mid-write."""
from pathlib import Path


def tear_atomic_write(monkeypatch, match):
    """Interrupt the real atomic writer while it writes a file whose final name satisfies ``match``: what is left
    on disk is the writer's own temporary file, half written (as after a kill during the write)."""
    import os

    real = os.replace
    torn = []

    def replace(src, dst):
        if match(Path(dst)) and not torn:
            data = Path(src).read_bytes()
            Path(src).write_bytes(data[: len(data) // 2])
            torn.append(Path(src))
            raise KeyboardInterrupt
        return real(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    return torn
