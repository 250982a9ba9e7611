"""A Ray wheel small enough to travel to a device machine (whose image has no Ray).

The device tool carries at most 64 MiB of working tree; Ray's manylinux wheel is ~79 MB. Most
of it is Java (``ray/jars/``, 32 MB) and libraries ``floxels run --ray`` never imports (RLlib,
Serve, Tune, Train, LLM). This rewrites the wheel without them and with a RECORD that lists
exactly the files left (pip checks it), keeping the core (``ray/_raylet.so``, ``ray/core``: the
GCS and raylet binaries), the dashboard agent (started by every node) and ``ray.data``/
``ray.util``.

    python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \\
        --platform manylinux2014_x86_64 -d /tmp/raywhl ray==2.60.0 jsonschema jsonschema-specifications \\
        referencing rpds-py
    python tools/strip_ray_wheel.py /tmp/raywhl/ray-2.60.0-cp312-*.whl .whl/
    cp /tmp/raywhl/{jsonschema,jsonschema_specifications,referencing,rpds_py}-*.whl .whl/

(jsonschema and its three dependencies are the only Ray requirements the device image lacks,
``/work/.library/device/KINDS.md``.) On the device: ``python3 -m pip install -q --no-index
--no-deps --no-compile --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site``.
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import zipfile
from pathlib import Path

DROP = ("ray/jars/", "ray/rllib/", "ray/serve/", "ray/tune/", "ray/train/", "ray/llm/")


def strip(src: Path, dst_dir: Path, drop=DROP) -> Path:
    dst_dir.mkdir(parents=True, exist_ok=True)
    dst = dst_dir / src.name
    records = []
    record_name = None
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED, compresslevel=6) as zout:
        for info in zin.infolist():
            name = info.filename
            if name.endswith(".dist-info/RECORD"):
                record_name = name
                continue
            if name.startswith(drop):
                continue
            data = zin.read(info)
            out = zipfile.ZipInfo(name, date_time=info.date_time)
            out.external_attr = info.external_attr  # keeps the executables (raylet, gcs_server) executable
            out.compress_type = zipfile.ZIP_DEFLATED
            zout.writestr(out, data)
            if not name.endswith("/"):
                digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
                records.append(f"{name},sha256={digest},{len(data)}")
        if record_name is None:
            raise SystemExit(f"{src}: no .dist-info/RECORD; not a wheel")
        records.append(f"{record_name},,")
        zout.writestr(record_name, "\n".join(records) + "\n")
    return dst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("wheel", type=Path)
    ap.add_argument("out_dir", type=Path)
    args = ap.parse_args()
    dst = strip(args.wheel, args.out_dir)
    print(f"{dst}: {dst.stat().st_size / 1e6:.1f} MB (from {args.wheel.stat().st_size / 1e6:.1f} MB)")


if __name__ == "__main__":
    main()
