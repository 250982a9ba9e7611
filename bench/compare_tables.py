"""Markdown tables of bench/compare.py rows (paper style: Tables 1-4 and the appendix)."""

from __future__ import annotations

import math


def fmt(v, digits=3) -> str:
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def _cells(m) -> list[str]:
    return [fmt(m.get("dynamic_epe")), fmt(m.get("dynamic_acc5")), fmt(m.get("dynamic_acc10")),
            fmt(m.get("dynamic_angle")), fmt(m.get("static_epe")), fmt(m.get("static_acc5")),
            fmt(m.get("static_acc10")), fmt(m.get("mean_dynamic_normalized_epe"))]


_HEAD = ("dyn EPE | dyn Acc5 | dyn Acc10 | dyn angle (rad) | static EPE | static Acc5 | static Acc10 "
         "| mean dyn norm EPE (bucketed) | s/frame")


def main_table(rows) -> str:
    lines = [f"| method | {_HEAD} |", "|" + " --- |" * 10]
    for r in rows:
        lines.append(f"| {r['label']} | " + " | ".join(_cells(r["metrics"]))
                     + f" | {fmt(r['seconds_per_frame'], 3)} |")
    return "\n".join(lines)


def ablation_table(rows) -> str:
    lines = [f"| group | setting | {_HEAD} |", "|" + " --- |" * 11]
    for r in rows:
        lines.append(f"| {r['group']} | {r['label']} | " + " | ".join(_cells(r["metrics"]))
                     + f" | {fmt(r['seconds_per_frame'], 3)} |")
    return "\n".join(lines)


def beyond_table(rows) -> str:
    """The ``accurate`` preset against ``paper`` (issue 33): the targets' columns, and each
    row's ratio to the paper row's dynamic normalised EPE and time."""
    ref = next((r for r in rows if r["label"] == "paper"), rows[0])
    m0 = ref["metrics"]
    lines = ["| setting | dyn EPE | static EPE | mean dyn norm EPE (bucketed) | x paper | car speed ratio (median) "
             "| s/frame | x paper |", "|" + " --- |" * 8]
    for r in rows:
        m = r["metrics"]
        a, b = m.get("mean_dynamic_normalized_epe"), m0.get("mean_dynamic_normalized_epe")
        ratio = a / b if a is not None and b else float("nan")
        tr = r["seconds_per_frame"] / ref["seconds_per_frame"] if ref["seconds_per_frame"] else float("nan")
        lines.append(f"| {r['label']} | {fmt(m.get('dynamic_epe'))} | {fmt(m.get('static_epe'))} | "
                     f"{fmt(a)} | {fmt(ratio, 2)} | {fmt(m.get('car_speed_ratio'), 2)} | "
                     f"{fmt(r['seconds_per_frame'], 3)} | {fmt(tr, 2)} |")
    return "\n".join(lines)
