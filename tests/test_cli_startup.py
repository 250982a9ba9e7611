"""``floxels --help`` loads neither torch nor numpy (it took 1.4-2.3 s when the package import
loaded torch), while ``import floxels_ext`` still registers ``torch.ops.floxels.*`` and the
public names still resolve. Checked in fresh interpreters (what a module imports, not a timing)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import floxels_ext

# the subprocess must import the same floxels_ext as the tests (installed or in-place build)
PYTHON_DIR = str(Path(floxels_ext.__file__).resolve().parents[1])

_LOADED = """
import json, sys
{code}
print(json.dumps({{"torch": "torch" in sys.modules, "numpy": "numpy" in sys.modules}}))
"""


def _python(code: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [PYTHON_DIR, os.environ.get("PYTHONPATH")])))
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)


def _loaded_after(code: str) -> dict:
    r = _python(_LOADED.format(code=code))
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def _help(args: list[str]) -> str:
    return f"""
import contextlib, io
from floxels_ext import cli
with contextlib.redirect_stdout(io.StringIO()):
    try:
        cli.main({args!r})
    except SystemExit as e:
        assert e.code == 0, e.code
"""


def test_top_level_help_loads_neither_torch_nor_numpy():
    assert _loaded_after(_help(["--help"])) == {"torch": False, "numpy": False}
    assert _loaded_after(_help(["--version"])) == {"torch": False, "numpy": False}


@pytest.mark.parametrize("command", ["run", "eval", "simulate", "demo", "show", "accumulate", "export"])
def test_subcommand_help_loads_no_torch(command):
    assert not _loaded_after(_help([command, "--help"]))["torch"]


def test_package_import_loads_no_torch():
    assert _loaded_after("import floxels_ext") == {"torch": False, "numpy": False}


@pytest.mark.parametrize("order", ["torch first", "floxels_ext first"])
def test_import_registers_the_ops_in_either_order(order):
    code = "import torch, floxels_ext" if order == "torch first" else "import floxels_ext, torch"
    r = _python(f"{code}\nprint(torch.ops.floxels.edt(torch.zeros(2, 2, 2, dtype=torch.bool), 1.0).shape)")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "torch.Size([2, 2, 2])"


def test_public_names_resolve():
    r = _python("import floxels_ext as f\nprint(f.estimate_flow.__name__, f.FloxelsConfig.__name__, "
                "f.ops.__name__, f.reference.__name__, f.lidar.__name__, 'estimate_sequence' in dir(f))")
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["estimate_flow", "FloxelsConfig", "floxels_ext.ops", "floxels_ext.reference",
                                "floxels_ext.lidar", "True"]
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        floxels_ext.not_a_name  # noqa: B018


def test_scene_names_of_the_parser_are_the_simulators():
    from floxels_ext.evaluation.sim.scenes import SCENES
    from floxels_ext.evaluation.simulate_cli import SCENE_NAMES

    assert list(SCENE_NAMES) == sorted(SCENES)
