"""Whether an estimated frame of ``floxels run`` may be written (issue 45, item 3): one check
for both delivery points (one sequence: ``estimate_loop``; a dataset: ``dataset/stream``).

A frame is not written, and fails with the reason, when the method says it has no estimate
(``fields["failure"]``: Floxels' optimisation diverged) or when none of its support scans
(``Method.support_frames``: Floxels' window, a baseline's pair) could be read: the method then
saw empty scans beside its target and answered zero flow, which was written as "all static"
(``--scans 2`` with the next frame's file broken: 0 moving points instead of 2,652).
"""

from __future__ import annotations

__all__ = ["frame_failure"]


def frame_failure(method, options: dict, loader, i: int, n: int, fields=None) -> str | None:
    """Why frame ``i`` (of ``n``; its own scan read) gets no output, or None to write it.
    ``loader.get(j)`` is None for a frame that could not be used (``loader.errors[j]`` says why)."""
    if fields and fields.get("failure"):
        return str(fields["failure"])
    if method.support_frames is None:
        return None
    support = method.support_frames(i, n, options)
    if not support or any(loader.get(j) is not None for j in support):
        return None
    names = [loader.seq.frames[j].path.name for j in support]
    first = loader.errors.get(support[0], "unreadable")
    return (f"no support scan: none of the scans its estimate reads besides its own ({', '.join(names)}) could be "
            f"used, so no flow could be estimated ({first})")
