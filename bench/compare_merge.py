"""``bench/compare.py --merge``: rows of several part runs (each a JSON with its NPZ of
predictions and ground truth) recombined; a row split over parts (e.g. one scene per part)
gets its metrics recomputed over all its frames, point-weighted, and its time per frame
from the summed seconds and frames."""

from __future__ import annotations

import json
import os

import numpy as np

from compare_rows import clean, evaluate_rows, log
from compare_tables import ablation_table, main_table


def merge(paths, out_json=None, out_md=None) -> int:
    rows, preds, truth, parts = {}, {}, {}, []
    for p in paths:
        with open(p) as fh:
            part = json.load(fh)
        npath = p[:-5] + ".npz" if p.endswith(".json") else p + ".npz"
        npz = np.load(npath) if os.path.exists(npath) else None  # absent: the JSON metrics stand
        dataset = part["args"].get("dataset", "sim")
        sim = part["args"].get("sim") or {}
        tag = dataset + ("" if not sim else "[" + ",".join(f"{k}={v}" for k, v in sorted(sim.items())) + "]")
        parts.append({k: part.get(k) for k in ("part", "command", "device", "gpu", "title", "total_seconds")})
        for k in (npz.files if npz is not None else []):
            kind, *rest = k.split("|")
            if kind == "pred":
                key, scene, f = rest
                preds[(tag, key, scene, int(f))] = npz[k]
            else:
                scene, f, name = rest
                truth.setdefault((tag, scene, int(f)), {})[name] = npz[k]
        for r in part["rows"]:
            rid = (tag, r["key"])
            cur = rows.setdefault(rid, {**r, "key": r["key"], "dataset": tag, "frames": {}, "seconds": {},
                                        "gpu": part.get("gpu")})
            cur["parts"] = cur.get("parts", 0) + 1
            cur["frames"].update(r["frames"])
            cur["seconds"].update(r["seconds"])
    records = list(rows.values())
    for r in records:
        tag = r["dataset"]
        if r["parts"] == 1 and not any((tag, r["key"], sc, int(f)) in preds for sc, fr in r["frames"].items() for f in fr):
            continue  # one part without its NPZ: its own metrics stand
        evaluate_rows([r], lambda k, sc, f, t=tag: preds[(t, k, sc, int(f))], lambda sc, f, t=tag: truth[(t, sc, int(f))])
    md = []
    for tag in sorted({r["dataset"] for r in records}):
        sel = [r for r in records if r["dataset"] == tag]
        scenes = sorted({sc for r in sel for sc in r["frames"]})
        nfr = max(sum(len(v) for v in r["frames"].values()) for r in sel)
        head = f"{tag}: scenes {', '.join(scenes)}; up to {nfr} evaluated frames per row"
        m = [r for r in sel if r["group"] == "main"]
        a = [r for r in sel if r["group"] != "main"]
        if m:
            md.append(f"### Comparison ({head})\n\n{main_table(m)}\n")
        if a:
            md.append(f"### Floxels ablations ({head})\n\n{ablation_table(a)}\n")
    text = "\n".join(md)
    log(text)
    if out_md:
        with open(out_md, "w") as fh:
            fh.write(text)
    out_json = out_json or os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "compare_merged.json")
    os.makedirs(os.path.dirname(os.path.abspath(out_json)), exist_ok=True)
    with open(out_json, "w") as fh:
        json.dump(clean({"parts": parts, "rows": records}), fh, indent=1, default=str)
    log(f"wrote {out_json}")
    return 0
