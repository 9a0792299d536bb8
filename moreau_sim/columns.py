"""A recording's storage: the columns of one group of trajectory.py's schema, grown in place by at most BLOCK_ROWS rows
(memory proportional to what was recorded, with at most FIT_SLACK_BYTES of unused rows a group), or, spilling,
SPILL_BYTES of rows in memory and the rest in unnamed temporary files (docs/theory.md §5). recording.Recorder
writes them."""

from __future__ import annotations

import functools
import math
import mmap
import tempfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

BLOCK_ROWS = 1 << 14  # the most rows a full column grows by at a time (see Columns)
SPILL_BYTES = 8 << 20  # [bytes] the rows a spilling group of columns keeps in memory before it writes them out
# [bytes] the most a group of columns reserves at the start for the rows it expects: address space only, its pages
# become memory as rows are written (a run that records what it expected never grows or copies a column)
RESERVE_BYTES = 1 << 30
FIT_SLACK_BYTES = 64 << 10  # [bytes] unused rows a group of columns keeps at the end of a recording (Columns.fit)


@functools.lru_cache(maxsize=64)
def layout(schema: tuple, sizes: tuple) -> tuple[dict, dict, dict]:
    """The shapes and dtypes of a schema's columns at the model's sizes, and the bytes of one row of each (the same
    for every run of a model: made once). The dicts are shared: read only."""
    sizes = dict(sizes)
    shapes = {k: tuple(sizes.get(d, d) for d in shape) for k, (_, shape) in schema}
    dtypes = {k: np.dtype(dtype) for k, (dtype, _) in schema}
    return shapes, dtypes, {k: dtypes[k].itemsize * math.prod(shapes[k]) for k in shapes}


