"""Columnar batches: a batch of observations sent as one observation whose values carry the batch.

A batched ``infer`` (``{observations: [obs, ...], env_ids}``) names every environment's arrays one by one: at
2,048 environments with three cameras that is 6,144 images, each sized, placed, framed, parsed and copied on its
own, and that per-environment work, not the bytes, was most of a request's time. The columnar form (advertised as
``capabilities.columnar_batch``) sends the batch the way a batched simulator holds it::

    {columns: {images: {head: uint8[B, H, W, 3], ...}, state: {joint_pos: float32[B, 14], ...},
               instruction: [str, ... B of them], meta: {episode: [int, ... B], ...}},
     env_ids: [id, ... B]}

Maps keep the observations' own keys; every other value is a *column*: an array whose first axis is the batch
(the environments' arrays of one shape and dtype, stacked), or a list of ``B`` values (anything else: strings,
numbers, arrays of differing shapes). Environment ``i``'s observation is every column's ``i``-th entry in the
same maps (``split``), so a server that does not care about columns hands its model exactly the observations
the list form would have carried.

On the client, a column of arrays stays a ``Rows`` until it goes on the wire: rows a batched simulator rendered
into one buffer lie at a constant distance from one another there, and are copied from that buffer as one array
(``Rows.runs``), into shared memory or into the frame.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

from xpolicylab.errors import ErrorCode, ProtocolError

#: The payload key of a columnar batch (the list form's is ``observations``).
KEY = "columns"


#: A column whose rows are at most this many bytes is one run by stacking them (a copy): reading a row's address to
#: find runs costs about as much as copying a few kB, so a joint state column (56-byte rows) stacks in
#: microseconds where finding its runs took milliseconds at 2,048 environments. Images are far larger.
STACKED_ROW_BYTES = 4096


class Rows:
    """The environments' arrays of one column (same shape and dtype), not yet stacked."""

    __slots__ = ("arrays", "_runs")

    def __init__(self, arrays: Sequence[np.ndarray]) -> None:
        self.arrays = list(arrays)
        self._runs: list[tuple[int, np.ndarray]] | None = None

    @property
    def shape(self) -> tuple[int, ...]:
        return (len(self.arrays), *self.arrays[0].shape)

    @property
    def dtype(self) -> np.dtype:
        return self.arrays[0].dtype

    @property
    def row_nbytes(self) -> int:
        return self.arrays[0].nbytes

    @property
    def nbytes(self) -> int:
        return self.row_nbytes * len(self.arrays)

    def runs(self) -> list[tuple[int, np.ndarray]]:
        """``(first row, array of those rows)`` covering every row in order, each run one array over memory that
        is already there: rows that are views of one buffer (C-contiguous each) at a constant distance from one
        another (one after another, or one camera's images of a ``[B, cameras, H, W, 3]`` batch) are one run,
        without a copy; any other row is its own run. Small rows (`STACKED_ROW_BYTES`) are one run, stacked. Found
        once: reading each row's address is most of the cost of placing a column, and a request asks twice
        (whether it lies in a lent buffer, then where it goes)."""
        if self._runs is None:
            self._runs = list(self._find_runs())
        return self._runs

    def _find_runs(self) -> Iterator[tuple[int, np.ndarray]]:
        rows = self.arrays
        if self.row_nbytes <= STACKED_ROW_BYTES:  # reading each row's address costs more than copying small rows
            yield 0, np.stack(rows)
            return
        start = 0
        while start < len(rows):
            first, stop = rows[start], start + 1
            if first.flags.c_contiguous and first.base is not None and first.nbytes and stop < len(rows):
                address, stride = first.ctypes.data, rows[stop].ctypes.data - first.ctypes.data
                if stride >= first.nbytes:  # rows that do not overlap, in order
                    while (stop < len(rows) and rows[stop].base is first.base and rows[stop].flags.c_contiguous
                           and rows[stop].ctypes.data == address + (stop - start) * stride):
                        stop += 1
            if stop - start == 1:
                yield start, first[None]
            else:  # every row is a view of one buffer, each `stride` bytes after the one before
                yield start, np.lib.stride_tricks.as_strided(first, (stop - start, *first.shape),
                                                             (stride, *first.strides), writeable=False)
            start = stop

    def joined(self) -> np.ndarray:
        """The column as one C-contiguous array ``[B, ...]``: the rows' own buffer when they lie one after another
        in it, else a copy."""
        runs = [run for _, run in self.runs()]
        return np.ascontiguousarray(runs[0]) if len(runs) == 1 else np.concatenate(runs)

    def take(self, start: int, stop: int) -> Rows:
        return Rows(self.arrays[start:stop])


