"""What a method sees of the stream's scans (``layout.StreamScans``) besides the stream itself:
one segment as a sequence of its own (:class:`SegmentView`, for a method's
``estimate_sequence``), and one per-scan field as a sequence (:class:`SensorView`,
:class:`GroundView`: the ``sensors=`` and ``ground=`` of the methods that take them)."""

from __future__ import annotations

from collections.abc import Sequence

__all__ = ["SegmentView", "SensorView", "GroundView"]


class SegmentView(Sequence):
    """Stream scans ``[lo, hi)`` as a sequence of their own (for ``estimate_sequence``)."""

    def __init__(self, scans, lo: int, hi: int) -> None:
        self.scans, self.lo, self.hi = scans, lo, hi

    def __len__(self) -> int:
        return self.hi - self.lo

    def __getitem__(self, k):
        if isinstance(k, slice):
            idx = range(len(self))[k]
            if k.step in (None, 1) and len(idx):
                return self.scans[self.lo + idx[0]:self.lo + idx[-1] + 1]
            return [self.scans[self.lo + j] for j in idx]
        k = int(k)
        if k < 0:
            k += len(self)
        if not 0 <= k < len(self):
            raise IndexError(k)
        return self.scans[self.lo + k]

    def sensor(self, k: int):
        return self.scans.sensor(self.lo + k)

    def ground(self, k: int):
        return self.scans.ground(self.lo + k)


class ScanFieldView(Sequence):
    """One per-scan field (``FIELD(k)``) of a scan sequence that has it (StreamScans, SegmentView),
    as a sequence of its own: what the methods that take it get (``sensors=``, ``ground=``)."""

    FIELD = ""

    def __init__(self, scans) -> None:
        self.scans = scans

    def __len__(self) -> int:
        return len(self.scans)

    def __getitem__(self, k):
        get = getattr(self.scans, self.FIELD)
        if isinstance(k, slice):
            return [get(j) for j in range(len(self))[k]]
        return get(int(k))


class SensorView(ScanFieldView):
    """Each scan's sensor position (``sensors=``)."""

    FIELD = "sensor"


class GroundView(ScanFieldView):
    """Each scan's ground returns, where the loader keeps them (``ground=``)."""

    FIELD = "ground"
