"""The tables of ``bench/accurate_map.py``: its per-case records grouped into rows (beams x length,
scene, frame position, all simulated frames, the real data) and written as markdown, with a
verdict per row (``LOSS`` where a row other than the first label is worse than it)."""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _map_data import SCENES, SPEED_BUCKETS, labelled_metrics  # noqa: E402

TOL = 5e-4  # a row loses where its EPE exceeds the base's by more than this (rounding of the tables)


def group_rows(records, labels) -> list[tuple[str, str, dict]]:
    """(group, name, {label: metrics}) rows of the table from the per-case records."""
    sim = [r for r in records if r["attrs"]["source"] == "sim"]
    groups: list[tuple[str, str, list]] = []
    for b in sorted({r["attrs"]["beams"] for r in sim}):
        for n in sorted({r["attrs"]["length"] for r in sim}):
            sel = [(r, None) for r in sim if r["attrs"]["beams"] == b and r["attrs"]["length"] == n]
            if sel:
                groups.append(("beams x length", f"{b} beams, {n} frames", sel))
    for sc in SCENES:
        sel = [(r, None) for r in sim if r["attrs"]["scene"] == sc]
        if sel:
            groups.append(("scene", sc, sel))
    for pos in ("first", "mid", "last"):
        sel = [(r, pos) for r in sim]
        groups.append(("position", pos, sel))
    if sim:
        groups.append(("all", "all simulated frames", [(r, None) for r in sim]))
    for r in records:
        if r["attrs"]["source"] != "sim":
            groups.append(("real", r["attrs"]["scene"], [(r, None)]))
    rows = []
    for g, name, sel in groups:
        row = {}
        for lab in labels:
            P, G, secs, nsec = [], [], 0.0, 0
            free = None
            for r, pos in sel:
                frames = [f for f in r["frames"] if pos is None or r["positions"][f] == pos]
                if r["truth"] is None:
                    free = r["label_free"][lab]
                    continue
                P += [r["preds"][lab][f] for f in frames]
                G += [r["truth"][f] for f in frames]
                if r["seconds"].get(lab) is not None:
                    secs, nsec = secs + r["seconds"][lab] * len(r["frames"]), nsec + len(r["frames"])
            if free is not None:
                row[lab] = {**free, "s_per_frame": secs / nsec if nsec else None}
            elif P:
                row[lab] = {**labelled_metrics(P, G), "s_per_frame": secs / nsec if nsec else None}
        if row:
            rows.append((g, name, row))
    return rows


def fmt(v, d=3):
    return "n/a" if v is None else f"{v:.{d}f}"


def table(rows, labels) -> str:
    base, others = labels[0], labels[1:]
    head = ["group", "cell"] + [f"{c} {lab}" for lab in labels for c in ("dyn norm", "static")]
    head += [f"fast dyn {lab}" for lab in labels] + [f"s/frame {lab}" for lab in labels] + ["verdict"]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for g, name, row in rows:
        if base not in row:
            continue
        if "unsupported" in row[base]:  # label-free
            cells = [f"{100 * row[lab]['unsupported']:.1f} % unsupported" if lab in row else "" for lab in labels]
            cells = [c for lab in labels for c in (cells[labels.index(lab)], "")]
            verdict = ", ".join(f"{lab}: LOSS" for lab in others if lab in row
                                and row[lab]["unsupported"] > row[base]["unsupported"] + TOL) or "ok"
            lines.append(f"| {g} | {name} | " + " | ".join(cells + [""] * len(labels))
                         + " | " + " | ".join(fmt(row[lab].get("s_per_frame")) for lab in labels) + f" | {verdict} |")
            continue
        cells = []
        for lab in labels:
            m = row.get(lab, {})
            cells += [fmt(m.get("dyn_norm")), fmt(m.get("static"))]
        cells += [fmt(row[lab]["speed"][f"{SPEED_BUCKETS[-1][0]:g}-inf"]["epe"]) if lab in row else "" for lab in labels]
        cells += [fmt(row[lab].get("s_per_frame")) if lab in row else "" for lab in labels]
        bad = []
        for lab in others:
            if lab not in row:
                continue
            for k in ("dyn_norm", "static"):
                a, b = row[lab].get(k), row[base].get(k)
                if a is not None and b is not None and a > b + TOL:
                    bad.append(f"{lab} {k}")
            ta, tb = row[lab].get("s_per_frame"), row[base].get("s_per_frame")
            if ta is not None and tb and ta > 2 * tb:  # issue 47: at most 2x paper's time a frame
                bad.append(f"{lab} time {ta / tb:.1f}x")
        lines.append(f"| {g} | {name} | " + " | ".join(cells) + f" | {'LOSS: ' + ', '.join(bad) if bad else 'ok'} |")
    return "\n".join(lines)


def speed_table(rows, labels) -> str:
    all_row = next((row for g, _, row in rows if g == "all"), None)
    if all_row is None:
        return ""
    lines = ["| true speed (m/frame) | points | " + " | ".join(f"dyn EPE {lab}" for lab in labels) + " |",
             "|" + " --- |" * (2 + len(labels))]
    for lo, hi in SPEED_BUCKETS:
        k = f"{lo:g}-{hi:g}"
        pts = all_row[labels[0]]["speed"][k]["points"]
        lines.append(f"| {k} | {pts} | " + " | ".join(fmt(all_row[lab]["speed"][k]["epe"]) for lab in labels) + " |")
    return "\n".join(lines)