def gather(observations: Sequence[Any]) -> Any:
    """The columns of ``observations`` (one value per environment), or ``None`` when they are not all maps of the
    same keys: such a batch goes as a list of observations instead. Arrays of one shape and dtype become a
    ``Rows``; anything else a list of the environments' values."""
    first = observations[0]
    if isinstance(first, dict):
        if not all(isinstance(o, dict) and len(o) == len(first) for o in observations):
            return None
        out = {}
        for key in first:
            if not isinstance(key, str):
                return None
            try:
                column = gather([o[key] for o in observations])
            except KeyError:  # same sizes, other keys
                return None
            if column is None:
                return None
            out[key] = column
        return out
    if isinstance(first, np.ndarray) and all(isinstance(o, np.ndarray) and o.shape == first.shape
                                             and o.dtype == first.dtype for o in observations):
        return Rows(observations)
    if any(isinstance(o, dict) for o in observations):
        return None  # a map in some environments only
    return list(observations)


def take(columns: Any, start: int, stop: int) -> Any:
    """The columns of environments ``start`` to ``stop`` (for a batch split over several requests)."""
    if isinstance(columns, dict):
        return {k: take(v, start, stop) for k, v in columns.items()}
    if isinstance(columns, Rows):
        return columns.take(start, stop)
    return columns[start:stop]


def joined(columns: Any) -> Any:
    """``columns`` with every ``Rows`` as one array (what goes through the socket)."""
    if isinstance(columns, dict):
        return {k: joined(v) for k, v in columns.items()}
    return columns.joined() if isinstance(columns, Rows) else columns


def _invalid(message: str, path: str) -> ProtocolError:
    return ProtocolError(ErrorCode.INVALID_FRAME, message, {"field": f"{KEY}{path}"})


def check(columns: Any, count: int, path: str = "") -> None:
    """Raise ``invalid_frame``, naming the column, unless ``columns`` is a map whose every column holds ``count``
    entries (an array with a first axis of ``count``, or a list of ``count`` values)."""
    if not path and not isinstance(columns, dict):
        raise _invalid(f"{KEY!r} must be a map of columns", path)
    for key, value in columns.items():
        where = f"{path}.{key}"
        if not isinstance(key, str):
            raise _invalid(f"column names must be strings, got {key!r}", path)
        if isinstance(value, dict):
            check(value, count, where)
        elif isinstance(value, np.ndarray):
            if value.ndim == 0 or value.shape[0] != count:
                raise _invalid(f"column {where[1:]!r} is an array of shape {list(value.shape)}; its first axis must "
                               f"be the batch, {count} environments", where)
        elif isinstance(value, list):
            if len(value) != count:
                raise _invalid(f"column {where[1:]!r} holds {len(value)} values for {count} environments", where)
        else:
            raise _invalid(f"column {where[1:]!r} must be an array, a list or a map, got {type(value).__name__}",
                           where)


def split(columns: dict[str, Any], count: int) -> list[dict[str, Any]]:
    """Environment by environment, the observations ``columns`` (checked, see ``check``) holds; array entries
    are views of the column."""
    return [_entry(columns, i) for i in range(count)]


def _entry(columns: Any, i: int) -> Any:
    if isinstance(columns, dict):
        return {k: _entry(v, i) for k, v in columns.items()}
    return columns[i]
