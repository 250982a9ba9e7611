"""Which output of a ``floxels run`` OUT_DIR a frame argument of ``floxels show`` /
``accumulate`` means (issue 45, item 4).

A frame is named by its name (the output's stem, e.g. ``000042``) or by its index among the
run's *input* frames, counted as ``floxels run --frames A:B`` counts them (negative from the
end). Indices used to count the outputs instead: a frame that failed or was not selected
shifted every later one, so ``--frame 2`` of a run whose 000002 failed drew 000003, and in a
``--frames 3:5`` run ``--frame 1`` drew 000004. The input frames are listed as the run listed
them: the files of the recorded ``source``'s directory with its extension, in natural order.
A frame of the input without an output is an error that says so, with its failure from the
run's ``run_summary.json`` when it has one.
"""

from __future__ import annotations

import json
from pathlib import Path

__all__ = ["RunFrames"]


class RunFrames:
    """The outputs of ``run_dir`` (natural order) and the frames of the input they came from."""

    def __init__(self, run_dir) -> None:
        from floxels_ext.cli import CLIError
        from floxels_ext.lidar.io.outputs import run_outputs

        self.dir = Path(run_dir)
        try:
            files = run_outputs(self.dir)
        except FileNotFoundError as e:
            raise CLIError(str(e)) from None
        self.outputs = {p.stem: p for p in files}
        self.names = list(self.outputs)
        self._inputs: list[str] | None | bool = False  # False: not listed yet
        self.source_dir: Path | None = None

    # -- the run's input --------------------------------------------------------------
    def inputs(self) -> list[str] | None:
        """The names of the run's input frames in the run's order, or None when its files
        cannot be listed (no recorded source, or the input moved)."""
        if self._inputs is False:
            self._inputs = self._list_inputs()
        return self._inputs

    def _list_inputs(self) -> list[str] | None:
        from floxels_ext.lidar.io.readers import natural_key
        from floxels_ext.numpy_files import open_npz

        try:
            with open_npz(self.outputs[self.names[0]]) as z:
                src = Path(str(z["source"])) if "source" in z.files else None
        except Exception:  # an unreadable output: the drawing reports it; indices are unknown
            return None
        if src is None or not src.parent.is_dir():
            return None
        suffix = src.suffix.lower()
        files = [p for p in src.parent.iterdir() if p.suffix.lower() == suffix and not p.name.startswith(".")
                 and (p.is_file() or p.is_symlink())]
        names = [p.stem for p in sorted(files, key=lambda p: natural_key(p.name))]
        if not set(self.names) <= set(names):
            return None  # outputs of other files (renamed, deleted): the run's indices are lost
        self.source_dir = src.parent
        return names

    def failure(self, name: str) -> str | None:
        """The message ``run_summary.json`` records for frame ``name``, if any."""
        try:
            summary = json.loads((self.dir / "run_summary.json").read_text())
            return next((f["message"] for f in summary.get("failures", []) if f.get("frame") == name), None)
        except (OSError, ValueError, TypeError, AttributeError, KeyError):
            return None

    # -- choosing ---------------------------------------------------------------------
    def pick(self, frame: str | int | None, note=print) -> str:
        """The output name ``frame`` means (None: the first output). CLIError when it names no
        frame or a frame without output; ``note(msg)`` where a name also reads as an index of
        another frame (the name wins)."""
        from floxels_ext.cli import CLIError

        if frame is None:
            return self.names[0]
        text = str(frame).strip()
        index = _as_int(text)
        inputs = self.inputs()
        if text in self.outputs:
            if index is not None and inputs is not None and -len(inputs) <= index < len(inputs) \
                    and inputs[index] != text:
                note(f"note: {text} is taken as the frame named {text}; the frame of index {text} is {inputs[index]}")
            return text
        if index is None:
            if inputs is not None and text in inputs:
                raise CLIError(self._no_output(text))
            raise CLIError(f"{self.dir} has no frame named {text!r} (outputs: {self._span()}; a frame is its "
                           f"name or its index among the run's input frames)")
        if inputs is None:
            raise CLIError(f"{self.dir}: frame {text} is not an output name, and the run's input frames cannot be "
                           f"listed to count an index (the directory of its source moved, or lost frames since); give a frame name "
                           f"(outputs: {self._span()})")
        if not -len(inputs) <= index < len(inputs):
            raise CLIError(f"frame index {index} is out of range: the input of {self.dir} ({self.source_dir}) holds "
                           f"{len(inputs)} frames (0 .. {len(inputs) - 1})")
        name = inputs[index]
        if name not in self.outputs:
            raise CLIError(self._no_output(name, index % len(inputs)))
        return name

    def neighbours(self, name: str, k: int) -> tuple[list[tuple[int, str | None]], list[str]]:
        """The frames within ``k`` of ``name`` in the run's input, as (offset, output name or None
        where that frame has no output), and the names of those without output; by output
        order when the input cannot be listed (offsets then assume consecutive outputs)."""
        inputs = self.inputs()
        seq = inputs if inputs is not None else self.names
        r = seq.index(name)
        around = [(j - r, seq[j] if seq[j] in self.outputs else None)
                  for j in range(max(0, r - k), min(len(seq), r + k + 1))]
        missing = [seq[j + r] for j, n in around if n is None]
        return around, missing

    def path(self, name: str) -> Path:
        return self.outputs[name]

    def _span(self) -> str:
        return f"{self.names[0]} .. {self.names[-1]}" if len(self.names) > 1 else self.names[0]

    def _no_output(self, name: str, index: int | None = None) -> str:
        what = f"frame {name}" + (f" (index {index})" if index is not None else "")
        why = self.failure(name)
        return (f"{self.dir}: {what} has no output: " + (f"it failed in the run: {why}" if why else
                "it was not estimated (outside the run's --frames, failed in an earlier run, or not reached)")
                + f"; outputs: {self._span()}")


def _as_int(text: str) -> int | None:
    """``text`` as an index; zero-padded numbers (``000009``) are names, never indices."""
    digits = text[1:] if text.startswith("-") else text
    if len(digits) > 1 and digits.startswith("0"):
        return None
    try:
        return int(text)
    except ValueError:
        return None