class Columns:
    """Arrays of one schema group, `n` rows recorded. A full column grows in place (ndarray.resize:
    realloc, which for large arrays remaps pages instead of copying them) by as many rows as it
    has, at most BLOCK_ROWS at a time, and is cut to its n rows when the recording ends (fit; rows to
    spare of at most FIT_SLACK_BYTES are left): the memory stays ~ the rows recorded, with no copy
    and at most BLOCK_ROWS rows to spare. A row counts (commit) only once written: an interrupt never
    leaves a half-written row.

    With `spill` (a folder), every SPILL_BYTES of rows the columns move their rows to one unnamed
    temporary file each there (rows [0, spilled); the columns in memory hold the rest) and
    arrays() returns read-only maps of those files: the memory is one block of rows, the files
    vanish with the last map or on any exit of the process (they have no name)."""

    def __init__(self, schema: dict, sizes: dict, capacity: int, spill: str | Path | None = None):
        self.shapes, self.dtypes, self.row_bytes = layout(tuple(schema.items()), tuple(sorted(sizes.items())))
        row = sum(self.row_bytes.values())
        # spilling: the rows of one block (at least one)
        self.block = max(1, SPILL_BYTES // row)
        capacity = min(capacity, self.block if spill is not None else max(1, RESERVE_BYTES // max(row, 1)))
        self.cols = {k: np.empty((max(capacity, 1),) + self.shapes[k], dtype) for k, (dtype, _) in schema.items()}
        self.n = 0
        self.spilled = 0  # rows in the spill files (rows [0, spilled); cols[k][i] is row spilled + i)
        self.keep = 0  # the last rows a spill leaves in memory (written to the files too): rows still to be changed
        self._files = None if spill is None else {k: tempfile.TemporaryFile(dir=spill) for k in schema}
        self._closed: dict | None = None  # the arrays once the spill files are closed

    def free(self) -> int:
        """Index in cols of the next row (growing or spilling the columns if full); call commit() once
        it is written."""
        i = self.n - self.spilled
        if i == len(next(iter(self.cols.values()))):
            if self._files is not None and i >= self.block:
                self._spill()
                i = self.n - self.spilled  # the rows it keeps
            if i == len(next(iter(self.cols.values()))):
                self._resize(i + min(max(i, 64), BLOCK_ROWS))
        return i

    def commit(self, rows: int = 1) -> None:
        self.n += rows

    def reserve(self, rows: int) -> int:
        """Index in cols of the next row, with at least `rows` rows free from it (grown or spilled as free()
        does); commit(k) once k of them are written (compiled_run.py writes them in C++)."""
        i = self.free()
        while len(next(iter(self.cols.values()))) - i < rows:
            if self._files is not None and i > min(self.keep, self.n - self.spilled):
                self._spill()
                i = self.n - self.spilled
            else:
                self._resize(i + max(rows, min(max(i, 64), BLOCK_ROWS)))
        return i

    @property
    def last(self) -> int:
        """Index in cols of the last row recorded."""
        return self.n - 1 - self.spilled

    def _resize(self, rows: int) -> None:
        m = self.n - self.spilled
        for k in self.cols:
            try:  # in place; refused (ValueError) while a view of the array is alive: then copied
                self.cols[k].resize((rows,) + self.cols[k].shape[1:])
            except ValueError:
                a = self.cols[k]
                b = np.empty((rows,) + a.shape[1:], a.dtype)
                b[:min(rows, m)] = a[:min(rows, m)]
                self.cols[k] = b

    def _spill(self) -> None:
        """Write the rows in memory to the spill files, at their place (an interrupted spill is
        simply redone: `spilled` moves only once every column is written); the last `keep` rows stay in
        memory as the first ones (a later spill writes them again, as they are then)."""
        m = self.n - self.spilled
        if m == 0:
            return
        for k, a in self.cols.items():
            write_at(self._files[k], a[:m], self.spilled * self.row_bytes[k])
        keep = min(self.keep, m)
        if keep:
            for a in self.cols.values():
                a[:keep] = a[m - keep:m].copy()
        self.spilled = self.n - keep

    def fit(self) -> None:
        """Release the rows not used (at the end of a recording), unless they are at most FIT_SLACK_BYTES (cutting
        a column costs a call per column, a few µs a group: more than a short run's recording); spilling: all rows
        go to the files."""
        if self._files is not None:
            self._spill()
        rows, used = len(next(iter(self.cols.values()))), max(self.n - self.spilled, 1)
        if rows > used and (rows - used) * sum(self.row_bytes.values()) > FIT_SLACK_BYTES:
            self._resize(used)

    def load(self, arrays: Mapping[str, np.ndarray]) -> None:
        """Start from rows recorded earlier (a checkpoint's arrays: a dict, or an open NPZ whose
        arrays are read one at a time; spilling, each goes to its file)."""
        for k in self.cols:
            a = np.ascontiguousarray(arrays[k], self.dtypes[k])
            n = len(a)
            if self._files is not None:
                write_at(self._files[k], a, 0)
                keep = min(self.keep, n)  # the rows still to be changed, in memory as a spill leaves them
                if keep > len(self.cols[k]):
                    self.cols[k] = np.empty((keep,) + self.shapes[k], self.dtypes[k])
                self.cols[k][:keep] = a[n - keep:]
                continue
            if n > len(self.cols[k]):
                self._resize(n)
            self.cols[k][:n] = a
        self.n = n
        if self._files is not None:
            self.spilled = n - min(self.keep, n)

    def arrays(self) -> dict[str, np.ndarray]:
        if self._files is None:
            return {k: a[:self.n] for k, a in self.cols.items()}
        if self._closed is not None:
            return self._closed
        self._spill()
        return {k: file_rows(self._files[k], self.n, self.dtypes[k], self.shapes[k]) for k in self.cols}

    def close(self) -> None:
        """Close the spill files (the end of a recording; maps of them stay valid: a map keeps its file)."""
        if self._files is not None and self._closed is None:
            self._closed = self.arrays()
            for f in self._files.values():
                f.close()


def write_at(f, a: np.ndarray, offset: int) -> None:
    """The bytes of the C-contiguous array `a` into the file `f` at byte `offset`, flushed (a map
    of the file then reads them)."""
    f.seek(offset)
    f.write(memoryview(a.reshape(-1).view(np.uint8)))
    f.flush()


def file_rows(f, n: int, dtype: np.dtype, shape: tuple) -> np.ndarray:
    """The first n rows of a spill file, as a read-only array over a map of it."""
    size = dtype.itemsize * math.prod(shape) * n
    if size == 0:
        a = np.empty((n,) + shape, dtype)
        a.flags.writeable = False  # read-only as every spilled array
        return a
    return np.frombuffer(mmap.mmap(f.fileno(), size, access=mmap.ACCESS_READ), dtype).reshape((n,) + shape)
