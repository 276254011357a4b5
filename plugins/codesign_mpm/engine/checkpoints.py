"""A differentiable rollout's checkpoints: in memory up to a budget, the rest in a temporary file.

Checkpointing trades memory for one recompute, but the checkpoints of a long episode still add
up: scene (a) at the paper's scale (61.5k particles, 200 frames) stores 65 states of 5.9 MB, as
much again as the segment's slots. The backward pass reads each checkpoint once, in reverse, a
segment's compute (tenths of a second) apart, so a file serves it as well as memory: the
operating system caches it while memory is free and writes it out when it is not, and the
process's resident memory no longer grows with the episode.
"""
from __future__ import annotations

import os
import tempfile
from typing import BinaryIO

import numpy as np


class CheckpointStore:
    """Equal-shaped tuples of arrays (one particle state each), appended in order and read by index.

    The first ones stay in memory while they fit in `memory_bytes`; the others go to an anonymous
    temporary file in `directory` (default: the environment's CODESIGN_CHECKPOINT_DIR, else the
    system's temporary directory), which is reused by the next rollout and deleted with the store.
    """

    def __init__(self, memory_bytes: int, directory: str | None = None) -> None:
        self.memory_bytes = memory_bytes
        self.directory = directory or os.environ.get("CODESIGN_CHECKPOINT_DIR") or None
        self._in_memory: list[tuple[np.ndarray, ...]] = []
        self._on_disk = 0
        self._file: BinaryIO | None = None
        self._layout: list[tuple[tuple[int, ...], np.dtype]] = []

    def __len__(self) -> int:
        return len(self._in_memory) + self._on_disk

    @property
    def spilled(self) -> int:
        """How many of the checkpoints are in the file."""
        return self._on_disk

    def clear(self) -> None:
        """Forget every checkpoint (the file is kept, and overwritten by the next ones)."""
        self._in_memory, self._on_disk, self._layout = [], 0, []

    def append(self, state: tuple[np.ndarray, ...]) -> None:
        layout = [(a.shape, a.dtype) for a in state]
        if self._layout and layout != self._layout:
            raise ValueError("every checkpoint of a rollout must have the same arrays")
        self._layout = layout
        if self._on_disk == 0 and (len(self._in_memory) + 1) * self._record_bytes() <= self.memory_bytes:
            self._in_memory.append(state)
            return
        f = self._open()
        try:
            f.seek(self._on_disk * self._record_bytes())
            for a in state:
                f.write(np.ascontiguousarray(a).data)
            f.flush()
        except OSError as e:
            raise OSError(f"could not write checkpoint {len(self)} ({self._record_bytes() / 2**20:.1f} MB) to "
                          f"{self._where()}: {e}; set CODESIGN_CHECKPOINT_DIR to a directory with room, or "
                          "lower the episode's frames") from e
        self._on_disk += 1

    def __getitem__(self, k: int) -> tuple[np.ndarray, ...]:
        if not 0 <= k < len(self):
            raise IndexError(f"checkpoint {k} of {len(self)}")
        if k < len(self._in_memory):
            return self._in_memory[k]
        f = self._open()
        f.seek((k - len(self._in_memory)) * self._record_bytes())
        state = tuple(np.empty(shape, dtype) for shape, dtype in self._layout)
        for a in state:
            if f.readinto(memoryview(a).cast("B")) != a.nbytes:
                raise OSError(f"checkpoint {k} could not be read back from {self._where()}")
        return state

    def close(self) -> None:
        """Delete the file (if any) and forget every checkpoint."""
        if self._file is not None:
            self._file.close()
            self._file = None
        self.clear()

    def _record_bytes(self) -> int:
        return sum(int(np.prod(shape)) * dtype.itemsize for shape, dtype in self._layout)

    def _where(self) -> str:
        return self.directory or f"the temporary directory ({tempfile.gettempdir()})"

    def _open(self) -> BinaryIO:
        if self._file is None:
            self._file = tempfile.TemporaryFile(dir=self.directory)
        return self._file
