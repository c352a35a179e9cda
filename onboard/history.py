"""Fixed-memory histories for the onboard loop's statistics: the newest N values in a preallocated array.

A `collections.deque(maxlen=N)` of Python floats is bounded too, but it grows for N appends (at
100 Hz and N = one hour, a robot's resident memory climbs for its first hour: about 32 bytes per
float, 300 per (t, command) pair) and then holds several times what the numbers need. `Ring`
allocates and touches its whole array when built (or, for rows whose width is known only from
the first value, at the first append), so the process's memory does not move after that: what a
soak test (hil.soak) measures as zero growth. It reads like the deque it replaces: `append`,
`len`, iteration oldest first, `reversed` newest first (lazily: the loop takes the newest hundred
at telemetry rate without copying the rest), truthiness, and `np.asarray(ring)` oldest first.
"""

from __future__ import annotations

import numpy as np


class Ring:
    """The newest `capacity` floats (width None) or float rows (width w) appended."""

    def __init__(self, capacity: int, width: int | None = None):
        if int(capacity) < 1:
            raise ValueError(f"Ring capacity must be >= 1, got {capacity!r}")
        self.capacity = int(capacity)
        self.width = width
        self._a = None if width == 0 else self._alloc(width)
        self._n = 0  # values appended over the ring's life

    def _alloc(self, width):
        shape = (self.capacity,) if width is None else (self.capacity, int(width))
        return np.full(shape, np.nan)  # written now, so resident now: no growth later

    def reserve(self, width: int) -> None:
        """Allocate rows of `width` now (else the first append does, inside whoever appends)."""
        if self._a is None:
            self.width = int(width)
            self._a = self._alloc(self.width)

    def append(self, value) -> None:
        if self._a is None:  # rows whose width the first value gives
            self.reserve(len(value))
        self._a[self._n % self.capacity] = value
        self._n += 1

    def __len__(self) -> int:
        return min(self._n, self.capacity)

    def __bool__(self) -> bool:
        return self._n > 0

    def values(self) -> np.ndarray:
        """A copy of the held values, oldest first."""
        if self._a is None:
            return np.zeros((0,) if self.width is None else (0, 0))
        if self._n <= self.capacity:
            return self._a[: self._n].copy()
        i = self._n % self.capacity
        return np.concatenate((self._a[i:], self._a[:i]))

    def __array__(self, dtype=None, copy=None):
        v = self.values()
        return v if dtype is None else v.astype(dtype)

    def _row(self, j):
        return float(self._a[j]) if self.width is None else self._a[j].copy()

    def __iter__(self):
        start = self._n - len(self)
        return (self._row(k % self.capacity) for k in range(start, self._n))

    def __reversed__(self):
        return (self._row(k % self.capacity) for k in range(self._n - 1, self._n - 1 - len(self), -1))


class PairRing(Ring):
    """The newest `capacity` (t, vector) pairs, stored as rows [t, *vector]; iterates as (t, vector)."""

    def __init__(self, capacity: int):
        super().__init__(capacity, width=0)

    def append(self, pair) -> None:
        t, v = pair
        v = np.asarray(v, dtype=float).ravel()
        super().append(np.concatenate(([float(t)], v)))

    def reserve(self, width: int) -> None:
        """Allocate pairs of vectors of `width` now."""
        super().reserve(int(width) + 1)

    def _row(self, j):
        return float(self._a[j, 0]), self._a[j, 1:].copy()
